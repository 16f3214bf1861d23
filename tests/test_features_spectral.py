"""Conformal factors (cf0, cf_smooth) and heat kernel signatures (hks, sihks)."""

import numpy as np
import pytest
import trimesh
from conftest import SHARED, require
from scipy.spatial.transform import Rotation
from scipy.stats import spearmanr

import meshseg.features.conformal  # noqa: F401  (registers cf0, cf_smooth)
import meshseg.features.heat_kernel as hk
from meshseg.features.operators import MeshOperators
from meshseg.features.registry import GROUPS

REFERENCE = SHARED / "data/reference/kalogerakis2010"


def group(name, V, F, **params):
    return GROUPS[name](np.asarray(V, np.float64), np.asarray(F, np.int64), **params)


def sphere(subdivisions=3, radius=1.0):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices), np.asarray(s.faces)


def bumpy_sphere():
    """A genus-0 shape without symmetries (so no repeated eigenvalues): a sphere with random bumps."""
    V, F = sphere(3)
    rng = np.random.default_rng(7)
    centres = rng.normal(size=(6, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    bumps = (rng.uniform(0.1, 0.4, 6) * np.exp(-(1 - V @ centres.T) / 0.05)).sum(axis=1)
    return V * (1 + bumps)[:, None] * [1.0, 0.8, 1.3], F


def cone():
    """A closed cone, apex at z = 3 over a flat disc at z = 0, subdivided so faces are small near the tip."""
    c = trimesh.creation.cone(radius=1.0, height=3.0, sections=32)
    V, F = trimesh.remesh.subdivide(c.vertices, c.faces)
    V, F = trimesh.remesh.subdivide(V, F)
    return np.asarray(V), np.asarray(F)


def moved(V, F, seed=0):
    """The same mesh after a rigid motion, a vertex renumbering, a face shuffle and a rotation of each
    face's corners; also returns the face permutation (row i of the result is face perm[i])."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    pv = rng.permutation(len(V))
    pf = rng.permutation(len(F))
    V2 = (V @ R.T + rng.normal(size=3) * 10)[pv]
    F2 = np.argsort(pv)[F][pf][:, [1, 2, 0]]
    return V2, F2, pf


ALL = ["cf0", "cf_smooth", "hks", "sihks"]


@pytest.mark.parametrize("name", ALL)
def test_shape_dtype_finite(name):
    V, F = bumpy_sphere()
    X = group(name, V, F)
    assert X.shape == (len(F), GROUPS[name].dim) and X.dtype == np.float32
    assert np.isfinite(X).all()
    assert X.std(axis=0).max() > 0


@pytest.mark.parametrize("name", ALL)
def test_rigid_motion_and_permutation_invariance(name):
    V, F = bumpy_sphere()
    X = group(name, V, F)
    V2, F2, perm = moved(V, F)
    Y = group(name, V2, F2)
    np.testing.assert_allclose(Y, X[perm], rtol=0, atol=1e-5 * np.abs(X).max())


# --- conformal factors ---------------------------------------------------------------------------


def test_cf_sphere_is_zero():
    V, F = sphere(3, radius=2.0)
    assert np.abs(group("cf0", V, F)).max() < 2e-3
    assert np.abs(group("cf_smooth", V, F)).max() < 2e-3
    # a non-spherical shape of the same tessellation is far from zero
    assert np.abs(group("cf0", *bumpy_sphere())).max() > 0.1


def test_cf_low_at_sharp_tip_high_on_flat_base():
    V, F = cone()
    c = V[F].mean(axis=1)
    tip, base = c[:, 2] > 2.4, np.abs(c[:, 2]) < 1e-9
    x0, xs = group("cf0", V, F), group("cf_smooth", V, F)
    assert x0[tip].mean() < x0[base].mean() - 0.2
    assert (xs[tip].mean(axis=0) < xs[base].mean(axis=0) - 0.02).all()


def test_cf_is_scale_invariant():
    V, F = bumpy_sphere()
    for name in ("cf0", "cf_smooth"):
        X = group(name, V, F)
        np.testing.assert_allclose(group(name, 3 * V, F), X, atol=1e-5 * np.abs(X).max())


def test_cf_solves_the_equation():
    from meshseg.features.conformal import angle_defect, conformal_factor, cotan_laplacian, vertex_areas

    V, F = bumpy_sphere()
    phi = conformal_factor(V, F)
    k = angle_defect(V, F)
    a = vertex_areas(V, F)
    target = k.sum() * a / a.sum()
    np.testing.assert_allclose(cotan_laplacian(V, F) @ phi, target - k, atol=1e-9)
    assert abs(np.dot(a, phi)) < 1e-9  # the gauge: zero area-weighted mean


def test_cf_components_solved_separately_and_degenerate_input_finite():
    (V1, F1), (V2, F2) = cone(), bumpy_sphere()
    # two components, an unreferenced vertex and a zero-area (collinear) face hanging on the cone
    i, j = F1[0, 0], F1[0, 1]
    V = np.vstack([V1, V2 + 5.0, [[9.0, 9.0, 9.0]], [(V1[i] + V1[j]) / 2]])
    mid = len(V) - 1
    F = np.vstack([F1, F2 + len(V1), [[i, mid, j]]])
    for name, cols in (("cf0", 1), ("cf_smooth", 5)):
        X = group(name, V, F)
        assert np.isfinite(X).all() and X.shape == (len(F), cols)
        # away from the degenerate face each component gets what it gets alone
        np.testing.assert_allclose(X[len(F1) : len(F1) + len(F2)], group(name, V2, F2), atol=1e-5)


def test_cf_smooth_is_zero_on_genus_one_unless_sphere_total():
    t = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=40, minor_sections=20)
    V, F = np.asarray(t.vertices), np.asarray(t.faces)
    assert np.abs(group("cf_smooth", V, F)).max() == 0.0
    assert np.abs(group("cf_smooth", V, F, target_total="sphere")).max() > 1e-6
    assert np.isfinite(group("cf0", V, F)).all()


def test_cf_smooth_parameters_change_values():
    V, F = bumpy_sphere()
    base = group("cf_smooth", V, F)
    for params in (
        {"taubin_pairs": 3},
        {"laplacian_mesh": "original"},
        {"taubin_mu": -0.6},
        {"taubin_weights": "uniform"},
    ):
        assert not np.allclose(group("cf_smooth", V, F, **params), base, atol=1e-6)
    with pytest.raises(ValueError, match="laplacian_mesh"):
        group("cf_smooth", V, F, laplacian_mesh="other")


# --- heat kernel signatures ----------------------------------------------------------------------


def test_sphere_spectrum():
    V, F = sphere(3, radius=1.0)
    lam, phi, _, n_comp = hk.laplace_beltrami_eigenpairs(V, F, 100)
    assert n_comp == 1 and lam[0] == 0.0
    # l(l+1) on the unit sphere with multiplicity 2l+1
    np.testing.assert_allclose(lam[1:4], 2.0, rtol=0.01)
    np.testing.assert_allclose(lam[4:9], 6.0, rtol=0.01)
    # eigenvectors are M-orthonormal: the constant one is 1/sqrt(area)
    np.testing.assert_allclose(np.abs(phi[:, 0]), 1 / np.sqrt(4 * np.pi), rtol=0.01)


def test_hks_sihks_constant_on_sphere():
    V, F = sphere(3)
    h, s = group("hks", V, F), group("sihks", V, F)
    assert (h.std(axis=0) / h.mean(axis=0)).max() < 0.01
    assert s.std(axis=0).max() < 0.01 * s[:, 0].mean()
    assert (
        np.all(np.diff(h.mean(axis=0)) <= 0) and h[:, 0].mean() > 2 * h[:, -1].mean()
    )  # heat leaves every point as t grows


def test_scale_by_3():
    V, F = bumpy_sphere()
    h, s = group("hks", V, F), group("sihks", V, F)
    h3, s3 = group("hks", 3 * V, F), group("sihks", 3 * V, F)
    np.testing.assert_allclose(s3, s, rtol=0, atol=1e-6 * np.abs(s).max())
    assert not np.allclose(h3, h, rtol=0.1)
    np.testing.assert_allclose(h3, h / 9, rtol=1e-4)  # values scale as 1/area, times follow


def test_sihks_columns_carry_signal():
    V, F = bumpy_sphere()
    s = group("sihks", V, F)
    rel = np.median(s / s[:, :1], axis=0)
    assert rel[0] == 1.0 and rel[99] > 1e-7 and rel[99] < rel[10]
    with pytest.raises(ValueError, match="n_tau"):
        group("sihks", V, F, n_tau=150)


def test_eigenpairs_shared_between_hks_and_sihks(monkeypatch):
    V, F = bumpy_sphere()
    calls = []
    real = hk._eigenpairs
    monkeypatch.setattr(hk, "_eigenpairs", lambda *a: calls.append(a[2]) or real(*a))
    ops = MeshOperators(V, F)
    h, s = GROUPS["hks"](V, F, ops=ops), GROUPS["sihks"](V, F, ops=ops)
    assert calls == [100]
    GROUPS["hks"](V, F, ops=ops, n_eigen=50)
    assert calls == [100, 50]
    # without operators each call solves on its own, to the same values
    np.testing.assert_array_equal(group("hks", V, F), h)
    np.testing.assert_array_equal(group("sihks", V, F), s)
    assert calls == [100, 50, 100, 100]


def test_heat_kernel_disconnected_small_and_degenerate():
    (V1, F1), (V2, F2) = sphere(2, radius=1.0), sphere(2, radius=2.0)
    V = np.vstack([V1, V2 + 5.0, [[9.0, 9.0, 9.0]]])  # plus an unreferenced vertex
    F = np.vstack([F1, F2 + len(V1)])
    lam, _, _, n_comp = hk.laplace_beltrami_eigenpairs(V, F, 40)
    assert n_comp == 2 and len(lam) == 41 and (lam[:2] == 0).all() and lam[2] > 0.1
    h = group("hks", V, F, n_eigen=40)
    # at the longest time only the constant modes are left: 1 / area of the face's own sphere
    np.testing.assert_allclose(h[len(F1) :, -1].mean(), 1 / (4 * np.pi * 4), rtol=0.05)
    np.testing.assert_allclose(h[: len(F1), -1].mean(), 1 / (4 * np.pi), rtol=0.05)
    assert np.isfinite(group("sihks", V, F, n_eigen=40)).all()
    # a mesh with fewer vertices than 2 n_eigen + 1 goes through the dense solver
    Vs, Fs = sphere(1)
    assert np.isfinite(group("hks", Vs, Fs)).all() and np.isfinite(group("sihks", Vs, Fs)).all()
    # a zero-area face
    V3 = np.vstack([V1, (V1[F1[0, 0]] + V1[F1[0, 1]]) / 2])
    F3 = np.vstack([F1, [[F1[0, 0], len(V1), F1[0, 1]]]])
    assert np.isfinite(group("hks", V3, F3)).all() and np.isfinite(group("sihks", V3, F3)).all()


# --- against Kalogerakis' reference features -----------------------------------------------------


def test_reference_relations_airplane(psb):
    """No reference column is a CF or an HKS, but both are known to track the average geodesic
    distance (AGD) on limbs: CF is low and mid-time HKS high at extremities, where AGD is high."""
    ref = np.load(require(REFERENCE / "Airplane_61.npz"))
    columns = [line.split("\t")[1] for line in (REFERENCE / "columns.txt").read_text().strip().splitlines()]
    agd = ref["X"][:, columns.index("AGD E[g]")]
    mesh = psb.load("Airplane", "61")
    faces = ref["faces"]
    cf = group("cf0", mesh.vertices, mesh.faces)[faces, 0]
    h = group("hks", mesh.vertices, mesh.faces)[faces, 50]
    assert spearmanr(cf, agd)[0] < -0.94  # measured -0.967
    assert spearmanr(h, agd)[0] > 0.94  # measured 0.970
