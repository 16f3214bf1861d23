"""Pictures for run tracking: a mesh coloured by predicted vs ground-truth labels, and a confusion matrix.

Plain numpy arrays in, PNG bytes out (upstream of tracking, which logs them). Only matplotlib's object
API is used (Figure + FigureCanvasAgg, never pyplot): thread-safe, headless, and the process-wide backend is
left alone. Meshes are drawn by a small
vectorised z-buffer rasteriser, so hidden surfaces are exact and 20k faces take milliseconds.
"""

from __future__ import annotations

import colorsys
import io
from dataclasses import dataclass

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import PercentFormatter

from meshseg.data.mesh import face_areas
from meshseg.metrics import area_weighted_accuracy

UNLABELLED = np.array([0.6, 0.6, 0.6])
"""Colour of faces whose label is outside [0, n_labels)."""

# tab10 then tab20's light tones, each without its grey: grey is reserved for unlabelled faces.
_BASE = np.array(
    [c for i, c in enumerate(colormaps["tab10"].colors) if i != 7]
    + [c for i, c in enumerate(colormaps["tab20"].colors[1::2]) if i != 7]
)
PANEL = 320  # pixels, the side of each panel of `label_comparison_png`
_MARGIN = 0.04  # fraction of the image left blank on each side of the mesh
_CHUNK = 1 << 19  # candidate pixels per rasterisation batch: bounds memory when triangles are large
_EPS = 1e-7  # barycentric tolerance, so pixel centres on a shared edge are never missed


