"""Rendering for run tracking: palette, camera, hidden surfaces, and the two PNG pictures."""

import io

import numpy as np
import pytest
import trimesh
from matplotlib.figure import Figure
from matplotlib.image import imread
from mpl_toolkits.mplot3d import proj3d

from meshseg.render import (
    UNLABELLED,
    Camera,
    _accuracy_title,
    _area_accuracy,
    _row_normalise,
    confusion_png,
    label_colors,
    label_comparison_png,
    render_labels,
)

SIZE = 90


def shows(pixel: np.ndarray, rgb: np.ndarray) -> bool:
    """Whether a rendered pixel is `rgb` times some shading factor (shading keeps the RGB ratios)."""
    p, c = pixel.astype(float), 255 * np.asarray(rgb, float)
    scale = p @ c / (c @ c)
    return 0.3 < scale <= 1.01 and np.abs(p - scale * c).max() < 3


def two_squares():
    """2x2 squares facing +-x: label 0 in the plane x = 0 over y, z in [0, 2]; label 1 at x = 1 over [1, 3].

    They overlap where y, z are in [1, 2]; viewed from +x (azim 0) the label-1 square is in front.
    """
    far = [[0, 0, 0], [0, 2, 0], [0, 2, 2], [0, 0, 2]]
    near = [[1, 1, 1], [1, 3, 1], [1, 3, 3], [1, 1, 3]]
    faces = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]
    return np.array(far + near, float), np.array(faces), np.array([0, 0, 1, 1])


def pixel_of(y: float, z: float, mirrored: bool) -> tuple[int, int]:
    """(row, col) of world point (., y, z) of two_squares() seen from +x (y right) or -x (y left); z is up."""
    col = (3 - y if mirrored else y) / 3 * SIZE
    return int((1 - z / 3) * SIZE), int(col)


def test_palette_distinct_deterministic_and_prefix_stable():
    for n in range(1, 31):
        c = label_colors(n)
        assert c.shape == (n, 3) and c.min() >= 0 and c.max() <= 1
        with_grey = np.vstack([c, UNLABELLED])
        dist = np.linalg.norm(with_grey[:, None] - with_grey[None], axis=-1) + np.eye(n + 1)
        assert dist.min() > 0.05, n
        np.testing.assert_array_equal(c, label_colors(n))
        np.testing.assert_array_equal(c, label_colors(30)[:n])
    assert label_colors(0).shape == (0, 3)


@pytest.mark.parametrize("elev, azim", [(20, -60), (0, 0), (90, -90), (35, 120), (-40, 200)])
def test_camera_matches_matplotlib_3d_axes(elev, azim):
    ax = Figure().add_subplot(projection="3d", proj_type="ortho")
    ax.set(xlim=(-1, 1), ylim=(-1, 1), zlim=(-1, 1))
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    xs, ys, _ = proj3d.proj_transform(*np.vstack([np.zeros(3), np.eye(3)]).T, ax.get_proj())
    theirs = np.stack([xs[1:] - xs[0], ys[1:] - ys[0]], 1)
    right, up, toward = Camera(elev, azim).axes()
    ours = np.stack([right, up], 1)
    np.testing.assert_allclose(ours / np.abs(ours).max(), theirs / np.abs(theirs).max(), atol=1e-9)
    np.testing.assert_allclose(np.cross(right, up), toward, atol=1e-12)


@pytest.mark.parametrize("azim, front, mirrored", [(0, 1, False), (180, 0, True)])
def test_nearer_square_hides_farther(azim, front, mirrored):
    v, f, labels = two_squares()
    img = render_labels(v, f, labels, 2, size=SIZE, camera=Camera(elev=0, azim=azim))
    colors = label_colors(2)
    assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8
    assert shows(img[pixel_of(0.5, 0.5, mirrored)], colors[0])  # only the label-0 square is there
    assert shows(img[pixel_of(2.5, 2.5, mirrored)], colors[1])  # only the label-1 square is there
    overlap = img[pixel_of(1.5, 1.5, mirrored)]
    assert shows(overlap, colors[front]) and not shows(overlap, colors[1 - front])
    for y, z in [(2.5, 0.5), (0.5, 2.5)]:  # neither square
        assert (img[pixel_of(y, z, mirrored)] == 255).all()


