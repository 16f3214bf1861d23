import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
PSB_ARCHIVE = SHARED / "data/psb/LabeledDB_new.tar.xz"
COSEG_ARCHIVE = SHARED / "data/coseg-fragment/coseg-fragment.tar.xz"
SPLIT_FILE = SHARED / "data/splits/shapepfcn_splits.txt"
#: the system's temporary folder, read before the session fixture below moves tempfile's (and TMPDIR) into
#: pytest's root-only folder, where daemons running as their own users (mysql, postgres) cannot reach
SYSTEM_TEMP = tempfile.gettempdir()


def require(path: Path) -> Path:
    """Shared data is beside every checkout in CI: there its absence is a failure, elsewhere a skip."""
    if not path.exists():
        if os.environ.get("CI"):
            pytest.fail(f"{path} missing: CI must have ../shared beside the clone")
        pytest.skip(f"{path} not available")
    return path


@pytest.fixture(autouse=True)
def no_store_in_the_checkout():
    """A test that opens the default store (`mlruns/` where it runs) writes into the checkout: fail it by name.
    (Where a checkout already holds a store of its own, the check cannot tell and is skipped.)"""
    store = REPO / "mlruns"
    had = store.exists()
    yield
    if not had and store.exists():
        import shutil

        shutil.rmtree(store, ignore_errors=True)
        pytest.fail(f"this test made {store}: give it a store of its own (paths.mlflow_dir or MESHSEG_MLFLOW_DIR)")


@pytest.fixture(scope="session", autouse=True)
def temporary_files_in_the_session(tmp_path_factory):
    """Temporary folders the tests' libraries leave behind (MLflow's artifact downloads make one a call and never
    remove it) land in the session's folder, which pytest prunes, not in /tmp; subprocesses too (TMPDIR)."""
    folder = tmp_path_factory.mktemp("tempfiles")
    with pytest.MonkeyPatch.context() as m:
        m.setattr(tempfile, "tempdir", str(folder))
        m.setenv("TMPDIR", str(folder))
        yield folder


#: fixtures of the tests that train folds (a store of runs, or a run of their own): those tests run first
HEAVY = {"smoke_store", "store"}


def pytest_collection_modifyitems(items):
    """The tests that train folds first, the rest after, each in file order: pytest-xdist hands tests out one
    at a time (--maxschedchunk=1 in pyproject), so the two workers share the long ones and the short ones
    fill the end, where one worker would otherwise wait for the other's last long test."""
    items.sort(key=lambda item: not HEAVY & set(getattr(item, "fixturenames", ())))


def shared_dir(tmp_path_factory) -> Path:
    """The session's folder common to pytest-xdist's workers (the session's own without xdist)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextmanager
def once(tmp_path_factory, name: str):
    """Make something once for all of the session's workers: the first to get here makes it (the body runs
    under a file lock) while the others wait."""
    from filelock import FileLock

    with FileLock(str(shared_dir(tmp_path_factory) / f"{name}.lock")):
        yield


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory) -> Path:
    """The session's feature cache, one for all workers (its files are written atomically): a mesh's features
    are computed once per session, an archive unpacked once."""
    path = shared_dir(tmp_path_factory) / "cache"
    path.mkdir(exist_ok=True)
    return path


@pytest.fixture(scope="session")
def psb(cache_dir, tmp_path_factory):
    from meshseg.data.datasets import PSB

    with once(tmp_path_factory, "psb"):  # the archive unpacked by one worker
        return PSB(str(require(PSB_ARCHIVE)), str(cache_dir))


@pytest.fixture(scope="session")
def coseg(cache_dir, tmp_path_factory):
    from meshseg.data.datasets import COSEG

    with once(tmp_path_factory, "coseg"):
        return COSEG(str(require(COSEG_ARCHIVE)), str(cache_dir))


# --- a small MLflow store made by a budget=smoke sweep (report, notebooks, mlflow ui) -------------------

#: run overrides of the smoke store: experiments/synthetic.yaml on 5 meshes per category, 2 folds,
#: three cheap feature groups, budget=smoke (the same overrides make the report find its runs); one torch
#: thread, as the two test workers already keep both cores busy (threads are no part of a run's identity)
SMOKE = [
    "dataset.meshes_per_category=5",
    "features.groups=[curvature,pca,gc]",
    "features.name=local",
    "budget=smoke",
    "split.k=2",
    "trainer.threads=1",
]


def smoke_env(root: Path, cache_dir: Path) -> dict:
    """Environment pointing meshseg at one store under `root` and the session's feature cache."""
    return {
        **os.environ,
        "MESHSEG_CACHE_DIR": str(cache_dir),
        "MESHSEG_MLFLOW_DIR": str(root / "mlruns"),
        "MESHSEG_LOG_DIR": str(root / "logs"),
    }


