"""Feature infrastructure: rings, sets and their layout, the cache. Uses small registered test groups."""

import numpy as np
import pytest
from omegaconf import OmegaConf

from meshseg.features import geometry
from meshseg.features.cache import FeatureCache
from meshseg.features.registry import GROUPS, register
from meshseg.features.rings import ring_means, step_matrix
from meshseg.features.sets import FeatureSet

# A strip of 6 triangles in a row: face i shares an edge with i-1 and i+1 only.
#   0---2---4---6
#    \ / \ / \ / \     (zig-zag of vertices 0..7)
#     1---3---5---7
STRIP_V = np.array([[i, i % 2, 0.0] for i in range(8)], float)
STRIP_F = np.array([[i, i + 1, i + 2] for i in range(6)])

CALLS = {"n": 0}


def _centre_x(V, F, *, scale=1.0):
    CALLS["n"] += 1
    return np.c_[geometry.face_centers(V, F)[:, 0] * scale, np.arange(len(F))]


if "test_centre" not in GROUPS:
    register("test_centre", dim=2, columns=["cx", "index"])(_centre_x)
    register("test_area", dim=1)(lambda V, F: geometry.face_areas(V, F)[:, None])


def test_strip_adjacency():
    a = geometry.face_adjacency(STRIP_F).toarray()
    expected = np.zeros((6, 6))
    for i in range(5):
        expected[i, i + 1] = expected[i + 1, i] = 1
    np.testing.assert_array_equal(a, expected)


def test_ring_means_hand_computed():
    X = np.arange(6, dtype=np.float32)[:, None] * 10
    x1, x2, x3 = ring_means(X, STRIP_F, 3)
    np.testing.assert_array_equal(x1, X)
    # N^2 = self and edge neighbours; N^3 = up to two steps
    np.testing.assert_allclose(x2[:, 0], [5, 10, 20, 30, 40, 45])
    np.testing.assert_allclose(x3[:, 0], [10, 15, 20, 30, 35, 40])
    assert x2.dtype == np.float32


def test_vertex_steps_reach_further():
    s_edge, s_vertex = step_matrix(STRIP_F, "edge"), step_matrix(STRIP_F, "vertex")
    assert s_edge[0].nnz == 2 and s_vertex[0].nnz == 3  # face 0 shares vertex 2 with face 2
    with pytest.raises(ValueError, match="unknown ring adjacency 'diag'"):
        step_matrix(STRIP_F, "diag")


def small_set(**params):
    return FeatureSet.from_config(
        OmegaConf.create({"name": "t", "groups": ["test_area", "test_centre[1:2]", "test_centre"], "params": params})
    )


def test_set_layout_and_columns():
    fs = small_set()
    assert fs.dim == 4
    assert fs.layout == {"test_area": (0, 1), "test_centre[1:2]": (1, 2), "test_centre": (2, 4)}
    assert fs.columns == ["test_area[0]", "index", "cx", "index"]
    X = fs.compute(STRIP_V, STRIP_F, "strip")
    np.testing.assert_allclose(X[:, 1], np.arange(6))
    np.testing.assert_allclose(X[:, 2], geometry.face_centers(STRIP_V, STRIP_F)[:, 0], rtol=1e-6)


@pytest.mark.parametrize(
    "groups, params, problem",
    [
        (["nope"], {}, "unknown feature group 'nope'"),
        (["test_centre[0:3]"], {}, "columns 0:3 outside 0:2"),
        (["test_centre[x]"], {}, "bad feature set entry"),
        (["test_centre"], {"test_centre": {"radius": 2}}, "has no parameters ['radius']; it has ['scale']"),
    ],
)
def test_set_errors(groups, params, problem):
    with pytest.raises(ValueError, match=__import__("re").escape(problem)):
        FeatureSet.from_config(OmegaConf.create({"name": "t", "groups": groups, "params": params}))


def test_cache_hit_param_change_and_corruption(tmp_path):
    cache = FeatureCache(tmp_path)
    fs = small_set()
    CALLS["n"] = 0
    X = fs.compute(STRIP_V, STRIP_F, "strip", cache)
    assert CALLS["n"] == 1  # test_centre computed once although used twice
    files = sorted((tmp_path / "features").rglob("*.npz"))
    assert [f.parent.name for f in files] == ["test_area", "test_centre"]
    np.testing.assert_array_equal(fs.compute(STRIP_V, STRIP_F, "strip", cache), X)
    assert CALLS["n"] == 1  # served from disk

    # a changed parameter recomputes that group only, into a new file
    X2 = small_set(test_centre={"scale": 2.0}).compute(STRIP_V, STRIP_F, "strip", cache)
    assert CALLS["n"] == 2
    np.testing.assert_allclose(X2[:, 2], 2 * X[:, 2])
    assert len(list((tmp_path / "features" / "test_centre").glob("*.npz"))) == 2
    assert len(list((tmp_path / "features" / "test_area").glob("*.npz"))) == 1

    # a corrupt file (flipped byte) and a truncated one are recomputed, not trusted
    path = cache.path("strip", GROUPS["test_centre"], {"scale": 1.0})
    raw = bytearray(path.read_bytes())
    at = bytes(raw).find(X[:, 2:].astype(np.float32).tobytes())  # the stored array's data
    assert at > 0
    raw[at + 5] ^= 0xFF
    path.write_bytes(bytes(raw))
    np.testing.assert_array_equal(fs.compute(STRIP_V, STRIP_F, "strip", cache), X)
    assert CALLS["n"] == 3
    path.write_bytes(path.read_bytes()[:50])
    np.testing.assert_array_equal(fs.compute(STRIP_V, STRIP_F, "strip", cache), X)
    assert CALLS["n"] == 4
    np.testing.assert_array_equal(fs.compute(STRIP_V, STRIP_F, "strip", cache), X)
    assert CALLS["n"] == 4  # the rewritten file is good again
    assert not list((tmp_path / "features").rglob("*.tmp"))
    # another mesh never shares an entry
    fs.compute(STRIP_V * 2, STRIP_F, "other", cache)
    assert CALLS["n"] == 5


