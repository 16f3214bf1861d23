"""The paper's feature sets end to end: layout, f600 ⊂ f800, face-order equivariance, finiteness on
real L-PSB meshes, and the features command."""

import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO
from hydra import compose, initialize_config_dir

from meshseg import CONF_DIR
from meshseg.data.datasets import Synthetic
from meshseg.features.cache import FeatureCache
from meshseg.features.geometry import face_adjacency
from meshseg.features.rings import ring_means
from meshseg.features.sets import FeatureSet

SETS = {"f800": 800, "f600": 600, "cf0": 1, "cf1": 1, "cf0_1": 2, "cf1_5": 5, "cf0_5": 6}


def feature_set(name: str) -> FeatureSet:
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return FeatureSet.from_config(compose("features", overrides=[f"features={name}"]).features)


@pytest.fixture(scope="module")
def small_mesh():
    return Synthetic(categories=["figure"], meshes_per_category=1, min_faces=1500, max_faces=2500).load("figure", "0")


@pytest.fixture(scope="module")
def f800_small(small_mesh, tmp_path_factory):
    cache = FeatureCache(tmp_path_factory.mktemp("fcache"))
    return cache, feature_set("f800").compute(small_mesh.vertices, small_mesh.faces, small_mesh.content_hash, cache)


@pytest.mark.parametrize("name, dim", SETS.items())
def test_set_widths(name, dim):
    fs = feature_set(name)
    assert fs.dim == dim and len(fs.columns) == dim


def test_f800_layout_follows_the_paper():
    fs = feature_set("f800")
    # the paper's order and widths: Kalogerakis' 593 columns (columns.txt), then CF0, CF1..5, GC, HKS, SIHKS
    widths = dict(curvature=64, pca=48, shape_context=270, agd=15, sdf=72, dms=24, spin_images=100)
    widths |= dict(cf0=1, cf_smooth=5, gc=1, hks=100, sihks=100)
    ends = np.cumsum(list(widths.values())).tolist()
    assert fs.layout == {g: (e - w, e) for (g, w), e in zip(widths.items(), ends)}
    assert fs.layout["shape_context"] == (112, 382) and fs.layout["sihks"] == (700, 800)
    ref = REPO.parent / "shared/data/reference/kalogerakis2010/columns.txt"
    if ref.exists():
        names = [line.split("\t", 1)[-1].strip() for line in ref.read_text().splitlines() if line.strip()]
        assert fs.columns[:593] == names


def test_f600_is_the_first_600_columns_of_f800(small_mesh, f800_small):
    cache, X800 = f800_small
    assert X800.shape == (small_mesh.n_faces, 800) and X800.dtype == np.float32
    assert np.isfinite(X800).all()
    X600 = feature_set("f600").compute(small_mesh.vertices, small_mesh.faces, small_mesh.content_hash, cache)
    np.testing.assert_array_equal(X600, X800[:, :600])
    cf = feature_set("cf0_1").compute(small_mesh.vertices, small_mesh.faces, small_mesh.content_hash, cache)
    np.testing.assert_array_equal(cf, X800[:, 593:595])


def test_face_permutation_permutes_rows_only(small_mesh, f800_small):
    _, X = f800_small
    perm = np.random.default_rng(3).permutation(small_mesh.n_faces)
    Xp = feature_set("f800").compute(small_mesh.vertices, small_mesh.faces[perm], "permuted")
    scale = np.abs(X).max(axis=0) + 1e-6
    err = np.abs(Xp - X[perm]) / scale
    assert err.max() < 2e-3, f"worst column {feature_set('f800').columns[err.max(axis=0).argmax()]}: {err.max():.2e}"


def test_multiscale_of_real_features(small_mesh, f800_small):
    _, X = f800_small
    x1, x2, x3 = ring_means(X, small_mesh.faces, 3)
    assert x2.shape == X.shape and np.isfinite(x3).all()
    # averaging over growing neighbourhoods smooths: neighbouring-face differences shrink
    pairs = np.array(face_adjacency(small_mesh.faces).nonzero()).T
    rough = [np.abs(x[pairs[:, 0]] - x[pairs[:, 1]]).mean() for x in (x1, x2, x3)]
    assert rough[0] > rough[1] > rough[2]


SMALL_PSB = ["Bearing/353", "Bird/257", "FourLeg/398", "Glasses/52", "Hand/200", "Human/9", "Octopus/125"]


@pytest.mark.parametrize("mesh_path", SMALL_PSB)
def test_f800_finite_on_real_meshes(psb, mesh_path):
    """The smallest mesh of seven L-PSB categories (zero-area faces and several components among them)."""
    category, mesh_id = mesh_path.split("/")
    mesh = psb.load(category, mesh_id)
    X = feature_set("f800").compute(mesh.vertices, mesh.faces, mesh.content_hash)
    bad = ~np.isfinite(X).all(axis=0)
    assert not bad.any(), f"non-finite columns: {np.array(feature_set('f800').columns)[bad][:5]}"
    # constant columns: the original's always-zero AGD column, and spin-image bins no surface reaches
    constant = {c for c, sd in zip(feature_set("f800").columns, X.std(axis=0)) if sd == 0}
    assert {c for c in constant if not c.startswith("SI ")} == {"AGD unused(0)"}


def run(*args):
    return subprocess.run(
        [sys.executable, "-m", "meshseg.features", *args], cwd=REPO, capture_output=True, text=True, timeout=600
    )


def test_cli_one_mesh_writes_f800(psb, tmp_path):
    out = tmp_path / "x.npy"
    r = run(f"mesh={psb.root / 'Airplane' / '74.off'}", f"out={out}", "features=f800", f"paths.cache_dir={tmp_path}")
    assert r.returncode == 0, r.stderr[-2000:]
    X = np.load(out)
    assert X.shape == (10084, 800) and X.dtype == np.float32 and np.isfinite(X).all()
    mesh = psb.load("Airplane", "74")
    np.testing.assert_allclose(
        X[:, 599], feature_set("f800").compute(mesh.vertices, mesh.faces, "x")[:, 599], rtol=1e-5
    )


def test_cli_dataset_run_caches(tmp_path):
    args = [
        "dataset=synthetic",
        "dataset.meshes_per_category=1",
        "features=cf0_5",
        "workers=2",
        f"paths.cache_dir={tmp_path}",
    ]
    r = run(*args)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = [line.split(" - ", 1)[-1] for line in r.stdout.strip().splitlines()]  # Hydra's log format
    assert [line.split(":")[0] for line in lines[:3]] == ["features 1/3", "features 2/3", "features 3/3"]
    last = lines[-1]
    ds = Synthetic(meshes_per_category=1)
    faces = sum(ds.load(c, "0").n_faces for c in ds.categories)
    assert last.startswith(f"features: 3 meshes, {faces} faces, ") and last.endswith(" faces/s")
    assert len(list((tmp_path / "features" / "cf0").glob("*.npz"))) == 3
    assert len(list((tmp_path / "features" / "cf_smooth").glob("*.npz"))) == 3


def test_cli_errors(tmp_path):
    r = run(f"mesh={tmp_path}/none.off", f"out={tmp_path}/x.npy")
    assert r.returncode == 1 and "none.off: cannot read" in r.stderr
    r = run("dataset=synthetic", "category=boat")
    assert r.returncode == 1 and "has no category 'boat'" in r.stderr