@pytest.fixture(scope="session")
def smoke_store(tmp_path_factory, cache_dir) -> Path:
    """Every run of experiments/synthetic.yaml (3 columns x 3 sets x 2 folds = 18) at budget=smoke.
    Returns the store's folder (mlflow.db, artifacts/); tests that change it work on a copy. pytest-xdist's
    workers share one: the first to need it builds it while the others wait."""
    import shutil

    root = shared_dir(tmp_path_factory) / "smoke"
    with once(tmp_path_factory, "smoke"):
        if not (root / "built").exists():
            shutil.rmtree(root, ignore_errors=True)  # a build that failed half-way is not reused
            _build_smoke_store(root, cache_dir)
            (root / "built").touch()
    return root / "mlruns"


def _build_smoke_store(root: Path, cache_dir: Path) -> None:
    import subprocess
    import sys

    root.mkdir(parents=True)
    env = smoke_env(root, cache_dir)
    # the two sweeps side by side (one store, as concurrent sweeps share one): their runs are mostly
    # single-threaded Python, so two cores make the store faster (69 s against 91 s, measured once)
    sweeps = [
        subprocess.Popen(
            [sys.executable, "-m", "meshseg.run", "-m", *SMOKE, *sweep],
            cwd=REPO,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for sweep in (["model=cnn1d", "branches=1,3"], ["model=rf"])
    ]
    for p in sweeps:
        _, err = p.communicate(timeout=900)
        assert p.returncode == 0, err[-3000:]


# --- a hand-made two-mesh L-PSB folder and manifests over it (predictions columns, study manifests) -----------

# mesh 1: two triangles of area 1/2 and 2 (a 1 x 1 and a 2 x 2 right triangle); mesh 2: three unit triangles
MESH1 = "OFF\n6 2 0\n0 0 0\n1 0 0\n0 1 0\n5 0 0\n7 0 0\n5 2 0\n3 0 1 2\n3 3 4 5\n"
MESH2 = "OFF\n9 3 0\n" + "".join(f"{x} 0 0\n{x + 1} 0 0\n{x} 1 0\n" for x in (0, 3, 6)) + "3 0 1 2\n3 3 4 5\n3 6 7 8\n"


def tiny_psb(root: Path) -> Path:
    """An L-PSB-shaped folder root/db: category Tiny, meshes 1 (faces head, body) and 2 (head, head, body)."""
    d = root / "db/Tiny"
    d.mkdir(parents=True)
    (d / "1.off").write_text(MESH1)
    (d / "1_labels.txt").write_text("head\n1\nbody\n2\n")
    (d / "2.off").write_text(MESH2)
    (d / "2_labels.txt").write_text("head\n1 2\nbody\n3\n")
    return root / "db"


def tiny_manifest(root: Path, name: str, columns: list[dict], sets: list[dict], average=None, **keys) -> Path:
    """Manifest `name` (root/<name>.yaml) on tiny_psb(root), leave-one-out: one group g of `sets` with an
    average row published as `average` in every column."""
    doc = {
        "name": name,
        "title": "t",
        "overrides": ["dataset=psb", f"dataset.root={root / 'db'}", "split=loo"],
        "columns": columns,
        "groups": [{"name": "g", "average": "Average", "published_average": [average] * len(columns), "sets": sets}],
        **keys,
    }
    path = root / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path
