"""Valid but unusual meshes (unused vertices, duplicated vertices, faces with a repeated or coincident
vertex) get finite features; a matrix that is not finite is refused naming the mesh, in every command."""

import numpy as np
import pytest
import trimesh
from omegaconf import OmegaConf

from meshseg import CONF_DIR
from meshseg.errors import MeshDataError
from meshseg.features.cache import FeatureCache
from meshseg.features.curvature import gc
from meshseg.features.sets import FeatureSet, check_finite


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(2)
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.fixture(scope="module")
def f800():
    return FeatureSet.from_config(OmegaConf.load(f"{CONF_DIR}/features/f800.yaml"))


def unusual(V, F):
    n = len(V)
    return {
        "unused vertices at the end": (np.vstack([V, [[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]]]), F),
        "a duplicated vertex in a zero-area face": (np.vstack([V, V[:1]]), np.vstack([F, [[0, n, 1]]])),
        "a repeated index": (V, np.vstack([F, [[0, 0, 1]]])),
    }


def test_gc_of_a_unit_sphere_ignores_unused_and_degenerate(sphere):
    V, F = sphere
    base = gc(V, F)[:, 0]
    assert abs(base.mean() - 1.0) < 0.05  # Gaussian curvature of the unit sphere
    for name, (v, f) in unusual(V, F).items():
        k = gc(v, f)[:, 0]  # the unused-vertex case raised IndexError ("area[used]") before
        assert np.isfinite(k).all(), name
        assert np.array_equal(k[: len(F)], base), name


def test_every_f800_column_is_finite_on_unusual_meshes(sphere, f800):
    V, F = sphere
    clean = f800.compute(V, F, "clean", FeatureCache(None))
    for name, (v, f) in unusual(V, F).items():
        X = f800.compute(v, f, name, FeatureCache(None))
        assert X.shape == (len(f), 800) and np.isfinite(X).all(), name
    X = f800.compute(*unusual(V, F)["unused vertices at the end"], "unused", FeatureCache(None))
    assert np.allclose(X, clean, atol=1e-5)  # vertices no face uses change nothing


def test_non_finite_features_are_refused_naming_the_mesh(f800):
    X = np.zeros((3, 800), np.float32)
    X[1, 5] = np.nan
    with pytest.raises(MeshDataError, match=r"meshes/7\.off: 1 faces have non-finite f800 features, in columns"):
        check_finite(X, f800, "meshes/7.off")