def test_background_white_and_mesh_fills_image():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    img = render_labels(sphere.vertices, sphere.faces, np.zeros(len(sphere.faces), int), 1, size=SIZE)
    for corner in [(0, 0), (0, -1), (-1, 0), (-1, -1)]:
        assert (img[corner] == 255).all()
    rows, cols = np.nonzero((img != 255).any(-1))
    assert max(np.ptp(rows), np.ptp(cols)) + 1 >= 0.9 * SIZE
    assert shows(img[SIZE // 2, SIZE // 2], label_colors(1)[0])


def test_cube_top_seen_from_above_bottom_from_below():
    box = trimesh.creation.box()
    labels = (box.face_normals[:, 2] > 0.5).astype(int)
    assert labels.sum() == 2
    colors = label_colors(2)
    for elev, label in [(90, 1), (-90, 0), (0, 0)]:
        img = render_labels(box.vertices, box.faces, labels, 2, size=SIZE, camera=Camera(elev=elev))
        centre = img[SIZE // 2, SIZE // 2]
        assert shows(centre, colors[label]) and not shows(centre, colors[1 - label]), elev


@pytest.mark.parametrize("label", [-1, 2])
def test_out_of_range_labels_are_grey(label):
    box = trimesh.creation.box()
    img = render_labels(box.vertices, box.faces, np.full(len(box.faces), label), 2, size=SIZE, camera=Camera(elev=90))
    assert shows(img[SIZE // 2, SIZE // 2], UNLABELLED)


def test_area_accuracy_and_title():
    # Face 0 has area 0.5 (right triangle, legs 1), face 1 has area 2 (legs 2).
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [2, 0, 1], [0, 2, 1]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    gt = np.array([0, 1])
    assert _area_accuracy(v, f, gt, gt) == 1.0
    assert _area_accuracy(v, f, np.array([0, 0]), gt) == pytest.approx(0.5 / 2.5)
    assert _area_accuracy(v, f, np.array([1, 1]), gt) == pytest.approx(2 / 2.5)
    assert _accuracy_title("mesh 12", 0.973) == "mesh 12 — accuracy 97.3 %"
    assert _accuracy_title("", 1.0) == "accuracy 100.0 %"


def test_label_comparison_png_is_two_panels_wide():
    box = trimesh.creation.box()
    gt = (box.face_normals[:, 2] > 0.5).astype(int)
    png = label_comparison_png(box.vertices, box.faces, 1 - gt, gt, ["side", "top"], title="mesh 1")
    assert png.startswith(b"\x89PNG")
    height, width = imread(io.BytesIO(png)).shape[:2]
    assert 1.6 < width / height < 2.6


def test_row_normalise():
    m = np.array([[2, 1, 1], [0, 0, 0], [0, 3, 1]])
    np.testing.assert_allclose(_row_normalise(m), [[0.5, 0.25, 0.25], [0, 0, 0], [0, 0.75, 0.25]])


@pytest.mark.parametrize("k", [3, 20])
def test_confusion_png_decodes(k):
    matrix = np.arange(k * k, dtype=float).reshape(k, k)
    png = confusion_png(matrix, [f"part {i}" for i in range(k)], title="fold 0")
    assert png.startswith(b"\x89PNG")
    assert imread(io.BytesIO(png)).ndim == 3


def test_batched_rasterisation_matches_single_batch(monkeypatch):
    import meshseg.render as render

    sphere = trimesh.creation.icosphere(subdivisions=2)
    labels = (sphere.triangles_center[:, 0] > 0).astype(int)
    whole = render_labels(sphere.vertices, sphere.faces, labels, 2, size=SIZE)
    monkeypatch.setattr(render, "_CHUNK", 37)  # many batches, most faces split across none, some alone
    np.testing.assert_array_equal(render_labels(sphere.vertices, sphere.faces, labels, 2, size=SIZE), whole)
