"""scripts/rerefine.py: a store's logged probabilities refined again at other settings, no training."""

from __future__ import annotations

import subprocess
import sys

from conftest import REPO, SMOKE, smoke_env


def rerefine(store, cache_dir, *args) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "scripts/rerefine.py", *args, f"tracking.uri=sqlite:///{store}/mlflow.db"]
    return subprocess.run(cmd, cwd=REPO, env=smoke_env(store.parent, cache_dir), capture_output=True, text=True)


def test_rerefine_replays_the_logged_labels_and_lam_0_is_the_argmax(smoke_store, cache_dir):
    out = rerefine(
        smoke_store, cache_dir, *SMOKE, "dataset=synthetic", "split=5fold", "model=rf", "category=cup", "lam=[0,2,64]"
    )
    assert out.returncode == 0, out.stderr
    rows = [line.split("|")[1:-1] for line in out.stdout.splitlines() if line.startswith("| ") and "---" not in line]
    header, meshes, mean = rows[0], rows[1:-1], rows[-1]
    assert [c.strip() for c in header] == ["mesh", "fold", "argmax", "logged", "lam=0", "lam=2", "lam=64"]
    assert len(meshes) == 5 and {m[1].strip() for m in meshes} == {"0", "1"}  # 5 meshes, 2 folds of the smoke split
    for m in meshes:
        argmax, logged, lam0, lam2, lam64 = (float(c) for c in m[2:])
        assert lam0 == argmax  # at lam = 0 the cut returns the argmax
        assert lam2 == logged  # the configured lam (2) replays the run's labels
    # a cut 32 times stronger labels some mesh differently from the configured one: the setting reaches the cut
    assert any(float(m[6]) != float(m[5]) for m in meshes)
    assert "5 meshes" in mean[0]


def test_rerefine_refuses_a_setting_the_refinement_does_not_have(smoke_store, cache_dir):
    out = rerefine(
        smoke_store, cache_dir, *SMOKE, "dataset=synthetic", "split=5fold", "model=rf", "category=cup", "gamma=[1,2]"
    )
    assert out.returncode == 1
    assert (
        out.stderr.strip().splitlines()[-1].startswith("error: gamma is not a numeric setting of refine=graphcut_agd")
    )


def test_rerefine_names_a_store_that_is_not_there(tmp_path, cache_dir):
    out = rerefine(tmp_path / "none", cache_dir, *SMOKE, "dataset=synthetic", "split=5fold", "category=cup", "lam=[1]")
    assert out.returncode == 1 and out.stderr.strip().splitlines()[-1].startswith("error: ")
    assert str(tmp_path / "none") in out.stderr and not (tmp_path / "none").exists()  # said, and no store made
