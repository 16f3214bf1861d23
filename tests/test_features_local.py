"""Local surface features: curvature (64), PCA (48), GC (1)."""

import heapq

import conftest
import numpy as np
import pytest
import trimesh

from meshseg.features import geometry
from meshseg.features.curvature import CURVATURE_COLUMNS, CurvatureSettings, curvature, gc, principal_curvatures
from meshseg.features.geometry import clip_outliers, kalogerakis_normalize, smoothed_face_normals
from meshseg.features.neighbourhoods import face_neighbours, geodesic_balls
from meshseg.features.pca import PCA_COLUMNS, PCASettings, covariance_eigenvalues, pca
from meshseg.features.registry import GROUPS

REFERENCE = conftest.SHARED / "data/reference/kalogerakis2010"


def blob(subdivisions=3, seed=0):
    """An irregular closed surface: a noisy ellipsoid (no symmetry, so no ties anywhere)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    rng = np.random.default_rng(seed)
    V = m.vertices * (1 + 0.05 * rng.standard_normal((len(m.vertices), 1))) * [1.0, 0.7, 0.5]
    return np.asarray(V), np.asarray(m.faces, dtype=np.int64)


def tube(radius=1.0, length=4.0, around=96, along=48):
    """An open cylinder with near-equilateral triangles (rows offset by half a step)."""
    t = np.linspace(0, length, along + 1)
    rows = []
    for i, z in enumerate(t):
        a = 2 * np.pi * (np.arange(around) + 0.5 * (i % 2)) / around
        rows.append(np.c_[radius * np.cos(a), radius * np.sin(a), np.full(around, z)])
    V = np.vstack(rows)
    F = []
    for i in range(along):
        lo, hi = i * around, (i + 1) * around
        for j in range(around):
            j1 = (j + 1) % around
            if i % 2 == 0:
                F += [[lo + j, lo + j1, hi + j], [lo + j1, hi + j1, hi + j]]
            else:
                F += [[lo + j, lo + j1, hi + j1], [lo + j, hi + j1, hi + j]]
    return V, np.array(F, dtype=np.int64)


def grid(n=30, size=1.0):
    """A flat triangulated square in the plane z = 0."""
    x, y = np.meshgrid(np.linspace(0, size, n + 1), np.linspace(0, size, n + 1))
    V = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    i = i.ravel()
    F = np.r_[np.c_[i, i + 1, i + n + 2], np.c_[i, i + n + 2, i + n + 1]]
    return V, F.astype(np.int64)


def random_rigid(seed=1):
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q, np.array([3.0, -7.0, 11.0])


# --- shape, dtype, columns --------------------------------------------------------------------


@pytest.mark.parametrize("name, dim", [("curvature", 64), ("pca", 48), ("gc", 1)])
def test_groups_registered_with_shape_float32_finite(name, dim):
    V, F = blob()
    g = GROUPS[name]
    X = g(V, F)
    assert g.dim == dim and len(g.columns) == dim
    assert X.shape == (len(F), dim) and X.dtype == np.float32
    assert np.isfinite(X).all()
    assert (X.std(axis=0) > 0).all()  # every column carries information on a generic shape


def test_column_names_match_the_reference_file():
    names = (REFERENCE / "columns.txt").read_text().split("\n")
    names = [line.split("\t", 1)[-1].strip() for line in names if line.strip()]
    assert CURVATURE_COLUMNS == names[:64]
    assert PCA_COLUMNS == names[64:112]


def test_degenerate_mesh_stays_finite():
    """Two components, an open boundary, a non-manifold edge, a zero-area face, a duplicate face."""
    V1, F1 = blob(2)
    V2, F2 = tube(0.3, 1.0, 24, 6)
    V = np.vstack([V1, V2 + [3.0, 0, 0]])
    F = np.vstack([F1, F2 + len(V1)])
    extra = len(V)
    V = np.vstack([V, V[F[0, 0]] + [0, 0, 0.2], (V[F[5, 0]] + V[F[5, 1]]) / 2])
    F = np.vstack([F, [F[0, 0], F[0, 1], extra], [F[5, 0], F[5, 1], extra + 1], F[7]])  # fin, zero area, duplicate
    for name in ("curvature", "pca", "gc"):
        X = GROUPS[name](V, F)
        assert X.shape[0] == len(F) and np.isfinite(X).all(), name


def test_bad_radii_count_is_an_error():
    V, F = blob(2)
    with pytest.raises(ValueError, match="4 radii"):
        curvature(V, F, CurvatureSettings(radii=(0.01, 0.02)))
    with pytest.raises(ValueError, match="4 radii"):
        pca(V, F, PCASettings(radii=(0.1, 0.2, 0.3)))


# --- invariances -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["curvature", "pca", "gc"])
def test_rigid_motion_and_face_order_invariance(name):
    V, F = blob()
    X = GROUPS[name](V, F)
    scale = np.abs(X).max(axis=0) + 1e-12
    R, t = random_rigid()
    Xr = GROUPS[name](V @ R.T + t, F)
    np.testing.assert_allclose(Xr / scale, X / scale, atol=1e-4)
    perm = np.random.default_rng(2).permutation(len(F))
    Xp = GROUPS[name](V, np.roll(F[perm], 1, axis=1))  # new face order and first vertex
    np.testing.assert_allclose(Xp / scale, X[perm] / scale, atol=1e-4)


def test_scale_invariance_of_kalogerakis_groups_and_gc_scaling():
    V, F = blob()
    for name in ("curvature", "pca"):
        X, Xs = GROUPS[name](V, F), GROUPS[name](2.5 * V, F)
        np.testing.assert_allclose(Xs, X, rtol=1e-4, atol=1e-5 * np.abs(X).max())
    np.testing.assert_allclose(gc(2.5 * V, F), gc(V, F) / 2.5**2, rtol=1e-5)


# --- analytic shapes ---------------------------------------------------------------------------


def test_gc_sphere_plane():
    r = 2.0
    m = trimesh.creation.icosphere(subdivisions=4, radius=r)
    V, F = np.asarray(m.vertices), np.asarray(m.faces, dtype=np.int64)
    import igl

    assert igl.gaussian_curvature(V, F).sum() == pytest.approx(4 * np.pi)
    K = gc(V, F)[:, 0]
    area = geometry.face_areas(V, F)
    assert np.median(K) == pytest.approx(1 / r**2, rel=0.05)
    assert (area @ K) / area.sum() == pytest.approx(1 / r**2, rel=0.02)
    Vg, Fg = grid(20)
    interior = ~np.isin(Fg, np.flatnonzero((Vg[:, 0] % 1 == 0) | (Vg[:, 1] % 1 == 0))).any(axis=1)
    assert np.abs(gc(Vg, Fg)[interior]).max() < 1e-8


def test_principal_curvatures_sphere_cylinder_torus():
    radii = (0.05, 0.1, 0.2)
    # unit sphere: k1 = k2 = 1 (positive for outward normals)
    m = trimesh.creation.icosphere(subdivisions=4)
    k = principal_curvatures(np.asarray(m.vertices), np.asarray(m.faces), radii)
    np.testing.assert_allclose(k, 1.0, atol=0.03)
    # unit cylinder: k1 = 1 around, k2 = 0 along (faces away from the open ends)
    V, F = tube(1.0, 2.0, 128, 40)
    k = principal_curvatures(V, F, radii)
    mid = np.abs(geometry.face_centers(V, F)[:, 2] - 1.0) < 0.5
    np.testing.assert_allclose(k[mid, :, 0], 1.0, atol=0.03)
    np.testing.assert_allclose(k[mid, :, 1], 0.0, atol=0.03)
    # torus R = 1, r = 0.3: outer equator k = (1/r, 1/(R + r)), inner k = (1/r, -1/(R - r))
    m = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=160, minor_sections=60)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    k = principal_curvatures(V, F, (0.05,))[:, 0]
    c = geometry.face_centers(V, F)
    rho = np.hypot(c[:, 0], c[:, 1])
    outer, inner = rho > 1.28, rho < 0.72
    np.testing.assert_allclose(k[outer].mean(axis=0), [1 / 0.3, 1 / 1.3], rtol=0.05)
    np.testing.assert_allclose(k[inner].mean(axis=0), [1 / 0.3, -1 / 0.7], rtol=0.05)


def test_curvature_columns_on_a_sphere():
    m = trimesh.creation.icosphere(subdivisions=4, radius=3.0)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    X = curvature(V, F)
    k = 1 / np.linalg.norm(kalogerakis_normalize(V, F), axis=1).mean()  # 1 / radius in the 2010 units
    for s in range(4):
        cols = dict(zip(CURVATURE_COLUMNS[16 * s : 16 * s + 16], X[:, 16 * s : 16 * s + 16].T))
        for name in ("k1", "k2", "K1", "K2", "H", "|k1|", "|H|"):
            np.testing.assert_allclose(cols[f"CUR s{s} {name}"], k, rtol=0.03)
        np.testing.assert_allclose(cols[f"CUR s{s} K"], k * k, rtol=0.06)
        np.testing.assert_allclose(cols[f"CUR s{s} k1-k2"], 0, atol=0.03 * k)


def test_pca_flat_plane_has_no_normal_spread():
    V, F = grid(40)
    X = pca(V, F, PCASettings(clip=False))
    for s in range(4):
        l0, l1, l2 = X[:, 12 * s], X[:, 12 * s + 1], X[:, 12 * s + 2]
        assert np.abs(l0).max() < 1e-6 * l2.max()
        assert (l1 > 0).all() and (l1 <= l2 + 1e-9).all()


def test_covariance_eigenvalues_formula():
    rng = np.random.default_rng(3)
    c, a = rng.standard_normal((50, 3)), rng.random(50)
    total = 7.0
    G = np.hstack(
        [
            a[:, None],
            a[:, None] * c,
            a[:, None] * np.stack([c[:, i] * c[:, j] for i, j in [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]], 1),
        ]
    )
    m = (a @ c) / total  # the original's mean: divided by the whole mesh's area
    C = ((c - m) * a[:, None]).T @ (c - m) / total
    expected = np.sqrt(np.linalg.eigvalsh(C))
    np.testing.assert_allclose(covariance_eigenvalues(G.sum(0), total), expected, rtol=1e-10)


# --- operators ---------------------------------------------------------------------------------


def _reference_traversal(mesh, src, R, min_faces, check_normals):
    """The 2010 code's traverseFaces, literally: a Dijkstra that takes a face when popped. `mesh`: (face
    neighbours, dual edge lengths, face normals)."""
    nbr, length, n = mesh
    dist, seen, taken = {src: 0.0}, set(), []
    heap = [(0.0, src)]
    while heap:
        d, f = heapq.heappop(heap)
        if f in seen:
            continue
        seen.add(f)
        if (not check_normals or n[f] @ n[src] > 0) or len(taken) <= min_faces:
            taken.append(f)
        else:
            continue
        if d > R and len(taken) > min_faces:
            continue
        for g, w in zip(nbr[f], length[f]):
            if g >= 0 and g not in seen and dist.get(g, np.inf) > d + w:
                dist[g] = d + w
                heapq.heappush(heap, (d + w, g))
    return set(taken)


@pytest.mark.parametrize("min_faces, check_normals", [(3, True), (9, False)])
def test_geodesic_balls_match_the_original_traversal(min_faces, check_normals):
    V, F = blob(3, seed=4)
    V = kalogerakis_normalize(V * [1.0, 1.0, 0.1], F)  # a thin disc: the far side is near the rim
    c, n = geometry.face_centers(V, F), smoothed_face_normals(V, F)
    nbr, length = neighbours = face_neighbours(V, F)
    radii = (0.02, 0.1, 0.25)
    got = {}
    for rows, J, masks in geodesic_balls(
        c, neighbours, radii, max_neighbors=400, min_faces=min_faces, normals=n if check_normals else None
    ):
        for i, f in enumerate(rows):
            got[f] = [set(J[i][m[i]]) for m in masks]
    assert sorted(got) == list(range(len(F)))
    for f in range(0, len(F), 7):
        for r, R in enumerate(radii):
            assert got[f][r] == _reference_traversal((nbr, length, n), f, R, min_faces, check_normals), (f, R)


def test_smoothed_normals_and_face_neighbours():
    m = trimesh.creation.icosphere(subdivisions=3)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    n = smoothed_face_normals(V, F)
    c = geometry.face_centers(V, F)
    assert (np.einsum("ij,ij->i", n, c / np.linalg.norm(c, axis=1, keepdims=True)) > 0.9999).all()
    Vg, Fg = grid(5)
    np.testing.assert_allclose(smoothed_face_normals(Vg, Fg), np.tile([0, 0, 1.0], (len(Fg), 1)), atol=1e-12)
    nbr, length = face_neighbours(V, F)
    assert (nbr >= 0).all() and np.isfinite(length).all() and (length > 0).all()
    assert all(f in nbr[g] for f in range(len(F)) for g in nbr[f])


def test_clip_outliers_order_statistics():
    x = np.arange(100.0)
    X = clip_outliers(np.c_[x, x, -x], np.array([True, False, False]))
    assert (X[:, 0].min(), X[:, 0].max()) == (5, 95)  # signed: sorted[5], sorted[95]
    assert (X[:, 1].min(), X[:, 1].max()) == (0, 95)  # absolute: |x| at sorted |x|[95] only
    assert (X[:, 2].min(), X[:, 2].max()) == (-95, 0)  # ... keeping the sign


def test_kalogerakis_units():
    V, F = blob()
    R, t = random_rigid()
    np.testing.assert_allclose(kalogerakis_normalize(3 * V @ R.T + t, F), kalogerakis_normalize(V, F) @ R.T, atol=1e-9)
    c = geometry.face_centers(kalogerakis_normalize(V, F), F)
    a = geometry.face_areas(V, F)
    np.testing.assert_allclose(a @ c, 0, atol=1e-9)
    assert np.sort(np.linalg.norm(c, axis=1))[int(0.33 * len(F))] == pytest.approx(0.33 / 0.5, rel=1e-9)


# --- the original's values ---------------------------------------------------------------------


def test_matches_kalogerakis_reference_airplane(psb):
    ref = np.load(conftest.require(REFERENCE / "Airplane_61.npz"))
    mesh = psb.load("Airplane", "61")
    assert len(mesh.faces) == ref["n_faces"]
    idx = ref["faces"]
    # measured: curvature 1.0000 on every column (exact up to float32); pca median 0.9999, worst 0.995
    for name, cols, median, worst in (("curvature", slice(0, 64), 0.9999, 0.999), ("pca", slice(64, 112), 0.999, 0.99)):
        X = GROUPS[name](mesh.vertices, mesh.faces)[idx]
        Y = ref["X"][:, cols]
        r = np.array([np.corrcoef(X[:, j], Y[:, j])[0, 1] for j in range(X.shape[1])])
        assert np.median(r) > median and r.min() > worst, (name, np.median(r), r.min(), r.argmin())
