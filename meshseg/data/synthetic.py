"""Deterministic synthetic labelled triangle meshes (the harness's default dataset).

Each shape is a union of part signed-distance functions (SDFs) with randomly drawn
proportions and pose.  The union (hard ``min``, so part junctions keep a crease that
curvature/SDF features can pick up) is sampled on a regular grid in a randomly rotated
frame with a random sub-cell offset, so tessellations differ between meshes; the surface
is extracted with marching cubes and cleaned into a single closed, consistently
outward-oriented component.  Each face is labelled by the part whose SDF is smallest at
its centroid.

Everything derives from ``np.random.default_rng([seed, category_number, index])``, so a
mesh depends only on its arguments (never on Python's salted ``hash``).  Proportions
and pose use their own child generators, so the shape of a mesh does not change with
the requested face-count range, only its tessellation does.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from skimage.measure import marching_cubes

from meshseg.data.sdf import (
    sd_capsule,
    sd_cylinder_z,
    sd_ellipsoid,
    sd_open_shell_z,
    sd_round_box,
    sd_sphere,
    sd_torus_xz,
)
from meshseg.errors import ConfigError

__all__ = ["CATEGORIES", "PART_NAMES", "SyntheticMesh", "generate", "sample"]

CATEGORIES: tuple[str, ...] = ("table", "cup", "figure")
PART_NAMES: dict[str, tuple[str, ...]] = {
    "table": ("top", "leg"),
    "cup": ("body", "handle"),
    "figure": ("head", "torso", "arm", "leg"),
}

_COARSE_CELLS = 25  # cells along the bounding-box diagonal for the face-count probe
_MAX_PASSES = 8  # marching-cubes passes allowed to hit the face-count range


# ----------------------------------------------------------------------------------
# Shape builders: proportions -> list of parts (label, sdf, axis-aligned bounds).
# Canonical frame: z is up, shapes stand on or around the origin.
# ----------------------------------------------------------------------------------
class _Part(NamedTuple):
    label: int
    sdf: Callable[[np.ndarray], np.ndarray]
    lo: np.ndarray
    hi: np.ndarray


def _part(label, sdf, lo, hi) -> _Part:
    return _Part(label, sdf, np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))


def _capsule_part(label, a, b, r) -> _Part:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return _part(label, lambda p: sd_capsule(p, a, b, r), np.minimum(a, b) - r, np.maximum(a, b) + r)


def _build_table(rng: np.random.Generator) -> tuple[list[_Part], dict]:
    width = rng.uniform(1.0, 1.5)
    depth = width * rng.uniform(0.6, 0.9)
    thick = rng.uniform(0.1, 0.16)
    height = rng.uniform(0.55, 1.0)
    leg_r = rng.uniform(0.06, 0.09)  # radius, or half-width for square legs
    # Legs sit under the top, with a wide gap between neighbours: nearly touching legs
    # would fuse at coarse grid spacings and open a spurious tunnel.
    inset = leg_r + min(rng.uniform(0.02, 0.15), (depth - 4 * leg_r - 0.2) / 2)
    leg_style = ("square", "cylinder", "splayed")[rng.integers(3)]
    splay = float(np.deg2rad(rng.uniform(3.0, 12.0))) if leg_style == "splayed" else 0.0
    params = dict(
        width=width,
        depth=depth,
        thickness=thick,
        height=height,
        leg_radius=leg_r,
        inset=inset,
        leg_style=leg_style,
        splay=splay,
    )

    top_c = np.array([0.0, 0.0, height - thick / 2])
    top_half = np.array([width / 2, depth / 2, thick / 2])
    rounding = thick * rng.uniform(0.15, 0.45)
    parts = [_part(0, lambda p: sd_round_box(p, top_c, top_half, rounding), top_c - top_half, top_c + top_half)]

    attach_z = height - thick / 2  # legs end inside the top so the union is one solid
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            x, y = sx * (width / 2 - inset), sy * (depth / 2 - inset)
            c = np.array([x, y, attach_z / 2])
            half = np.array([leg_r, leg_r, attach_z / 2])
            if leg_style == "splayed":
                # The capsule's rounded end must stay inside the top, not poke through it.
                top_z = min(attach_z, height - 0.2 * thick - leg_r)
                spread = np.tan(splay) * (top_z - leg_r)
                foot = np.array([x + sx * spread, y + sy * spread, leg_r])
                parts.append(_capsule_part(1, [x, y, top_z], foot, leg_r))
            elif leg_style == "cylinder":
                parts.append(_part(1, lambda p, c=c: sd_cylinder_z(p, c, leg_r, attach_z / 2), c - half, c + half))
            else:
                parts.append(
                    _part(1, lambda p, c=c, half=half: sd_round_box(p, c, half, 0.2 * leg_r), c - half, c + half)
                )
    return parts, params


def _build_cup(rng: np.random.Generator) -> tuple[list[_Part], dict]:
    r_bottom = rng.uniform(0.28, 0.38)
    r_top = r_bottom * rng.uniform(1.0, 1.2)  # from straight mugs to slightly flared tumblers
    height = rng.uniform(0.9, 1.2)
    wall = rng.uniform(0.075, 0.1)
    tube = rng.uniform(0.07, 0.09)
    # Handle loop (centred on the wall's mid-surface): keep the hole between it and the
    # outer wall open, and the whole loop between bottom and rim.
    half_span = (height - 1.5 * wall) / 2 - 0.02
    hole = min(rng.uniform(0.14, 0.24), half_span - 2 * tube - wall / 2)
    major = tube + wall / 2 + hole
    stretch = rng.uniform(0.0, 1.0) * (half_span - major - tube)  # taller, D-shaped handles
    reach = major + stretch + tube  # half the handle's height
    handle_z = rng.uniform(wall + reach, height - wall / 2 - reach)
    slope = (r_top - r_bottom) / height
    handle_x = r_bottom + slope * handle_z  # on the wall's mid-surface
    params = dict(
        r_bottom=r_bottom,
        r_top=r_top,
        height=height,
        wall=wall,
        handle_major=major,
        handle_minor=tube,
        handle_stretch=stretch,
        handle_z=handle_z,
    )

    handle_c = np.array([handle_x, 0.0, handle_z])

    def handle(p):
        # Cut away the inner half along the wall's mid-surface, so the cut face stays hidden.
        inside_mid = np.hypot(p[:, 0], p[:, 1]) - (r_bottom + slope * p[:, 2])
        return np.maximum(sd_torus_xz(p, handle_c, major, tube, stretch), -inside_mid)

    r_max = r_top + wall / 2
    parts = [
        _part(
            0,
            lambda p: sd_open_shell_z(p, r_bottom, r_top, height, wall),
            [-r_max, -r_max, -wall / 2],
            [r_max, r_max, height + wall / 2],
        ),
        _part(1, handle, [r_bottom - wall, -tube, handle_z - reach], [handle_x + major + tube, tube, handle_z + reach]),
    ]
    return parts, params


def _limb_dir(side: float, out: float, swing: float) -> np.ndarray:
    """Unit vector pointing mostly down, tilted sideways by `out` and forward (+y) by `swing`."""
    return np.array([side * np.sin(out), np.cos(out) * np.sin(swing), -np.cos(out) * np.cos(swing)])


def _build_figure(rng: np.random.Generator) -> tuple[list[_Part], dict]:
    tw, td, th = rng.uniform(0.22, 0.32), rng.uniform(0.14, 0.2), rng.uniform(0.32, 0.45)
    head_r = rng.uniform(0.14, 0.2)
    arm_r, leg_r = rng.uniform(0.065, 0.09), rng.uniform(0.085, 0.11)
    hand_r = arm_r * rng.uniform(1.15, 1.4)  # ball hands: a bulge ending each arm
    upper_arm, fore_arm = rng.uniform(0.3, 0.42), rng.uniform(0.26, 0.38)
    thigh, shin = rng.uniform(0.38, 0.52), rng.uniform(0.36, 0.5)
    params = dict(
        torso=(tw, td, th),
        head_radius=head_r,
        arm_radius=arm_r,
        leg_radius=leg_r,
        arm_lengths=(upper_arm, fore_arm),
        leg_lengths=(thigh, shin),
        pose={},
    )

    torso_c = np.zeros(3)
    head_radii = head_r * np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(1.0, 1.2)])
    head_c = np.array([0.0, 0.0, th + 0.8 * head_radii[2]])  # overlaps the torso a little: a neck crease
    parts = [
        _part(0, lambda p: sd_ellipsoid(p, head_c, head_radii), head_c - head_radii, head_c + head_radii),
        _part(1, lambda p: sd_ellipsoid(p, torso_c, (tw, td, th)), -np.array([tw, td, th]), np.array([tw, td, th])),
    ]
    # The pose: every limb gets its own sideways / forward angles and a joint bend.
    for side in (-1.0, 1.0):
        out, swing, bend = np.deg2rad([rng.uniform(20, 85), rng.uniform(-45, 45), rng.uniform(0, 70)])
        shoulder = np.array([side * 0.75 * tw, 0.0, 0.55 * th])
        elbow = shoulder + upper_arm * _limb_dir(side, out, swing)
        hand = elbow + fore_arm * _limb_dir(side, out, swing + bend)  # elbows bend forward
        parts += [
            _capsule_part(2, shoulder, elbow, arm_r),
            _capsule_part(2, elbow, hand, arm_r),
            _part(2, lambda p, c=hand: sd_sphere(p, c, hand_r), hand - hand_r, hand + hand_r),
        ]
        params["pose"][f"arm{side:+.0f}"] = np.rad2deg([out, swing, bend])
    for side in (-1.0, 1.0):
        out, swing, bend = np.deg2rad([rng.uniform(5, 22), rng.uniform(-35, 35), rng.uniform(0, 50)])
        hip = np.array([side * max(0.45 * tw, 1.2 * leg_r), 0.0, -0.7 * th])
        knee = hip + thigh * _limb_dir(side, out, swing)
        foot = knee + shin * _limb_dir(side, out, swing - bend)  # knees bend backward
        parts += [_capsule_part(3, hip, knee, leg_r), _capsule_part(3, knee, foot, leg_r)]
        params["pose"][f"leg{side:+.0f}"] = np.rad2deg([out, swing, bend])
    return parts, params


_BUILDERS = {"table": _build_table, "cup": _build_cup, "figure": _build_figure}
# Genus of the intended surface (the cup's handle makes one tunnel).  A larger genus means
# an under-resolved thin wall got perforated.  Figures may legitimately close loops where
# a limb touches the body, so they are not checked.
_GENUS = {"table": 0, "cup": 1}


# ----------------------------------------------------------------------------------
# Meshing.
# ----------------------------------------------------------------------------------


@dataclass
class SyntheticMesh:
    """A generated mesh plus the frame it was posed in.

    ``vertices @ rotation + center`` maps vertices back to the canonical frame
    (z up, parts as built), which is where the labels were assigned.
    """

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray
    rotation: np.ndarray
    center: np.ndarray
    spacing: float
    params: dict = field(default_factory=dict)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    # A normalised 4D Gaussian is a uniform unit quaternion, i.e. uniform on SO(3).
    w, x, y, z = (q := rng.normal(size=4)) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _part_distances(parts: list[_Part], p: np.ndarray) -> np.ndarray:
    return np.stack([part.sdf(p) for part in parts])


def _clean(verts: np.ndarray, faces: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Merge duplicate vertices, drop degenerate faces, keep the largest component.

    Also returns the surface area thrown away with the smaller components."""
    keys = np.round(verts / tol).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    verts, faces = verts[first], inverse.reshape(-1)[faces]
    a, b, c = faces.T
    faces = faces[(a != b) & (b != c) & (a != c)]
    area = 0.5 * np.linalg.norm(
        np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]]), axis=1
    )
    faces, area = faces[area > tol * tol], area[area > tol * tol]
    # Components over the vertex graph; keep the one carrying the most faces.
    n = len(verts)
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    graph = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    face_comp = comp[faces[:, 0]]
    keep = face_comp == np.bincount(face_comp).argmax()
    used, kept = np.unique(faces[keep], return_inverse=True)
    return verts[used], kept.reshape(-1, 3).astype(np.int64), float(area[~keep].sum())