def label_colors(n: int) -> np.ndarray:
    """(n, 3) RGB in [0, 1]; label i gets the same colour whatever n is, so all pictures agree.

    Beyond the 18 base colours, hues follow the golden-ratio sequence with alternating saturation/value.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    extra = [
        colorsys.hsv_to_rgb(0.618034 * k % 1.0, (1.0, 0.6)[k % 2], (0.95, 0.7, 0.5)[k % 3])
        for k in range(max(0, n - len(_BASE)))
    ]
    return np.vstack([_BASE[:n], np.reshape(extra, (-1, 3))])


@dataclass(frozen=True)
class Camera:
    """Where the eye is, as in matplotlib's 3D axes: `azim` about z and `elev` above the xy plane, degrees."""

    elev: float = 20
    azim: float = -60

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit vectors screen-right, screen-up and towards the viewer."""
        e, a = np.radians(self.elev), np.radians(self.azim)
        toward = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        right = np.array([-np.sin(a), np.cos(a), 0.0])
        return right, np.cross(toward, right), toward


_DEFAULT_CAMERA = Camera()


def _rasterise(x: np.ndarray, y: np.ndarray, z: np.ndarray, size: int) -> np.ndarray:
    """(size * size,) index of the nearest face covering each pixel centre, -1 where none does.

    x, y: (F, 3) pixel coordinates of each face's corners (y pointing down); z: (F, 3) depth, larger = nearer.
    Each face tests the pixel centres of its bounding box; per pixel the largest depth wins.
    """
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    area = np.where(area == 0, np.inf, area)  # edge-on faces: zero slopes here, and c1 = -1 below keeps them out
    # Barycentric weights of corners 1 and 2, and the depth, as affine functions a*px + b*py + c of the pixel.
    a1, b1 = (y[:, 2] - y[:, 0]) / area, (x[:, 0] - x[:, 2]) / area
    a2, b2 = (y[:, 0] - y[:, 1]) / area, (x[:, 1] - x[:, 0]) / area
    c1, c2 = -(a1 * x[:, 0] + b1 * y[:, 0]), -(a2 * x[:, 0] + b2 * y[:, 0])
    dz1, dz2 = z[:, 1] - z[:, 0], z[:, 2] - z[:, 0]
    c1 = np.where(np.isfinite(area), c1, -1.0)
    coef = np.stack(
        [
            np.stack([a1, b1, c1], 1),
            np.stack([a2, b2, c2], 1),
            np.stack([a1 * dz1 + a2 * dz2, b1 * dz1 + b2 * dz2, z[:, 0] + c1 * dz1 + c2 * dz2], 1),
        ],
        1,
    )

    col0 = np.clip(np.ceil(x.min(1) - 0.5), 0, size).astype(np.int64)
    col1 = np.clip(np.floor(x.max(1) - 0.5), -1, size - 1).astype(np.int64)
    row0 = np.clip(np.ceil(y.min(1) - 0.5), 0, size).astype(np.int64)
    row1 = np.clip(np.floor(y.max(1) - 0.5), -1, size - 1).astype(np.int64)
    width = np.maximum(col1 - col0 + 1, 0)
    count = width * np.maximum(row1 - row0 + 1, 0)
    begin = np.cumsum(count) - count  # each face's first candidate in the concatenation of all faces' candidates

    depth = np.full(size * size, -np.inf)
    face = np.full(size * size, -1, np.int64)
    start = 0
    while start < len(count):
        stop = max(start + 1, int(np.searchsorted(begin, begin[start] + _CHUNK)))
        fid = np.repeat(np.arange(start, stop), count[start:stop])
        k = begin[start] + np.arange(len(fid)) - begin[fid]  # candidate's index within its face's bounding box
        col, row = col0[fid] + k % width[fid], row0[fid] + k // width[fid]
        c = coef[fid]
        w = c[:, :, 0] * (col + 0.5)[:, None] + c[:, :, 1] * (row + 0.5)[:, None] + c[:, :, 2]
        inside = (w[:, 0] >= -_EPS) & (w[:, 1] >= -_EPS) & (w[:, 0] + w[:, 1] <= 1 + _EPS)
        pix, d, fid = (row * size + col)[inside], w[inside, 2], fid[inside]
        order = np.lexsort((-d, pix))  # by pixel, nearest first
        pix, d, fid = pix[order], d[order], fid[order]
        first = np.diff(pix, prepend=-1) != 0
        pix, d, fid = pix[first], d[first], fid[first]
        nearer = d > depth[pix]
        depth[pix[nearer]], face[pix[nearer]] = d[nearer], fid[nearer]
        start = stop
    return face


def render_faces(
    vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, *, size: int = 320, camera: Camera = _DEFAULT_CAMERA
) -> np.ndarray:
    """(size, size, 3) uint8 flat-shaded orthographic view, each face in its (F, 3) RGB colour in [0, 1], white
    background.

    The `camera` follows matplotlib's 3D axes (azim about z, elev above the xy plane, degrees); the projected
    mesh is centred and scaled to fill the image up to a small margin. Shading is Lambert with the light at the
    camera (0.35 + 0.65 |n.l|), so colours keep their hue.
    """
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    colors = np.asarray(colors, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or colors.shape != (len(f), 3):
        raise ValueError(f"need vertices (V, 3), faces (F, 3), colors (F, 3); got {v.shape}, {f.shape}, {colors.shape}")
    image = np.full((size * size, 3), 255, np.uint8)
    if not len(f):
        return image.reshape(size, size, 3)
    right, up, toward = camera.axes()
    x, y, depth = v @ right, v @ up, v @ toward
    scale = size * (1 - 2 * _MARGIN) / max(np.ptp(x), np.ptp(y), 1e-300)
    px = size / 2 + scale * (x - (x.min() + x.max()) / 2)
    py = size / 2 - scale * (y - (y.min() + y.max()) / 2)
    face_of = _rasterise(px[f], py[f], depth[f], size)

    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    shade = 0.35 + 0.65 * np.abs(normals @ toward) / np.maximum(np.linalg.norm(normals, axis=1), 1e-300)
    hit = face_of >= 0
    image[hit] = np.round(255 * (colors * shade[:, None])[face_of[hit]]).astype(np.uint8)
    return image.reshape(size, size, 3)


def render_labels(
    vertices: np.ndarray,
    faces: np.ndarray,
    labels: np.ndarray,
    n_labels: int,
    *,
    size: int = 320,
    camera: Camera = _DEFAULT_CAMERA,
) -> np.ndarray:
    """render_faces with each face in its label's colour (label_colors); labels outside [0, n_labels) are grey."""
    labels = np.asarray(labels, np.int64)
    if labels.shape != (len(faces),):
        raise ValueError(f"need one label per face: {len(faces)} faces, labels {labels.shape}")
    palette = np.vstack([label_colors(n_labels), UNLABELLED])
    colors = palette[np.where((labels >= 0) & (labels < n_labels), labels, n_labels)]
    return render_faces(vertices, faces, colors, size=size, camera=camera)


