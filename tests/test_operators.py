"""One object per mesh (`operators.MeshOperators`): the groups of a feature set share its eigen-solve
(hks, sihks) and its Dijkstra run (agd, shape_context); another mesh or parameter value never does."""

import numpy as np
import pytest
import trimesh
from omegaconf import OmegaConf

from meshseg.features import agd
from meshseg.features import heat_kernel as hk
from meshseg.features.cache import FeatureCache
from meshseg.features.operators import MeshOperators
from meshseg.features.registry import GROUPS
from meshseg.features.sets import FeatureSet

# small and light: cheap solves, few Dijkstra sources
LIGHT = {
    "agd": {"n_samples": 48},
    "shape_context": {"n_samples": 48, "n_near_samples": 96},
}


def bumpy(seed):
    """A 320-face icosphere with radial noise; another seed, another mesh of the same shape."""
    m = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(seed)
    return m.vertices * (1 + 0.1 * rng.standard_normal((len(m.vertices), 1))), np.asarray(m.faces, np.int64)


def feature_set(groups=("hks", "sihks", "agd", "shape_context"), **params):
    cfg = {"name": "t", "groups": list(groups), "params": {**LIGHT, **params}}
    return FeatureSet.from_config(OmegaConf.create(cfg))


@pytest.fixture
def counted(monkeypatch):
    """Records the n_eigen of every eigen-solve and the sources of every sampled-geodesics Dijkstra run."""
    calls = {"eigen": [], "dijkstra": []}
    solve, dijkstra = hk._eigenpairs, agd.dijkstra

    def counted_solve(V, F, n_eigen):
        calls["eigen"].append(n_eigen)
        return solve(V, F, n_eigen)

    def counted_dijkstra(graph, *args, indices, **kw):
        calls["dijkstra"].append(len(indices))
        return dijkstra(graph, *args, indices=indices, **kw)

    monkeypatch.setattr(hk, "_eigenpairs", counted_solve)
    monkeypatch.setattr(agd, "dijkstra", counted_dijkstra)
    return calls


def unshared(fs, V, F):
    """The set's matrix from group calls that share nothing."""
    return np.concatenate([GROUPS[e.group](V, F, **fs.params.get(e.group, {})) for e in fs.entries], axis=1)


def test_one_solve_and_one_dijkstra_per_mesh(counted):
    V, F = bumpy(0)
    fs = feature_set()
    X = fs.compute(V, F, "mesh0")
    assert counted == {"eigen": [100], "dijkstra": [48]}
    # the same values as four separate calls, which solve twice and run Dijkstra twice
    np.testing.assert_array_equal(X, unshared(fs, V, F))
    assert counted == {"eigen": [100, 100, 100], "dijkstra": [48, 48, 48]}


def test_another_mesh_never_shares(counted):
    (V0, F0), (V1, F1) = bumpy(0), bumpy(1)
    fs = feature_set()
    X0 = fs.compute(V0, F0, "mesh0")
    X1 = fs.compute(V1, F1, "mesh1")
    assert counted == {"eigen": [100, 100], "dijkstra": [48, 48]}
    assert not np.allclose(X0, X1)
    np.testing.assert_array_equal(X1, unshared(fs, V1, F1))  # mesh 1's own values, none of mesh 0's
    # the same mesh again, in a new call: a new object, computed again (the memo dies with the call)
    np.testing.assert_array_equal(fs.compute(V0, F0, "mesh0"), X0)
    assert counted["eigen"][2:] == [100, 100, 100] and len(counted["dijkstra"]) == 5


def test_memo_is_per_parameter_value(counted):
    V, F = bumpy(0)
    fs = feature_set(hks={"n_eigen": 40})  # sihks keeps n_eigen=100
    X = fs.compute(V, F, "mesh0")
    assert sorted(counted["eigen"]) == [40, 100]
    np.testing.assert_array_equal(X, unshared(fs, V, F))
    counted["eigen"].clear(), counted["dijkstra"].clear()
    fs = feature_set(("agd", "shape_context"), shape_context={"n_samples": 32, "n_near_samples": 96})
    fs.compute(V, F, "mesh0")
    assert sorted(counted["dijkstra"]) == [32, 48]
    ops = MeshOperators(V, F)
    assert ops.eigenpairs(40) is ops.eigenpairs(40) and len(ops.eigenpairs(40)[0]) == 40
    assert len(ops.eigenpairs(30)[0]) == 30
    assert counted["eigen"] == [40, 30]


def test_only_groups_not_on_disk_compute(counted, tmp_path):
    V, F = bumpy(0)
    cache = FeatureCache(tmp_path)
    X = feature_set(("hks",)).compute(V, F, "mesh0", cache)
    assert counted["eigen"] == [100]
    Y = feature_set(("hks", "sihks")).compute(V, F, "mesh0", cache)  # hks from disk, sihks solves
    assert counted["eigen"] == [100, 100]
    np.testing.assert_array_equal(Y[:, :100], X)
    feature_set(("hks", "sihks")).compute(V, F, "mesh0", cache)
    assert counted["eigen"] == [100, 100]  # all on disk: nothing computed


def test_operators_of_another_mesh_are_refused():
    (V0, F0), (V1, F1) = bumpy(0), bumpy(1)
    ops = MeshOperators(V0, F0, key="mesh0")
    assert ops.describes(V0, F0) and ops.describes(V0.copy(), F0.copy()) and not ops.describes(V1, F1)
    assert not ops.describes(V0[:-1], F0)
    with pytest.raises(ValueError, match="another mesh"):
        GROUPS["agd"](V1, F1, ops=ops)
    assert "mesh0" in repr(ops)


def test_shared_is_not_a_parameter():
    for name in ("hks", "sihks", "agd", "shape_context"):
        assert GROUPS[name].shared and "ops" not in GROUPS[name].defaults
    assert not GROUPS["pca"].shared
    with pytest.raises(ValueError, match=r"no parameters \['ops'\]"):
        GROUPS["hks"].params({"ops": None})
