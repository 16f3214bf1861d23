"""The stacked second stage's context features (meshseg/features/label_context.py) on meshes small enough to
work out by hand."""

import numpy as np
import pytest

from meshseg.errors import ConfigError
from meshseg.features.label_context import LabelContext, label_context

# a unit square cut along its diagonal 0-2: two faces of area 1/2 whose centres (2/3, 1/3) and (1/3, 2/3)
# lie sqrt(2)/6 from the shared edge's midpoint (1/2, 1/2)
SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])
# the 2010 units: both centres lie sqrt(2)/6 from the area-weighted centroid, so unit = sqrt(2)/6 * 0.5/0.33
UNIT = np.sqrt(2) / 6 * 0.5 / 0.33
DUAL = np.sqrt(2) / 3  # centre -> midpoint -> centre
WEIGHT = np.sqrt(2) / DUAL  # shared edge length / dual length = 3


def test_two_faces_by_hand():
    P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # face 0 is class 0, face 1 class 1, class 2 nowhere
    settings = LabelContext(radii=(0.1,), share=True, distance=True, distance_cap=2.0)
    got = label_context(SQUARE_V, SQUARE_F, P, settings)
    assert settings.names(3) == [
        *(f"smooth_r0.1/{c}" for c in range(3)),
        *(f"share/{c}" for c in range(3)),
        *(f"distance/{c}" for c in range(3)),
    ]
    assert got.shape == (2, 9) and got.dtype == np.float32
    # (A + s L) Q = A P with A = diag(1/2, 1/2), s = (r unit)^2 * WEIGHT: a 2x2 system
    s = (0.1 * UNIT) ** 2 * WEIGHT
    own, other = 0.5 * (0.5 + s) / (0.25 + s), 0.5 * s / (0.25 + s)
    np.testing.assert_allclose(got[:, 0:3], [[own, other, 0], [other, own, 0]], rtol=1e-6)
    np.testing.assert_allclose(got[:, 3:6], [[0.5, 0.5, 0], [0.5, 0.5, 0]], rtol=1e-6)
    # one dual edge to the other class: (sqrt(2)/3) / unit = 2 x 0.33 / 0.5 = 1.32; class 2 absent: the cap
    np.testing.assert_allclose(got[:, 6:9], [[0, 1.32, 2.0], [1.32, 0, 2.0]], rtol=1e-6)


def test_a_wide_radius_averages_the_whole_component_and_a_small_one_keeps_the_face():
    P = np.array([[0.9, 0.1], [0.2, 0.8]])
    got = label_context(SQUARE_V, SQUARE_F, P, LabelContext(radii=(1e4, 1e-4), share=False, distance=False))
    wide, narrow = got[:, :2], got[:, 2:]
    np.testing.assert_allclose(wide, [[0.55, 0.45], [0.55, 0.45]], atol=1e-6)
    np.testing.assert_allclose(narrow, P, atol=1e-6)


# three faces of areas 1/2, 3/2 and 1 (worked out from the cross products), joined through edges 0-1 and 1-2
FAN_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 0], [0.5, -2, 0]], float)
FAN_F = np.array([[0, 1, 2], [1, 3, 2], [1, 0, 4]])


def test_shares_and_a_wide_radius_weigh_faces_by_area():
    P = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]])
    # area-weighted: class 0 (1/2 + 1/2) / 3 = 1/3, class 1 (3/2 + 1/2) / 3 = 2/3 (a plain mean: 1/2, 1/2)
    got = label_context(FAN_V, FAN_F, P, LabelContext(radii=(1e4,), share=True, distance=False))
    np.testing.assert_allclose(got, np.tile([1 / 3, 2 / 3, 1 / 3, 2 / 3], (3, 1)), atol=1e-6)


def test_moving_and_scaling_a_mesh_changes_no_context_feature():
    P = np.array([[0.7, 0.2, 0.1], [0.1, 0.3, 0.6], [0.2, 0.7, 0.1]])
    settings = LabelContext(radii=(0.05, 0.4), share=True, distance=True, distance_cap=50.0)
    here = label_context(FAN_V, FAN_F, P, settings)
    there = label_context(FAN_V * 7 + [3, -5, 11], FAN_F, P, settings)
    assert here[:, 6:9].max() > 0 and 0 < here[:, -3:].max() < 50  # every group says something here
    np.testing.assert_allclose(there, here, rtol=1e-5, atol=1e-7)


def test_a_class_in_another_component_is_at_the_cap():
    # the square and a second square far away, not joined: distances never cross between them
    V = np.vstack([SQUARE_V, SQUARE_V + [10, 0, 0]])
    F = np.vstack([SQUARE_F, SQUARE_F + 4])
    P = np.array([[1, 0], [1, 0], [0, 1], [0, 1]], float)
    got = label_context(V, F, P, LabelContext(radii=(), share=False, distance=True, distance_cap=3.0))
    assert got[:2, 1].tolist() == [3.0, 3.0] and got[2:, 0].tolist() == [3.0, 3.0]
    assert got[:2, 0].tolist() == [0.0, 0.0]


@pytest.mark.parametrize(
    "settings, message",
    [
        ({"radii": [0.1, 0.0]}, "every radius must be > 0"),
        ({"distance_cap": 0}, "distance_cap=0: must be > 0"),
        ({"radius": [0.1]}, "unknown settings ['radius']"),
        ({"radii": [], "share": False, "distance": False}, "no group left"),
    ],
)
def test_bad_settings_are_named(settings, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        LabelContext.of(settings)
