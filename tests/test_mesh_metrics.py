"""Mesh validation and the paper's area-weighted accuracy on hand-computed cases."""

import re

import numpy as np
import pytest

from meshseg.data.mesh import Mesh, MeshDataError
from meshseg.metrics import area_weighted_accuracy, confusion_matrix, mean_by

# Four faces of areas 0.5, 2, 1.5 and 0 (the last is degenerate: three collinear points).
V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [0, 2, 0], [3, 0, 0]], float)
F = np.array([[0, 1, 2], [0, 3, 4], [0, 5, 2], [0, 1, 3]])
GT = np.array([0, 1, 1, 0])


def four_face_mesh(**kw):
    return Mesh(V, F, kw.pop("labels", GT), kw.pop("label_names", ("a", "b")), source="four.off", **kw)


def test_face_areas_and_degenerate_faces_are_kept():
    m = four_face_mesh()
    np.testing.assert_allclose(m.face_areas, [0.5, 2.0, 1.5, 0.0])
    assert m.n_faces == 4 and m.n_degenerate == 1


@pytest.mark.parametrize(
    "pred, expected",
    [
        ([0, 1, 0, 1], 2.5 / 4.0),  # unweighted would be 0.5
        ([0, 0, 1, 0], 2.0 / 4.0),  # unweighted would be 0.75
        ([0, 1, 1, 1], 1.0),  # only the zero-area face is wrong
        ([1, 0, 0, 1], 0.0),
    ],
)
def test_area_weighted_accuracy_hand_computed(pred, expected):
    m = four_face_mesh()
    assert area_weighted_accuracy(np.array(pred), m.labels, m.face_areas) == pytest.approx(expected, abs=1e-15)


def test_accuracy_rejects_mismatched_or_zero_area():
    with pytest.raises(ValueError, match="equal-length"):
        area_weighted_accuracy(np.zeros(3), np.zeros(4), np.ones(4))
    with pytest.raises(ValueError, match="zero"):
        area_weighted_accuracy(np.zeros(2), np.zeros(2), np.zeros(2))


def test_confusion_matrix_counts_and_areas():
    m = four_face_mesh()
    pred = np.array([0, 1, 0, 1])
    np.testing.assert_array_equal(confusion_matrix(pred, m.labels, 2), [[1, 1], [1, 1]])
    np.testing.assert_allclose(confusion_matrix(pred, m.labels, 2, m.face_areas), [[0.5, 0.0], [1.5, 2.0]])


def test_mean_by_groups():
    assert mean_by([1.0, 0.5, 0.0, 0.25], ["f0", "f0", "f1", "f1"]) == {"f0": 0.75, "f1": 0.125}


@pytest.mark.parametrize(
    "kw, problem",
    [
        (dict(faces=F + 3), "face 1 has vertex index 6 outside 0..5 (3 such faces)"),
        (dict(faces=-F - 1), "outside 0..5"),
        (
            dict(vertices=np.where(np.arange(18).reshape(6, 3) == 7, np.nan, V)),
            "1 vertices have NaN/inf coordinates (first: vertex 2)",
        ),
        (dict(vertices=np.where(np.arange(18).reshape(6, 3) == 0, np.inf, V)), "NaN/inf"),
        (dict(faces=np.c_[F, F[:, :1]]), "only triangle faces are supported, got 4"),
        (dict(faces=F.astype(float)), "face indices must be integers"),
        (dict(vertices=np.zeros((0, 3))), "vertices must be a non-empty"),
        (dict(labels=GT[:3]), "3 labels for 4 faces"),
        (dict(labels=np.array([0, 1, 2, 0])), "unknown label id 2 on face 2"),
    ],
)
def test_mesh_validation_errors_name_the_source(kw, problem):
    args = dict(vertices=V, faces=F, labels=GT, label_names=("a", "b"), source="four.off") | kw
    with pytest.raises(MeshDataError, match=re.escape(problem)) as e:
        Mesh(**args)
    assert str(e.value).startswith("four.off: ")


def test_content_hash_tracks_geometry():
    a, b = four_face_mesh(), four_face_mesh(labels=np.array([1, 1, 1, 1]))
    assert a.content_hash == b.content_hash
    assert Mesh(V * 2, F).content_hash != a.content_hash