def _signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return float(np.einsum("ij,ij->", v0, np.cross(v1, v2)) / 6.0)


def _is_closed_oriented(faces: np.ndarray) -> bool:
    """Every undirected edge in exactly two faces, traversed once in each direction."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    if len(np.unique(directed, axis=0)) != len(directed):
        return False  # a directed edge used twice: inconsistent winding or non-manifold
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    return bool(np.all(counts == 2))


class _Pose(NamedTuple):
    """How a shape is posed: world = (canonical - center) @ rotation.T, and the posed shape's bounding box."""

    rotation: np.ndarray
    center: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def _polygonize(parts, pose: _Pose, spacing, offset):
    """Marching cubes of the union SDF on a grid with the given spacing and sub-cell offset."""
    rotation, center, lo, hi = pose
    origin = lo - (2.0 + offset) * spacing  # >= 2 cells of padding: the surface never touches the border
    shape = np.ceil((hi - origin) / spacing).astype(int) + 3
    axes = [origin[k] + spacing * np.arange(shape[k]) for k in range(3)]
    world = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    canonical = world @ rotation + center  # world = (canonical - center) @ rotation.T
    field_ = _part_distances(parts, canonical).min(axis=0).reshape(shape)
    verts, faces, _, _ = marching_cubes(field_, 0.0, spacing=(spacing,) * 3)
    return _clean(verts + origin, faces, tol=1e-6 * spacing)


