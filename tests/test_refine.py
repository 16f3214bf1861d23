"""Graph-cut refinement (paper §3.5): the concavity angle, the weights, the cut, and refine_labels."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from meshseg.data import synthetic
from meshseg.data.mesh import Mesh
from meshseg.features.geometry import face_centers, per_face_normals
from meshseg.metrics import area_weighted_accuracy
from meshseg.refine import Argmax, GraphCutAGD, GraphCutClassic, build_refinement, graphcut, refine_labels
from meshseg.refine.search import choose

METHODS = ("none", "graphcut_classic", "graphcut_agd")

CONF = Path(__file__).resolve().parents[1] / "conf" / "refine"


def conf(name: str, **overrides):
    cfg = OmegaConf.load(CONF / f"{name}.yaml")
    for k, v in overrides.items():
        cfg[k] = v
    return cfg


def hinge(turn: float) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles on the edge (0,0,0)-(1,0,0): face 0 flat in y > 0 with normal +z, face 1
    continuing into y < 0 and turned by |turn| radians about the edge: downwards for turn > 0 (a
    convex fold, like a box's corner at pi/2), upwards for turn < 0 (a concave one)."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -np.cos(turn), -np.sin(turn)]], float)
    return V, np.array([[0, 1, 2], [1, 0, 3]])


def step(k: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A stair step extruded along y, k x k squares per panel: panel 0 the top (z = 0, normal +z),
    panel 1 the riser (x = 1, normal +x), panel 2 the lower tread (z = -1, normal +z). The
    top/riser edge is a 90-degree convex ridge, the riser/tread edge a 90-degree concave valley.
    Returns V, F and each face's panel."""
    s = np.linspace(0, 3, 3 * k + 1)
    y = np.linspace(0, 1, k + 1)
    x = np.clip(s, 0, 1) + np.clip(s - 2, 0, 1)
    z = -np.clip(s - 1, 0, 1)
    V = np.array([[x[i], yj, z[i]] for i in range(len(s)) for yj in y])
    idx = np.arange(len(V)).reshape(len(s), len(y))
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    panel = np.r_[np.repeat(np.arange(3), k * k), np.repeat(np.arange(3), k * k)]
    top = panel == 0
    if per_face_normals(V, F)[top][:, 2].mean() < 0:  # outward = +z on the top
        F = F[:, ::-1]
    return V, F, panel


# ----------------------------------------------------------------------------------------------
# the dihedral angle and the weights, by hand


def test_dihedral_edges_signed_fold_angles():
    for turn in (np.pi / 2, -np.pi / 2, np.pi / 3, -np.pi / 6):
        pairs, angle, length = graphcut.dihedral_edges(*hinge(turn))
        assert pairs.tolist() == [[0, 1]]
        assert angle[0] == pytest.approx(turn)  # > 0 convex, < 0 concave
        assert length[0] == pytest.approx(1.0)
    _, angle, _ = graphcut.dihedral_edges(*hinge(0.0))  # flat
    assert abs(angle[0]) < 1e-12
    V, F = hinge(-np.pi / 3)
    F[1] = F[1, ::-1]  # one face wound the other way: the angle is still pi/3, not 2 pi/3
    _, angle, _ = graphcut.dihedral_edges(V, F)
    assert abs(angle[0]) == pytest.approx(np.pi / 3)


def test_edge_theta_concave_cheap_convex_dear():
    angle = np.array([-np.pi / 2, np.pi / 2, 0.0, -np.pi])
    theta = graphcut.edge_theta(angle, convex_factor=0.08, theta_eps=1e-3)
    np.testing.assert_allclose(theta, [np.pi / 2, 0.08 * np.pi / 2, 1e-3 * np.pi, np.pi])
    cost = graphcut.concavity_cost(theta)
    np.testing.assert_allclose(cost, [np.log(2), -np.log(0.04), -np.log(1e-3), 0.0], atol=1e-12)
    assert cost[1] > cost[0]  # a 90-degree ridge costs more than a 90-degree valley
    # convex_factor 1: a ridge is a valley of the same angle
    assert graphcut.edge_theta(angle, convex_factor=1.0)[1] == pytest.approx(np.pi / 2)


