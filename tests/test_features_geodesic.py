"""Geodesic features: shape context (`shape_context`, 270) and average geodesic distance (`agd`, 15)."""

import conftest
import numpy as np
import pytest
import trimesh
from scipy.sparse.csgraph import dijkstra

from meshseg.features import agd, geometry, shape_context
from meshseg.features.operators import MeshOperators
from meshseg.features.registry import GROUPS

REFERENCE = conftest.SHARED / "data/reference/kalogerakis2010"
CALIBRATION = GROUPS["shape_context"].defaults["scale_calibration"]
COLUMNS = (
    [line.split("\t")[1].strip() for line in (REFERENCE / "columns.txt").read_text().splitlines()]
    if (REFERENCE / "columns.txt").exists()
    else None
)


def bumpy_sphere(subdivisions=2, seed=0):
    """An icosphere with radial noise: no symmetry, so sampling ties cannot depend on face order."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    rng = np.random.default_rng(seed)
    V = m.vertices * (1 + 0.08 * rng.standard_normal((len(m.vertices), 1)))
    return V, np.asarray(m.faces, np.int64)


def grid(n=14):
    """A flat n x n square of 2 n^2 triangles in the z = 0 plane, with jittered interior vertices."""
    x, y = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    V = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    rng = np.random.default_rng(1)
    inner = (V[:, 0] > 0) & (V[:, 0] < 1) & (V[:, 1] > 0) & (V[:, 1] < 1)
    V[inner, :2] += rng.uniform(-0.2, 0.2, (inner.sum(), 2)) / n
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    i = i.ravel()
    F = np.r_[np.c_[i, i + 1, i + n + 2], np.c_[i, i + n + 2, i + n + 1]]
    return V, F


def tube(radius=0.5, length=6.0, n_around=24):
    """An open cylinder along z, of nearly equilateral triangles."""
    n_along = int(round(length / (2 * np.pi * radius / n_around))) + 1
    t = 2 * np.pi * np.arange(n_around) / n_around
    z = np.linspace(-length / 2, length / 2, n_along)
    shift = (np.arange(n_along) % 2)[:, None] * np.pi / n_around  # staggered rings
    V = np.stack(
        [radius * np.cos(t + shift), radius * np.sin(t + shift), np.broadcast_to(z[:, None], (n_along, n_around))], -1
    ).reshape(-1, 3)
    ring = np.arange(n_around)
    F = []
    for k in range(n_along - 1):
        a, b = k * n_around + ring, (k + 1) * n_around + ring
        a1, b1 = k * n_around + (ring + 1) % n_around, (k + 1) * n_around + (ring + 1) % n_around
        F += [np.c_[a, a1, b], np.c_[a1, b1, b]] if k % 2 == 0 else [np.c_[a, a1, b1], np.c_[a, b1, b]]
    return V, np.concatenate(F)


def random_rigid(seed=3):
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q)), np.array([0.3, -2.0, 5.0])


def all_pairs(V, F):
    """Normalised vertices, areas / total, centres, normals and all dual-graph distances."""
    centre, unit = geometry.kalogerakis_units(V, F)
    Vn = (V - centre) / unit
    a = geometry.face_areas(Vn, F)
    D = dijkstra(geometry.face_dual_graph(Vn, F), directed=False)
    return Vn, a / a.sum(), geometry.face_centers(Vn, F), geometry.per_face_normals(Vn, F), D


# --- shape, registration, robustness -------------------------------------------------------------


@pytest.mark.parametrize("name, dim", [("shape_context", 270), ("agd", 15)])
def test_registered_shape_float32_finite(name, dim):
    V, F = bumpy_sphere(2)
    X = GROUPS[name](V, F)
    assert X.shape == (len(F), dim) and X.dtype == np.float32 and np.isfinite(X).all()
    assert X.std(axis=0).max() > 0


def test_one_dijkstra_run_per_mesh():
    V, F = bumpy_sphere(2)
    ops = MeshOperators(V, F)
    geo = ops.geodesics(64)
    assert ops.geodesics(64) is geo and ops.geodesics(32) is not geo  # memoised per n_samples
    assert MeshOperators(V.copy(), F.copy()).geodesics(64) is not geo  # the memo is the object's
    plain = agd.sampled_geodesics(V, F, 64)  # pure: a new run, the same values
    assert plain is not geo and (plain.dist == geo.dist).all() and (plain.samples == geo.samples).all()
    assert len(geo.samples) == 64 and geo.dist.shape == (64, len(F))
    np.testing.assert_allclose(geo.cell_area.sum(), 1.0)
    # shared or not, the groups' values are the same
    for name in ("agd", "shape_context"):
        np.testing.assert_array_equal(GROUPS[name](V, F, ops=ops, n_samples=64), GROUPS[name](V, F, n_samples=64))


def test_column_names_are_the_reference_names():
    if COLUMNS is None:
        pytest.skip("reference columns.txt not available")
    assert list(GROUPS["shape_context"].columns) == COLUMNS[112:382]
    assert list(GROUPS["agd"].columns) == COLUMNS[382:397]


def test_disconnected_and_degenerate_meshes_stay_finite():
    V1, F1 = bumpy_sphere(2, seed=0)
    V2, F2 = bumpy_sphere(1, seed=1)
    V = np.r_[V1, V2 * 0.5 + [4.0, 0, 0], [[9, 9, 9], [9, 9, 9], [9, 9, 9]]]
    F = np.r_[
        F1, F2 + len(V1), [[len(V1) + len(V2), len(V1) + len(V2) + 1, len(V1) + len(V2) + 2]]
    ]  # + a zero-area face alone
    F = np.r_[F, F[:1][:, [0, 0, 1]]]  # and a zero-area face glued to the first sphere
    for name in ("agd", "shape_context"):
        X = GROUPS[name](V, F, n_samples=64)
        assert np.isfinite(X).all(), name
    # statistics are per component: the small sphere's AGD is about half the big one's
    raw = agd.distance_statistics(agd.sampled_geodesics(V, F, 64))
    big, small = raw[: len(F1), 0].mean(), raw[len(F1) : len(F1) + len(F2), 0].mean()
    assert small / big == pytest.approx(0.5, rel=0.1)


def test_tiny_meshes():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.2]], float)
    for F in (np.array([[0, 1, 2]]), np.array([[0, 1, 2], [1, 3, 2]])):
        for name in ("agd", "shape_context"):
            X = GROUPS[name](V, F)
            assert X.shape[0] == len(F) and np.isfinite(X).all()


def test_rigid_motion_scale_and_face_order_invariance():
    V, F = bumpy_sphere(3)
    R, t = random_rigid()
    perm = np.random.default_rng(5).permutation(len(F))
    for name in ("agd", "shape_context"):
        X = GROUPS[name](V, F, n_samples=96)
        Y = GROUPS[name](2.5 * V @ R.T + t, F, n_samples=96)
        Z = GROUPS[name](V, F[perm][:, [1, 2, 0]], n_samples=96)  # faces reordered, corners rotated
        scale = np.abs(X).max(axis=0) + 1e-12
        np.testing.assert_allclose(Y / scale, X / scale, atol=1e-4, err_msg=name)
        np.testing.assert_allclose(Z / scale, X[perm] / scale, atol=1e-4, err_msg=name)
    # a symmetric mesh too (sampling breaks exact ties the same way after a rigid motion)
    m = trimesh.creation.icosphere(subdivisions=3)
    for name in ("agd", "shape_context"):
        X = GROUPS[name](m.vertices, m.faces, n_samples=96)
        Y = GROUPS[name](m.vertices @ R.T + t, m.faces, n_samples=96)
        np.testing.assert_allclose(Y, X, atol=1e-5 * np.abs(X).max(), err_msg=name)


# --- exactness: with every face a sample, the sampled groups are the 2010 definitions -------------


def test_agd_with_every_face_sampled_is_exact():
    V, F = bumpy_sphere(2)
    _, a, _, _, D = all_pairs(V, F)
    raw = agd.distance_statistics(agd.sampled_geodesics(V, F, len(F)))
    E = np.zeros((len(F), 15))
    for j, p in enumerate((1, 2, 4, 8, 0.5, 0.25)):
        E[:, j] = D**p @ a
    dev = D - E[:, :1]
    E[:, 6] = dev**2 @ a
    E[:, 7] = dev**3 @ a / np.sqrt(E[:, 6] ** 3)
    E[:, 8] = dev**4 @ a / E[:, 6] ** 2
    order = np.argsort(D, axis=1)  # the 2010 code walks the faces in Dijkstra order
    cum = np.cumsum(a[order], axis=1)
    for j, q in enumerate((0.1, 0.2, 0.3, 0.4, 0.5)):
        E[:, 9 + j] = np.take_along_axis(D, order, 1)[np.arange(len(F)), (cum < q - 1e-12).sum(1)]
    np.testing.assert_allclose(raw, E, rtol=1e-5, atol=1e-6 * np.abs(E).max())
    X = agd.average_geodesic_distance(V, F, n_samples=len(F))
    np.testing.assert_allclose(X, raw - raw.min(axis=0), rtol=1e-5, atol=1e-5 * np.abs(raw).max())  # the per-mesh shift
    assert (X[:, 14] == 0).all() and (X.min(axis=0) == 0).all()


def _original_shape_context(V, F, D):
    """The 2010 histograms by brute force over all face pairs (dual-graph distances D), with the
    mesh scale computed independently of the module (95th percentile of the 95th percentiles)."""
    _, a, c, n, _ = all_pairs(V, F)
    nf = len(F)
    per = np.sort(D, axis=1)[:, int(0.95 * (nf - 1))]
    scale = np.sort(per)[int(np.ceil(0.95 * nf)) - 1] * CALIBRATION
    i, k = np.nonzero(~np.eye(nf, dtype=bool))
    d = D[i, k]
    u = c[k] - c[i]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    angle = np.degrees(np.arcsin(np.clip((u * n[k]).sum(1), -1, 1)))
    w = a[k] / (d / scale + 0.1)
    cols = []
    for nd, na in shape_context.BINNINGS:
        s = nd + 1
        edges = (-np.log((s - np.arange(s)) / s)) ** 0.9 * (1.2 * scale / np.log(s) ** 0.9)
        x = np.searchsorted(edges, d, side="right") - 1
        y = np.minimum(((angle + 90) / 180 * na).astype(int), na - 1)
        ok = x < nd
        cols.append(np.bincount(i[ok] * nd * na + x[ok] * na + y[ok], w[ok], nf * nd * na).reshape(nf, -1))
    return np.hstack(cols)


def test_shape_context_with_every_face_sampled_is_the_original():
    V, F = bumpy_sphere(2)
    X = shape_context.shape_context(
        V, F, shape_context.ShapeContextSettings(n_samples=len(F), n_near_samples=0, soft_binning=False)
    )
    geo = agd.sampled_geodesics(V, F, len(F))
    E = _original_shape_context(V, F, geo.dist.astype(np.float64))
    np.testing.assert_allclose(X, E, atol=1e-5)
    assert X[:, :20].sum(1).mean() > 1.0  # a real histogram, not zeros


# --- analytic shapes ------------------------------------------------------------------------------


def test_agd_sphere_is_uniform_and_analytic():
    r = 2.0
    m = trimesh.creation.icosphere(subdivisions=4, radius=r)
    V, F = m.vertices, np.asarray(m.faces)
    geo = agd.sampled_geodesics(V, F, 256)
    raw = agd.distance_statistics(geo)
    mean_g = raw[:, 0] * geo.unit  # back to input units
    assert mean_g.std() / mean_g.mean() < 0.01  # the same for every face, up to sampling
    # pi r / 2 is the sphere's mean geodesic distance; paths over the face dual graph (a honeycomb
    # here) zig-zag, longer than arcs by a factor measured on a few source faces
    c = geometry.face_centers(V, F)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    src = [0, 77, 1001]
    path = dijkstra(geometry.face_dual_graph(V, F), directed=False, indices=src)
    stretch = path.sum() / (r * np.arccos(np.clip(c[src] @ c.T, -1, 1))).sum()
    assert 1.1 < stretch < 1.35
    assert mean_g.mean() == pytest.approx(np.pi * r / 2 * stretch, rel=0.01)
    assert raw[:, 13].mean() * geo.unit == pytest.approx(np.pi * r / 2 * stretch, rel=0.03)  # median = mean here
    X = GROUPS["agd"](V, F)
    assert X[:, 0].max() < 0.05 * raw[:, 0].mean()  # after the per-mesh shift: about 0


def test_agd_elongated_shape_ends_exceed_middle():
    V, F = tube()
    X = GROUPS["agd"](V, F)
    z = np.abs(geometry.face_centers(V, F)[:, 2])
    ends, middle = X[z > 2.7, 0], X[z < 0.3, 0]
    assert ends.min() > middle.max() + 0.5 * (X[:, 0].max() - X[:, 0].min())
    # along a tube of length L, E[g] at height z is about (L^2 / 4 + z^2) / L: quadratic in z
    assert np.corrcoef(z**2, X[:, 0])[0, 1] > 0.99


def test_shape_context_flat_patch_sums_as_documented():
    V, F = grid()
    H = shape_context.shape_context(V, F)
    _, a, _, _, D = all_pairs(V, F)
    geo = agd.sampled_geodesics(V, F, 256)
    counts = np.bincount(geo.owner, minlength=len(geo.samples)).astype(float)
    scale = shape_context.geodesic_scale(geo.dist, counts, CALIBRATION)
    np.fill_diagonal(D, np.inf)  # the face itself is not counted
    expected = ((a[None, :] / (D / scale + 0.1)) * (D < 1.2 * scale)).sum(1)
    start = 0
    for nd, na in shape_context.BINNINGS:
        h = H[:, start : start + nd * na].reshape(len(F), nd, na)
        start += nd * na
        # every row sums to sum_k (a_k / A) / (d / D + 0.1) over faces within 1.2 D
        np.testing.assert_allclose(h.sum((1, 2)), expected, rtol=0.03)
        # flat: every other face lies in the tangent plane (angle 0), split evenly around 0
        ang = h.sum(1)
        np.testing.assert_allclose(ang[:, : na // 2 - 1].sum(1), 0, atol=1e-6)
        np.testing.assert_allclose(ang[:, na // 2 + 1 :].sum(1), 0, atol=1e-6)
        np.testing.assert_allclose(ang[:, na // 2 - 1], ang[:, na // 2], rtol=1e-4)


def test_shape_context_angles_on_a_sphere_are_positive():
    """On a sphere the direction to another face dips below that face's tangent plane by half the
    arc between them: u . n_k > 0, positive angles only, and small ones for near faces."""
    m = trimesh.creation.icosphere(subdivisions=3)
    H = shape_context.shape_context(
        m.vertices, np.asarray(m.faces), shape_context.ShapeContextSettings(soft_binning=False)
    )
    h = H[:, :20].reshape(len(m.faces), 5, 4)  # 5 x 4: angle bins [-90,-45), [-45,0), [0,45), [45,90)
    assert h[:, :, :2].sum() < 1e-3 * h.sum()  # (face normals tilt a little off the radius)
    assert h[:, 0, 3].sum() < 1e-6 * h[:, 0].sum()  # the nearest bin: under 45 degrees
    assert h[:, 4, 3].sum() > 0.5 * h[:, 4].sum()  # the farthest: mostly over 45 (arcs over 90)


# --- the original's values ------------------------------------------------------------------------


def test_matches_kalogerakis_reference_airplane(psb):
    ref = np.load(conftest.require(REFERENCE / "Airplane_61.npz"))
    mesh = psb.load("Airplane", "61")
    assert len(mesh.faces) == ref["n_faces"]
    idx = ref["faces"]
    for name, cols, median, p10 in (
        ("shape_context", slice(112, 382), 0.975, 0.87),
        ("agd", slice(382, 396), 0.995, 0.99),
    ):
        X = GROUPS[name](mesh.vertices, mesh.faces)[idx].astype(np.float64)
        Y = ref["X"][:, cols].astype(np.float64)
        live = Y.std(axis=0) > 0  # the original leaves a few rare bins empty on these faces
        r = np.array([np.corrcoef(X[:, j], Y[:, j])[0, 1] for j in np.flatnonzero(live)])
        assert np.median(r) > median and np.percentile(r, 10) > p10, (name, np.median(r), np.percentile(r, 10))
    assert (GROUPS["agd"](mesh.vertices, mesh.faces)[:, 14] == 0).all() and (ref["X"][:, 396] == 0).all()
