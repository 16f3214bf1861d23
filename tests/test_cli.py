"""`python -m meshseg.data` and the Hydra config groups it composes."""

import os
import re
import subprocess
import sys

import pytest
from conftest import COSEG_ARCHIVE, REPO, require
from hydra import compose, initialize_config_dir

from meshseg import CONF_DIR
from meshseg.data.datasets import COSEG, PSB, Synthetic, build_dataset


def run(*overrides, cache):
    return subprocess.run(
        [sys.executable, "-m", "meshseg.data", f"paths.cache_dir={cache}", *overrides],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.parametrize("dataset, cls", [("synthetic", Synthetic), ("psb", PSB), ("coseg", COSEG)])
@pytest.mark.parametrize("split, protocol", [("loo", "LeaveOneOut"), ("5fold", "KFold"), ("fixed", "FixedSplit")])
def test_config_groups_compose(dataset, cls, split, protocol, tmp_path):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("data", overrides=[f"dataset={dataset}", f"split={split}", f"paths.cache_dir={tmp_path}"])
    assert cfg.dataset._target_ == f"{cls.__module__}.{cls.__name__}"
    assert cfg.split._target_ == f"meshseg.data.splits.{protocol}"
    if dataset != "synthetic":
        assert cfg.dataset.cache_dir == str(tmp_path)


def test_build_dataset_surfaces_the_real_error(tmp_path):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("data", overrides=["dataset=psb", f"dataset.root={tmp_path}/none"])
    with pytest.raises(ValueError, match="none: dataset.root does not exist"):
        build_dataset(cfg.dataset)


def test_summary_synthetic(tmp_path):
    r = run("dataset.meshes_per_category=2", cache=tmp_path)
    assert r.returncode == 0, r.stderr
    ds = Synthetic(meshes_per_category=2)
    faces = sum(m.n_faces for c in ds.categories for m in ds.meshes(c))
    lines = r.stdout.splitlines()
    assert [line.split()[:2] for line in lines[1:4]] == [["table", "2"], ["cup", "2"], ["figure", "2"]]
    assert lines[-1] == f"total: 6 meshes, {faces} faces"


def test_summary_coseg_archive(tmp_path):
    r = run("dataset=coseg", f"dataset.root={require(COSEG_ARCHIVE)}", cache=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[-1] == "total: 27 meshes, 224754 faces"


def test_summary_bad_root_is_one_clear_error(tmp_path):
    r = run("dataset=psb", f"dataset.root={tmp_path}/missing.tar.xz", cache=tmp_path)
    assert r.returncode == 1
    assert (
        r.stderr.strip() == f"error: {tmp_path}/missing.tar.xz: dataset.root does not exist "
        "(give a folder or an archive with dataset.root=PATH)"
    )


def test_help_lists_every_user_option_and_no_internal_budget():
    """`meshseg.run --help` is meshseg's own page (conf/hydra/help/meshseg.yaml): examples, then each
    config group with every option conf/ has, except the `budget/for_*` defaults the datasets pick."""
    from pathlib import Path

    r = subprocess.run(
        [sys.executable, "-m", "meshseg.run", "--help"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr[-2000:]
    head = r.stdout.split("== Composed config ==")[0]
    assert "== Examples ==" in head and "python -m meshseg.run model=cnn1d branches=3 split=5fold -m" in head
    assert "for_" not in head
    section = head.split("== Config groups (group=option) ==")[1].split("== Settings ==")[0]
    entries, current = {}, None
    for line in section.splitlines():  # a group's line and the more indented lines continuing it
        if re.match(r"  \w+:", line):
            current = line.split(":")[0].strip()
            entries[current] = line
        elif current and line.startswith("    "):
            entries[current] += line
    groups = sorted(p for p in Path(CONF_DIR).iterdir() if p.is_dir() and p.name != "hydra")
    assert sorted(entries) == [g.name for g in groups]
    for group in groups:
        options = {p.stem for p in group.glob("*.yaml") if not p.stem.startswith("for_")}
        assert options <= set(re.findall(r"\w+", entries[group.name])), (group.name, entries[group.name])


# --- one error contract: every command, one `error:` line, one exit status ---------------------------


@pytest.mark.parametrize(
    "command, message",
    [
        (["meshseg.run", "model.net.hidden=-1"], "error: model.net.hidden=-1 is not allowed"),
        (["meshseg.run", "branches=7"], "error: branches=7 is not allowed"),
        (["meshseg.report", "experiments/none.yaml"], "error: "),
        (["meshseg.results", "exprot"], "error: unknown action 'exprot'"),
        (["meshseg.predict", "run_id=x", "mesh=x.off", "out=x.npy", "budget=cpu"], "error: meshseg.predict takes"),
        (["meshseg.features", "mesh=none.off"], "error: mesh=FILE needs out=FILE.npy"),
        (
            ["meshseg.data", "dataset=psb", "dataset.root=/nonexistent"],
            "error: /nonexistent: dataset.root does not exist",
        ),
    ],
)
def test_every_command_ends_a_user_error_with_one_line_and_the_same_status(command, message, tmp_path):
    """A user's mistake ends any command with `error: ...` alone on stderr and cli.ERROR_EXIT; a network
    setting out of range is refused before any feature is computed or any store is made."""
    from meshseg.cli import ERROR_EXIT

    paths = [f"paths.{p}_dir={tmp_path}/{p}" for p in ("cache", "mlflow")]
    extra = paths if command[0] in ("meshseg.run", "meshseg.features") else []
    env = {**os.environ, "MESHSEG_LOG_DIR": str(tmp_path / "logs")}  # Hydra's run folders, not the checkout's logs/
    r = subprocess.run(
        [sys.executable, "-m", *command, *extra], cwd=REPO, capture_output=True, text=True, timeout=300, env=env
    )
    assert r.returncode == ERROR_EXIT == 1, r.stderr[-2000:]
    assert r.stderr.strip().startswith(message) and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert not (tmp_path / "cache").exists() and not (tmp_path / "mlflow").exists()  # no feature, no store