def value_colors(values: np.ndarray, cmap: str = "viridis", limits: tuple[float, float] | None = None) -> np.ndarray:
    """(F, 3) colours of per-face `values` by the colour map, from limits[0] to limits[1] (default: the values'
    2nd and 98th percentiles, so that a few extreme faces do not wash the map out)."""
    values = np.asarray(values, np.float64)
    lo, hi = limits if limits is not None else np.percentile(values, [2, 98])
    t = np.clip((values - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
    return colormaps[cmap](t)[:, :3]


def principal_pose(vertices: np.ndarray) -> np.ndarray:
    """The vertices in the frame of their principal axes, the longest as z (up in Camera's views) and the
    shortest as y (the default camera looks nearly along it): every mesh of a figure shown by the same rule,
    whatever pose its file has. Each axis points the way of the file's axis nearest to it, so a mesh stored
    upright (along +y or +z) stays upright."""
    v = np.asarray(vertices, np.float64)
    c = v - v.mean(axis=0)
    _, vecs = np.linalg.eigh(c.T @ c)  # ascending variance: shortest, middle, longest
    vecs *= np.sign(vecs[np.abs(vecs).argmax(axis=0), range(3)])
    return (c @ vecs)[:, [1, 0, 2]]


def _area_accuracy(vertices: np.ndarray, faces: np.ndarray, pred: np.ndarray, gt: np.ndarray) -> float:
    """Fraction of surface area whose predicted label equals the ground truth (the paper's accuracy)."""
    return area_weighted_accuracy(pred, gt, face_areas(np.asarray(vertices, np.float64), np.asarray(faces, np.int64)))


def _accuracy_title(title: str, accuracy: float) -> str:
    """`title` with the accuracy appended, e.g. "mesh 12 — accuracy 97.3 %"."""
    text = f"accuracy {100 * accuracy:.1f} %"
    return f"{title} — {text}" if title else text


def _figure(width_px: float, height_px: float, **kwargs) -> Figure:
    """A Figure drawn by Agg, detached from pyplot."""
    fig = Figure(figsize=(width_px / 100, height_px / 100), dpi=100, **kwargs)
    FigureCanvasAgg(fig)
    return fig


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def label_comparison_png(
    vertices: np.ndarray,
    faces: np.ndarray,
    pred: np.ndarray,
    gt: np.ndarray | None,
    label_names: list[str],
    *,
    title: str = "",
) -> bytes:
    """PNG: the mesh coloured by predicted (left) and ground-truth (right) labels from the same camera
    (`PANEL` pixels square each), a colour legend, and the area-weighted accuracy in the title. Without
    ground truth (gt None): the predicted labels alone, titled `title`."""
    size = PANEL
    n = len(label_names)
    panels = [(np.asarray(pred, np.int64), "predicted")]
    if gt is not None:
        panels.append((np.asarray(gt, np.int64), "ground truth"))
    handles = [Patch(color=c, label=name) for c, name in zip(label_colors(n), label_names)]
    if any(np.any((labels < 0) | (labels >= n)) for labels, _ in panels):
        handles.append(Patch(color=UNLABELLED, label="unlabelled"))
    columns = 1 + (len(handles) - 1) // 20
    fig = _figure(len(panels) * size + 130 * columns, size + 60, layout="constrained")
    for ax, (labels, name) in zip(np.atleast_1d(fig.subplots(1, len(panels))), panels):
        ax.imshow(render_labels(vertices, faces, labels, n, size=size), interpolation="nearest")
        ax.set_title(name)
        ax.set_axis_off()
    fig.legend(handles=handles, loc="outside right center", ncols=columns, fontsize="small", frameon=False)
    fig.suptitle(title if gt is None else _accuracy_title(title, _area_accuracy(vertices, faces, panels[0][0], gt)))
    return _png(fig)


def _row_normalise(matrix: np.ndarray) -> np.ndarray:
    """Each row divided by its sum (per ground-truth class: where its area went); all-zero rows stay zero."""
    m = np.asarray(matrix, np.float64)
    sums = m.sum(1, keepdims=True)
    return np.divide(m, sums, out=np.zeros_like(m), where=sums != 0)


def confusion_png(matrix: np.ndarray, label_names: list[str], *, title: str = "") -> bytes:
    """PNG heat-map of the row-normalised confusion matrix (rows ground truth, columns predicted).

    Cells carry percentages when there are at most 15 classes; more would not be legible.
    """
    m = _row_normalise(matrix)
    k = len(m)
    if m.shape != (k, k) or len(label_names) != k:
        raise ValueError(f"need a square matrix with one name per class; got {m.shape} and {len(label_names)} names")
    side = 250 + 45 * k
    fig = _figure(side + 100, side)
    ax = fig.add_subplot()
    im = ax.imshow(m, cmap="Blues", vmin=0, vmax=1)
    ax.set_xticks(range(k), label_names, rotation=45, ha="right", rotation_mode="anchor")
    ax.set_yticks(range(k), label_names)
    ax.set_xlabel("predicted")
    ax.set_ylabel("ground truth")
    if k <= 15:
        for (i, j), value in np.ndenumerate(m):
            ax.text(
                j,
                i,
                f"{100 * value:.0f}%",
                ha="center",
                va="center",
                fontsize="small",
                color="white" if value > 0.5 else "black",
            )
    fig.colorbar(im, ax=ax, format=PercentFormatter(xmax=1))
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _png(fig)


@dataclass(frozen=True)
class Panel:
    """One picture of a grid: an image (None: nothing to draw, `title` says why) and its title."""

    image: np.ndarray | None
    title: str


def grid_png(
    panels: list[list[Panel]],
    *,
    title: str = "",
    row_titles: list[str] | None = None,
    legends: list[list[tuple[str, tuple[float, float, float]]]] | None = None,
    note: str = "",
) -> bytes:
    """PNG of a grid of panels (rows of equal length), each with its title; `row_titles` at the left of each
    row, `legends` (per grid column: (name, colour) pairs, or empty) under each column, `note` under the grid."""
    n_rows, n_cols = len(panels), len(panels[0])
    size = max((p.image.shape[0] for r in panels for p in r if p.image is not None), default=PANEL)
    legend_rows = max((len(g) for g in legends or []), default=0)
    fig = _figure(n_cols * (size + 20) + 120, n_rows * (size + 50) + 90 + 16 * legend_rows, layout="constrained")
    axes = np.atleast_2d(fig.subplots(n_rows, n_cols, squeeze=False))
    for i, row in enumerate(panels):
        for j, panel in enumerate(row):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            for side in ax.spines.values():
                side.set_visible(False)
            if panel.image is not None:
                ax.imshow(panel.image, interpolation="nearest")
            else:
                ax.imshow(np.full((size, size, 3), 255, np.uint8))
            ax.set_title(panel.title, fontsize="small")
            if row_titles and j == 0:
                ax.set_ylabel(row_titles[i])
            if legends and i == n_rows - 1 and legends[j]:
                handles = [Patch(color=c, label=name) for name, c in legends[j]]
                ax.legend(
                    handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0), fontsize="x-small", frameon=False
                )
    if title:
        fig.suptitle(title, fontsize="medium")
    if note:
        fig.supxlabel(note, fontsize="small")
    return _png(fig)


def feature_image_png(
    image: np.ndarray, bands: list[tuple[str, int, int]], *, title: str = "", cmap: str = "coolwarm"
) -> bytes:
    """PNG of a feature vector laid out as an image (ToG15's 30 x 20), values symmetric about 0, with `bands`
    ((name, first, stop) flat indices of each feature family, row-major) parted by lines and named at the left."""
    h, w = image.shape
    fig = _figure(140 + 22 * w, 90 + 22 * h, layout="constrained")
    ax = fig.add_subplot()
    limit = float(np.nanmax(np.abs(image))) or 1.0
    im = ax.imshow(image, cmap=cmap, vmin=-limit, vmax=limit, interpolation="nearest")
    ticks, names = [], []
    for name, first, stop in bands:
        at = (first // w + (stop - 1) // w) / 2
        if ticks and at - ticks[-1] < 1:  # bands sharing a row: one label, or the names overprint
            names[-1] += f", {name}"
        else:
            ticks.append(at)
            names.append(name)
        if first > 0:  # the staircase between flat indices < first and >= first (cells are 1 x 1)
            r, c = divmod(first, w)
            x = [-0.5, c - 0.5, c - 0.5, w - 0.5] if c else [-0.5, w - 0.5]
            y = [r + 0.5, r + 0.5, r - 0.5, r - 0.5] if c else [r - 0.5, r - 0.5]
            ax.plot(x, y, color="black", linewidth=1.5)
    ax.set_yticks(ticks, names, fontsize="small")
    ax.set_xticks([])
    fig.colorbar(im, ax=ax, shrink=0.8)
    if title:
        ax.set_title(title, fontsize="small")
    return _png(fig)