def test_classic_and_agd_weight_formulas():
    theta = np.array([np.pi / 2, np.pi / 4, np.pi])
    np.testing.assert_allclose(
        graphcut.classic_weights(theta, np.array([2.0, 1.0, 5.0])), [2 * np.log(2), np.log(4), 0.0]
    )
    f = np.array([[0.0, 0.0], [0.3, 0.4], [3.0, 4.0], [3.0, 4.0]])  # jumps 0.5 and 5
    pairs = np.array([[0, 1], [1, 2], [2, 3]])
    w = graphcut.agd_weights(theta, f, pairs, omega=1.0)
    # log 2 - 0.5; log 4 - ||(2.7, 3.6)|| = log 4 - 4.5 < 0 -> clamped to 0; 0 - 0 = 0
    np.testing.assert_allclose(w, [np.log(2) - 0.5, 0.0, 0.0])
    assert (w >= 0).all()


def test_normalize_features_per_column_std():
    f = np.c_[np.arange(5.0), 100 * np.arange(5.0), np.zeros(5)]
    g = graphcut.normalize_features(f, "std")
    np.testing.assert_allclose(g[:, 0], g[:, 1])  # scale of a column does not matter
    np.testing.assert_allclose(g.std(axis=0), [1, 1, 0])  # constant column contributes nothing
    np.testing.assert_array_equal(graphcut.normalize_features(f, "none"), f)
    with pytest.raises(ValueError, match="feature normalisation"):
        graphcut.normalize_features(f, "l2")


def test_degenerate_faces_give_finite_weights():
    # a zero-area face (collinear) and a zero-length edge (duplicate vertex)
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [1, 0, 0], [1, -1, 0]], float)
    F = np.array([[0, 1, 2], [1, 0, 3], [0, 4, 1], [4, 0, 5]])
    pairs, angle, length = graphcut.dihedral_edges(V, F)
    theta = graphcut.edge_theta(angle)
    f = np.zeros((len(F), 15))
    for w in (graphcut.classic_weights(theta, length), graphcut.agd_weights(theta, f, pairs, 2.0)):
        assert np.isfinite(w).all() and (w >= 0).all()
    mesh = Mesh(V, F)
    P = np.full((len(F), 2), 0.5)
    P[0] = [0.9, 0.1]
    for name in ("graphcut_classic", "graphcut_agd"):
        labels = refine_labels(mesh, P, conf(name), f)
        assert labels.shape == (len(F),) and set(labels) <= {0, 1}


# ----------------------------------------------------------------------------------------------
# the cut


def brute_force(P: np.ndarray, pairs: np.ndarray, w: np.ndarray, lam: float) -> dict:
    """The energy of every labelling of a small problem."""
    return {
        lab: graphcut.potts_energy(np.array(lab), P, pairs, w, lam, 1e-6)
        for lab in itertools.product(range(P.shape[1]), repeat=len(P))
    }


def test_alpha_expansion_matches_brute_force_on_small_problems():
    rng = np.random.default_rng(0)
    pairs = np.array([[0, 1], [1, 2], [0, 2]])  # three faces around a vertex
    checked = 0
    for _ in range(40):
        P = rng.dirichlet(np.ones(2), size=3)
        w = rng.uniform(0, 2, size=3)
        lam = rng.uniform(0.2, 3)
        energies = brute_force(P, pairs, w, lam)
        best, second = sorted(energies.values())[:2]
        if second - best < 1e-3:  # a near tie: integer rounding may pick either
            continue
        got = graphcut.alpha_expansion(P, pairs, w, lam, eps=1e-6)
        assert tuple(got) == min(energies, key=energies.get)  # two labels: expansion is exact
        checked += 1
    assert checked >= 30