def sample(category: str, index: int, seed: int = 0, min_faces: int = 1500, max_faces: int = 6000) -> SyntheticMesh:
    """Like :func:`generate`, but also returns the pose (rotation/center) and shape parameters."""
    if category not in _BUILDERS:
        raise ConfigError(f"unknown category {category!r}; allowed categories: {', '.join(CATEGORIES)}")
    if not 0 < min_faces <= max_faces:
        raise ConfigError(f"need 0 < min_faces <= max_faces, got {min_faces}, {max_faces}")
    root = np.random.default_rng([int(seed), CATEGORIES.index(category), int(index)])
    shape_rng, pose_rng, grid_rng = root.spawn(3)

    parts, params = _BUILDERS[category](shape_rng)
    n_labels = len(PART_NAMES[category])
    part_labels = np.array([p.label for p in parts], dtype=np.int64)
    rotation = _random_rotation(pose_rng)
    c_lo = np.min([p.lo for p in parts], axis=0)
    c_hi = np.max([p.hi for p in parts], axis=0)
    center = (c_lo + c_hi) / 2
    corners = np.array([[x, y, z] for x in (c_lo[0], c_hi[0]) for y in (c_lo[1], c_hi[1]) for z in (c_lo[2], c_hi[2])])
    rotated = (corners - center) @ rotation.T
    lo, hi = rotated.min(axis=0), rotated.max(axis=0)

    # Draw the target inside the range (away from its edges so one rescale usually lands).
    margin = 0.1 * (max_faces - min_faces)
    target = grid_rng.uniform(min_faces + margin, max_faces - margin)
    spacing = np.linalg.norm(c_hi - c_lo) / _COARSE_CELLS
    n_faces = []
    max_spacing = np.inf  # below the coarsest spacing seen to lose a thin part
    for attempt in range(_MAX_PASSES):
        offset = grid_rng.uniform(0.0, 1.0, size=3)  # random grid phase: tessellation differs per mesh
        verts, faces, dropped = _polygonize(parts, _Pose(rotation, center, lo, hi), spacing, offset)
        n_faces.append(n := len(faces))
        centroids = verts[faces].mean(axis=1) @ rotation + center
        labels = part_labels[_part_distances(parts, centroids).argmin(axis=0)]
        # A broken-off piece of a thin part has an area of several cells; specks far below
        # one cell are harmless crease artefacts (tiny sealed pockets) and are just dropped.
        resolved = dropped < 0.1 * spacing**2 and len(np.unique(labels)) == n_labels
        closed = _is_closed_oriented(faces)
        if closed and category in _GENUS:
            resolved &= len(verts) - len(faces) // 2 == 2 - 2 * _GENUS[category]  # Euler: V - E + F
        in_range = min_faces <= n <= max_faces
        if attempt > 0 and in_range and resolved and closed:
            if _signed_volume(verts, faces) < 0:  # inward normals: flip the winding
                faces = faces[:, ::-1].copy()
            return SyntheticMesh(verts, faces, labels, rotation, center, float(spacing), params)
        if not resolved:  # a thin part broke off or vanished: never go this coarse again
            max_spacing = 0.9 * spacing
        if attempt == 0 or not in_range:  # pass 0 is the coarse probe
            spacing *= np.sqrt(max(n, 1) / target)  # face count ~ 1 / spacing^2
        elif not closed:
            spacing *= 0.98  # rare marching-cubes glitch: retry on a shifted grid
        spacing = min(spacing, max_spacing)
    raise RuntimeError(
        f"could not mesh {category!r} index {index} seed {seed} with {min_faces}..{max_faces} closed faces "
        f"containing every part (face counts per pass: {n_faces}); the range may be too small "
        "to resolve the thinnest part"
    )


def generate(
    category: str, index: int, seed: int = 0, min_faces: int = 1500, max_faces: int = 6000
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mesh `index` of `category` for dataset seed `seed`.

    Returns ``(V, F, labels)``: float64 (n, 3) vertices, int64 (m, 3) outward-wound faces
    and int64 (m,) per-face labels indexing ``PART_NAMES[category]``.  The mesh is a single
    closed, consistently oriented component with ``min_faces <= m <= max_faces``.
    """
    m = sample(category, index, seed, min_faces, max_faces)
    return m.vertices, m.faces, m.labels
