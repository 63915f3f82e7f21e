"""Surface segments and lever arms on clouds with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from policies.surface_segments import segment_levers, segment_surfaces, surface_levers


def _face(centre, size, spacing=0.005, normal=(0.0, 0.0, 1.0)):
    """A horizontal square grid of points (normals up) centred at ``centre``."""
    ticks = np.arange(-size / 2, size / 2 + 1e-9, spacing)
    u, v = np.meshgrid(ticks, ticks)
    points = np.c_[u.ravel(), v.ravel(), np.zeros(u.size)] + np.asarray(centre)
    return points, np.tile(normal, (len(points), 1))


def test_two_separate_box_tops_are_two_segments_with_levers_to_their_centres():
    (a, na), (b, nb) = _face((0.0, 0.0, 0.10), 0.10), _face((0.20, 0.0, 0.15), 0.08)
    points, normals = np.r_[a, b], np.r_[na, nb]
    labels = segment_surfaces(points, normals, radius=0.01)
    assert len(np.unique(labels[: len(a)])) == 1 and len(np.unique(labels[len(a):])) == 1
    assert labels[0] != labels[-1]
    levers = segment_levers(points, labels)
    np.testing.assert_allclose(points[: len(a)] + levers[: len(a), :3], np.tile((0.0, 0.0, 0.10), (len(a), 1)),
                               atol=1e-6)
    np.testing.assert_allclose(levers[:, 3], np.linalg.norm(levers[:, :2], axis=1), rtol=1e-6)
    centre = np.argmin(np.linalg.norm(a[:, :2], axis=1))
    corner = np.argmax(np.linalg.norm(a[:, :2], axis=1))
    assert levers[centre, 3] < 1e-6 and levers[corner, 3] == pytest.approx(np.hypot(0.05, 0.05), rel=1e-5)


def test_a_crease_cuts_touching_faces_and_agreeing_normals_join_them():
    top, n_top = _face((0.0, 0.0, 0.0), 0.06)
    # a vertical face hanging from the top's edge at x = 0.03, 5 mm from it
    ticks = np.arange(-0.03, 0.03 + 1e-9, 0.005)
    y, z = np.meshgrid(ticks, -ticks - 0.03)  # z from -0.06 up to 0
    side = np.c_[np.full(y.size, 0.035), y.ravel(), z.ravel()]
    points, normals = np.r_[top, side], np.r_[n_top, np.tile((1.0, 0.0, 0.0), (len(side), 1))]
    labels = segment_surfaces(points, normals, radius=0.008, min_cos=0.8)
    assert set(labels[: len(top)]).isdisjoint(labels[len(top):])
    assert len(np.unique(segment_surfaces(points, normals, radius=0.008, min_cos=-1.0))) == 1


def test_empty_and_bad_inputs():
    assert segment_surfaces(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)
    assert surface_levers(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 4)
    one = surface_levers(np.ones((1, 3)), np.array([[0.0, 0.0, 1.0]]))
    np.testing.assert_array_equal(one, np.zeros((1, 4)))  # a lone point is its own centre
    with pytest.raises(ValueError, match="both be"):
        segment_surfaces(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="radius"):
        segment_surfaces(np.zeros((5, 3)), np.zeros((5, 3)), radius=0.0)
    with pytest.raises(ValueError, match="one label per point"):
        segment_levers(np.zeros((5, 3)), np.zeros(4, dtype=int))