def test_alpha_expansion_three_labels_hand_case():
    # face 1 alone prefers label 1, but both its neighbours want label 2 and the edges are strong
    P = np.array([[0.1, 0.2, 0.7], [0.25, 0.5, 0.25], [0.1, 0.1, 0.8]])
    pairs = np.array([[0, 1], [1, 2]])
    w = np.array([1.0, 1.0])
    energies = brute_force(P, pairs, w, 1.0)
    assert min(energies, key=energies.get) == (2, 2, 2)
    # E(2,2,2) = -log .7 - log .25 - log .8; E(2,1,2) = -log .7 - log .5 - log .8 + 2
    assert energies[(2, 2, 2)] == pytest.approx(-np.log(0.7 * 0.25 * 0.8))
    assert energies[(2, 1, 2)] == pytest.approx(-np.log(0.7 * 0.5 * 0.8) + 2)
    np.testing.assert_array_equal(graphcut.alpha_expansion(P, pairs, w, 1.0), [2, 2, 2])
    # weak edges: face 1 keeps its own preference
    np.testing.assert_array_equal(graphcut.alpha_expansion(P, pairs, w, 0.2), [2, 1, 2])


def test_lambda_zero_is_the_argmax():
    rng = np.random.default_rng(1)
    V, F, y = synthetic.generate("cup", 0)
    mesh = Mesh(V, F, y, synthetic.PART_NAMES["cup"])
    P = rng.dirichlet(np.ones(2), size=len(F))
    f = rng.normal(size=(len(F), 15))
    for name in ("graphcut_classic", "graphcut_agd"):
        np.testing.assert_array_equal(refine_labels(mesh, P, conf(name, lam=0.0), f), P.argmax(1))
    # the cut itself: edge weights that round to nothing leave the argmax start unchanged
    pairs, angle, length = graphcut.dihedral_edges(V, F)
    w = graphcut.classic_weights(graphcut.edge_theta(angle), length)
    np.testing.assert_array_equal(graphcut.alpha_expansion(P, pairs, w, 1e-12), P.argmax(1))
    np.testing.assert_array_equal(graphcut.alpha_expansion(P, pairs, w, 0.0), P.argmax(1))


@pytest.fixture(scope="module")
def noisy_cup():
    """A synthetic cup (body / handle), its AGD features and seeded noisy probabilities."""
    from meshseg.features.agd import average_geodesic_distance

    V, F, y = synthetic.generate("cup", 3)
    mesh = Mesh(V, F, y, synthetic.PART_NAMES["cup"], id="3", source="synthetic:cup/3")
    rng = np.random.default_rng(0)
    logits = 1.0 * np.eye(2)[y] + rng.normal(size=(len(F), 2))
    P = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    return mesh, P, average_geodesic_distance(V, F, n_samples=64)


@pytest.mark.parametrize("name", ["graphcut_classic", "graphcut_agd"])
def test_refinement_repairs_noisy_labels(noisy_cup, name):
    mesh, P, agd = noisy_cup
    raw = area_weighted_accuracy(P.argmax(1), mesh.labels, mesh.face_areas)
    refined = area_weighted_accuracy(refine_labels(mesh, P, conf(name), agd), mesh.labels, mesh.face_areas)
    assert raw < 0.85  # the noise is real
    assert refined > 0.95 and refined > raw + 0.1


@pytest.mark.parametrize("name", ["graphcut_classic", "graphcut_agd"])
def test_ambiguous_panel_is_cut_at_the_valley_not_the_ridge(name):
    V, F, panel = step()
    pairs, angle, length = graphcut.dihedral_edges(V, F)
    between = np.sort(panel[pairs], axis=1)
    ridge, valley = (between == [0, 1]).all(axis=1), (between == [1, 2]).all(axis=1)
    np.testing.assert_allclose(angle[ridge], np.pi / 2)
    np.testing.assert_allclose(angle[valley], -np.pi / 2)
    # AGD-like features that change as fast across the ridge as across the valley: arc length
    c = face_centers(V, F)
    f = np.select([panel == 0, panel == 1, panel == 2], [c[:, 0], 1 - c[:, 2], 1 + c[:, 0]])[:, None]
    cfg = conf(name)
    theta = graphcut.edge_theta(angle, cfg.convex_factor, cfg.theta_eps)
    w = (
        graphcut.classic_weights(theta, length)
        if name == "graphcut_classic"
        else graphcut.agd_weights(theta, graphcut.normalize_features(f, cfg.feature_norm), pairs, cfg.omega)
    )
    assert w[ridge].min() > 0 and w[ridge].min() > w[valley].max()  # a ridge is never free, and dearer
    mesh = Mesh(V, F, source="step")
    for sure in (0, 1):  # whichever label the top carries, the riser follows it
        P = np.full((len(F), 2), 0.5)
        P[panel == 0] = np.eye(2)[sure] * 0.8 + 0.1
        P[panel == 2] = np.eye(2)[1 - sure] * 0.8 + 0.1
        labels = refine_labels(mesh, P, cfg, f)
        assert (labels[panel == 0] == sure).all() and (labels[panel == 2] == 1 - sure).all()
        assert (labels[panel == 1] == sure).all()  # cut along the concave valley


