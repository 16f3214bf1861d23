# Quickstart: `make demo` and `make test`. Both create .venv on first use and reuse it after.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
# Re-install only when the package's requirements change.
STAMP  := $(VENV)/.installed

.PHONY: install demo ui lint format test cluster-test ui-test clean-venv

install: $(STAMP)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch is pinned in the same pip call as everything else: unpinned, pip pulls a multi-GB CUDA build.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]" "torch==2.13.0"
	touch $(STAMP)

# The worked example: every run of experiments/synthetic.yaml (1D CNN 3B and 1B, RF; 3 synthetic categories x
# 5 folds) through meshseg.reproduce, which skips what the store has and ends by printing the table.
demo: install
	$(BIN)/python -m meshseg.reproduce experiments/synthetic.yaml
	@echo "Browse the runs: make ui"

# The MLflow UI on the default store, at the runs table (the URL is printed first); Ctrl-C stops it.
ui: install
	$(BIN)/python -m meshseg.ui

# Lint and format check (ruff, configured in pyproject.toml); `make format` applies both.
lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: install
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

# Two pytest-xdist workers (TEST_WORKERS=0: one process); they build the tests' smoke store once, together.
TEST_WORKERS ?= 2
test: lint
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --durations=10

# Races of processes and kills mid-run (pytest -m processes): slow by nature, so outside `make test`; CI runs them
# right after it.
process-test: install
	$(BIN)/python -m pytest -n $(TEST_WORKERS) -m processes --durations=5

# A one-node SLURM cluster and an MLflow server on PostgreSQL, started here as root (scripts/local_cluster.sh,
# apt-installing what is missing), a smoke sweep through hydra/launcher=slurm, and everything stopped again.
cluster-test: install
	$(BIN)/python -m pytest -m cluster tests/test_cluster.py

# The MLflow UI driven in headless Chromium (Debian's chromium and chromium-driver, apt-installed as root when
# missing): the runs table, a run's source, dataset, train/loss curve and a render.
ui-test: install
	command -v chromium >/dev/null && command -v chromedriver >/dev/null || \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null)
	$(BIN)/python -m pytest -m browser tests/test_mlflow_ui.py

clean-venv:
	rm -rf $(VENV)