def test_group_shape_is_checked():
    register("test_bad", dim=3)(lambda V, F: np.zeros((len(F), 2)))
    try:
        with pytest.raises(RuntimeError, match="returned shape"):
            GROUPS["test_bad"](STRIP_V, STRIP_F)
    finally:
        del GROUPS["test_bad"]


SEEN_OPS = []


def _shared_x(V, F, *, ops=None):
    SEEN_OPS.append(ops)
    return geometry.face_centers(V, F)[:, :1]


if "test_shared_a" not in GROUPS:
    register("test_shared_a", dim=1, shared=True)(_shared_x)
    register("test_shared_b", dim=1, shared=True)(_shared_x)


def test_shared_groups_get_one_operators_object_per_mesh(tmp_path):
    fs = FeatureSet.from_config(
        OmegaConf.create({"name": "t", "groups": ["test_shared_a", "test_centre", "test_shared_b"]})
    )
    SEEN_OPS.clear()
    fs.compute(STRIP_V, STRIP_F, "strip", FeatureCache(tmp_path))
    a, b = SEEN_OPS
    assert a is b and a.key == "strip" and a.V is STRIP_V and a.F is STRIP_F  # through the cache's get
    fs.compute(STRIP_V * 2, STRIP_F, "other")
    assert SEEN_OPS[2] is SEEN_OPS[3] and SEEN_OPS[2] is not a and SEEN_OPS[2].key == "other"
    GROUPS["test_shared_a"](STRIP_V, STRIP_F)  # a direct call: the function computes on its own
    assert SEEN_OPS[4] is None
    assert GROUPS["test_shared_a"].defaults == {} and not GROUPS["test_centre"].shared


def test_shared_group_needs_ops_keyword():
    with pytest.raises(ValueError, match="needs the keyword ops=None"):
        register("test_no_ops", dim=1, shared=True)(lambda V, F: np.zeros((len(F), 1)))
    assert "test_no_ops" not in GROUPS


def test_every_single_byte_flip_of_a_cache_entry_is_recomputed_or_read_right(tmp_path):
    """Issue 26, defect 6: flips in the zip central directory raised NotImplementedError ('zip file version'),
    in the npy header tokenize.TokenError. Any failure to read an entry is a miss: never a crash, never a
    wrong array."""
    cache = FeatureCache(tmp_path)
    fs = small_set()
    X = fs.compute(STRIP_V, STRIP_F, "strip", cache)
    path = cache.path("strip", GROUPS["test_centre"], {"scale": 1.0})
    good = path.read_bytes()
    for at in range(len(good)):
        raw = bytearray(good)
        raw[at] ^= 0xFF
        path.write_bytes(bytes(raw))
        np.testing.assert_array_equal(fs.compute(STRIP_V, STRIP_F, "strip", cache), X, err_msg=f"byte {at}")


def test_a_cache_entry_that_cannot_be_written_or_vanishes_is_a_miss(tmp_path, monkeypatch):
    """Defect 6: a folder at a cache file's path, and a temporary file deleted before it is renamed (a user
    clearing the cache while a fold runs), crashed the run; now the values are returned and not cached."""
    import os

    cache = FeatureCache(tmp_path)
    fs = small_set()
    want = fs.compute(STRIP_V, STRIP_F, "strip", FeatureCache(None))
    path = cache.path("strip", GROUPS["test_centre"], {"scale": 1.0})
    path.mkdir(parents=True)  # a folder where the entry goes
    np.testing.assert_array_equal(fs.compute(STRIP_V, STRIP_F, "strip", cache), want)
    path.rmdir()
    real = os.replace

    def vanished(src, dst):
        os.unlink(src)  # deleted between writing and renaming
        return real(src, dst)

    monkeypatch.setattr(os, "replace", vanished)
    np.testing.assert_array_equal(fs.compute(STRIP_V, STRIP_F, "strip", cache), want)
    assert not path.exists() and not list((tmp_path / "features").rglob("*.tmp"))