# ----------------------------------------------------------------------------------------------
# refine_labels' contract


def test_agd_features_missing_or_misshapen_name_the_mesh(noisy_cup):
    mesh, P, agd = noisy_cup
    cfg = conf("graphcut_agd")
    with pytest.raises(ValueError, match=r"synthetic:cup/3.*needs the mesh's AGD features"):
        refine_labels(mesh, P, cfg)
    for bad in (agd[:-1], agd[:, 0], agd[:, :0]):
        with pytest.raises(ValueError, match=r"synthetic:cup/3.*AGD features must be \(faces="):
            refine_labels(mesh, P, cfg, bad)
    with pytest.raises(ValueError, match=r"synthetic:cup/3.*NaN"):
        refine_labels(mesh, P, cfg, np.where(np.arange(len(agd))[:, None] == 5, np.nan, agd))
    with pytest.raises(ValueError, match=r"synthetic:cup/3.*probabilities must be"):
        refine_labels(mesh, P[:-1], conf("graphcut_classic"))
    # the classic term needs no features
    assert refine_labels(mesh, P, conf("graphcut_classic")).shape == (mesh.n_faces,)


def test_methods_and_configs():
    for name, cls in zip(METHODS, (Argmax, GraphCutClassic, GraphCutAGD)):
        assert OmegaConf.load(CONF / f"{name}.yaml").name == name
        r = build_refinement(conf(name))
        assert type(r) is cls and r.name == name
        assert r.needs == (("agd",) if name == "graphcut_agd" else ())  # what the run must compute for it
    assert build_refinement(conf("graphcut_agd", omega=0.5, lam=3)).omega == 0.5
    mesh = Mesh(*hinge(-np.pi / 2))
    P = np.array([[0.6, 0.4], [0.3, 0.7]])
    np.testing.assert_array_equal(refine_labels(mesh, P, conf("none")), [0, 1])
    with pytest.raises(ValueError, match="refine=crf: the config names no class"):
        refine_labels(mesh, P, OmegaConf.create({"name": "crf"}))
    with pytest.raises(ValueError, match=r"refine=graphcut_classic: .*GraphCutClassic does not take .*'omega'"):
        build_refinement(conf("graphcut_classic", omega=1.0))


@pytest.mark.parametrize(
    "name, key, value",
    [
        ("graphcut_agd", "lam", -1),
        ("graphcut_agd", "eps", 1.5),
        ("graphcut_agd", "omega", -0.1),
        ("graphcut_agd", "feature_norm", "l2"),
        ("graphcut_classic", "length_norm", "max"),
        ("graphcut_classic", "theta_eps", 0),
        ("graphcut_classic", "n_iter", 0),
    ],
)
def test_a_bad_setting_is_refused_when_the_refinement_is_built(name, key, value):
    with pytest.raises(ValueError, match=rf"refine.{key}={value} is not allowed with refine={name}: it must be"):
        build_refinement(conf(name, **{key: value}))


# --- refine.search: settings chosen on held-out meshes (meshseg/refine/search.py) ------------------------


