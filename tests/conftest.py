import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
PSB_ARCHIVE = SHARED / "data/psb/LabeledDB_new.tar.xz"
COSEG_ARCHIVE = SHARED / "data/coseg-fragment/coseg-fragment.tar.xz"
SPLIT_FILE = SHARED / "data/splits/shapepfcn_splits.txt"


def require(path: Path) -> Path:
    """Shared data is beside every checkout in CI: there its absence is a failure, elsewhere a skip."""
    if not path.exists():
        if os.environ.get("CI"):
            pytest.fail(f"{path} missing: CI must have ../shared beside the clone")
        pytest.skip(f"{path} not available")
    return path


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="session")
def psb(cache_dir):
    from meshseg.data.datasets import PSB

    return PSB(str(require(PSB_ARCHIVE)), str(cache_dir))


@pytest.fixture(scope="session")
def coseg(cache_dir):
    from meshseg.data.datasets import COSEG

    return COSEG(str(require(COSEG_ARCHIVE)), str(cache_dir))
