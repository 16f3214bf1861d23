# Quickstart: `make demo` and `make test`. Both create .venv on first use and reuse it after.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
# Re-install only when the package's requirements change.
STAMP  := $(VENV)/.installed

.PHONY: install demo lint format test cluster-test clean-venv

install: $(STAMP)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# torch is pinned in the same pip call as everything else: unpinned, pip pulls a multi-GB CUDA build.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]" "torch==2.13.0"
	touch $(STAMP)

# The user's command on the embedded synthetic data: every category x fold, one MLflow run each.
demo: install
	$(BIN)/python -m meshseg.run model=cnn1d branches=3 split=5fold -m
	@echo "Runs are in the MLflow store mlruns/mlflow.db. Browse them with:"
	@echo "  $(BIN)/mlflow ui --backend-store-uri sqlite:///mlruns/mlflow.db   # then open http://127.0.0.1:5000"
	@echo "Their table (reports/synthetic/): $(BIN)/python -m meshseg.report experiments/synthetic.yaml"

# Lint and format check (ruff, configured in pyproject.toml); `make format` applies both.
lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: install
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

test: lint
	$(BIN)/python -m pytest --durations=10

# A one-node SLURM cluster and an MLflow server on PostgreSQL, started here as root (scripts/local_cluster.sh,
# apt-installing what is missing), a smoke sweep through hydra/launcher=slurm, and everything stopped again.
cluster-test: install
	$(BIN)/python -m pytest -m cluster tests/test_cluster.py

clean-venv:
	rm -rf $(VENV)