def test_search_chooses_the_best_grid_point_and_the_first_of_equals(noisy_cup):
    mesh, P, agd = noisy_cup
    refinement = build_refinement(conf("graphcut_agd", search={"lam": [0.0, 2.0], "omega": [2.0, 0.0]}))
    acc = lambda m, labels: area_weighted_accuracy(labels, m.labels, m.face_areas)  # noqa: E731
    found = choose(refinement, [mesh, mesh], [P, P], [agd, agd], acc)
    assert [(r["lam"], r["omega"]) for r in found.table] == [(0.0, 2.0), (0.0, 0.0), (2.0, 2.0), (2.0, 0.0)]
    raw = acc(mesh, P.argmax(1))
    assert found.table[0]["score"] == found.table[1]["score"] == raw  # lam 0: the argmax, whatever omega
    assert (
        found.settings["lam"] == 2.0 and found.score > raw + 0.1 and found.score == max(r["score"] for r in found.table)
    )
    assert found.chosen.lam == 2.0 and found.chosen.search is None and found.chosen.omega == found.settings["omega"]
    assert found.table[2]["per_mesh"] == [found.table[2]["score"]] * 2
    same = choose(refinement, [mesh], [P], [agd], lambda m, labels: 0.5)  # all equal: the grid's first
    assert same.settings == {"lam": 0.0, "omega": 2.0}
    # the config hash sorts a grid's keys, so the grid's order must not depend on how the YAML wrote them
    swapped = build_refinement(conf("graphcut_agd", search={"omega": [2.0, 0.0], "lam": [0.0, 2.0]}))
    assert [r["per_mesh"] for r in choose(swapped, [mesh], [P], [agd], acc).table] == [
        r["per_mesh"][:1] for r in found.table
    ]
    tie = choose(swapped, [mesh], [P], [agd], lambda m, labels: 0.5).settings
    assert list(tie.items()) == [("lam", 0.0), ("omega", 2.0)]  # walked lam first, as written the other way


def test_a_search_logs_its_grid_size_and_each_point(noisy_cup, caplog):
    mesh, P, agd = noisy_cup
    refinement = build_refinement(conf("graphcut_agd", search={"lam": [0.0, 2.0], "omega": [2.0]}))
    with caplog.at_level("INFO", logger="meshseg.refine.search"):
        choose(refinement, [mesh], [P], [agd], lambda m, labels: 0.5)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "refine.search: 2 grid points on 1 held-out meshes"
    assert lines[1].startswith("refine.search 1/2 {'lam': 0.0, 'omega': 2.0}: 0.5000")
    assert lines[2].startswith("refine.search 2/2 {'lam': 2.0, 'omega': 2.0}: 0.5000") and len(lines) == 3


@pytest.mark.parametrize(
    "grid, message",
    [
        ({"lamb": [1.0]}, r"refine.search.lamb is not allowed with refine=graphcut_agd: it takes convex_factor, eps"),
        ({"feature_norm": ["std", "none"]}, r"refine.search.feature_norm is not allowed with refine=graphcut_agd"),
        ({"lam": []}, r"refine.search.lam=\[\] is not allowed: it must be a non-empty list of numbers"),
        ({"lam": 2.0}, r"refine.search.lam=2.0 is not allowed: it must be a non-empty list of numbers"),
        ({"lam": ["2"]}, r"refine.search.lam=\['2'\] is not allowed: it must be a non-empty list of numbers"),
        ([1.0, 2.0], r"refine.search=\[1.0, 2.0\] is not allowed: give settings with lists of values"),
        (True, r"refine.search=True is not allowed: give settings with lists of values"),
        (
            {"lam": [1.0, -1.0]},
            r"refine.search \{'lam': -1.0\}: refine.lam=-1.0 is not allowed with refine=graphcut_agd",
        ),
        ({}, r"refine.search=\{\} is not allowed: give settings with lists of values"),
        # issue 48, 8: 10^6 points were built (1.3 GB) and searched for days without a word
        (
            {"lam": [float(i) for i in range(1000)], "omega": [float(i) for i in range(1000)]},
            r"refine.search has 1,000,000 points \(1000 lam x 1000 omega\): at most 100 are allowed",
        ),
        ({"lam": [float(i) for i in range(101)]}, r"refine.search has 101 points \(101 lam\): at most 100"),
    ],
)
def test_a_bad_search_grid_is_refused_when_the_refinement_is_built(grid, message):
    with pytest.raises(ValueError, match=message):
        build_refinement(conf("graphcut_agd", search=grid))
