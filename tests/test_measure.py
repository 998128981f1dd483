"""Volumes and bounding boxes against closed forms."""

import numpy as np
import pytest

from volpuzzle.spline import Volume
from volpuzzle.spline.measure import bbox, control_net_bbox, volume


def quarter_cylinder_shell(r1=1.0, r2=2.0, h=3.0):
    """Exact rational quarter annulus (weights 1, sqrt(1/2), 1) extruded along z."""
    circ = np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    cp = np.zeros((3, 2, 2, 3))
    for i in range(3):
        for j, r in enumerate((r1, r2)):
            for k, z in enumerate((0.0, h)):
                cp[i, j, k] = [r * circ[i, 0], r * circ[i, 1], z]
    w = np.ones((3, 2, 2))
    w[1] = np.sqrt(0.5)
    return Volume((2, 1, 1), [[0, 0, 0, 1, 1, 1], [0, 0, 1, 1], [0, 0, 1, 1]], cp, w)


def test_unit_cube():
    g = np.stack(np.meshgrid([0.0, 1.0], [0.0, 1.0], [0.0, 1.0], indexing="ij"), axis=-1)
    vol = Volume((1, 1, 1), [[0, 0, 1, 1]] * 3, g)
    assert volume(vol) == pytest.approx(1.0, rel=1e-14)
    np.testing.assert_allclose(bbox(vol), [[0, 0, 0], [1, 1, 1]], atol=1e-14)


def test_affine_box_with_refined_knots():
    rng = np.random.default_rng(21)
    g = np.stack(np.meshgrid([0.0, 1.0], [0.0, 1.0], [0.0, 1.0], indexing="ij"), axis=-1)
    vol = Volume((1, 1, 1), [[0, 0, 1, 1]] * 3, g).insert_knot(0, 0.3).insert_knot(2, 0.6)
    m = rng.normal(size=(3, 3)) + 2 * np.eye(3)
    off = rng.normal(size=3)
    box = vol.transformed(m, off)
    assert volume(box) == pytest.approx(abs(np.linalg.det(m)), rel=1e-12)
    corners = g.reshape(-1, 3) @ m.T + off
    np.testing.assert_allclose(bbox(box), [corners.min(0), corners.max(0)], atol=1e-12)


def test_rational_quarter_cylinder_shell():
    vol = quarter_cylinder_shell(1.0, 2.0, 3.0)
    assert volume(vol) == pytest.approx(np.pi / 4 * (4 - 1) * 3, rel=1e-10)
    np.testing.assert_allclose(bbox(vol), [[0, 0, 0], [2, 2, 3]], atol=1e-9)
    # rotated by 45 degrees about z, the outer arc's extreme lies inside a face: x_max = 2, not a control point
    c = np.cos(np.pi / 4)
    rot = np.array([[c, -c, 0], [c, c, 0], [0, 0, 1.0]])
    b = bbox(vol.transformed(rot))
    assert b[0, 0] == pytest.approx(-2 * c, abs=1e-9)
    assert b[1, 1] == pytest.approx(2.0, abs=1e-9)
    net = control_net_bbox(vol.transformed(rot))
    assert np.all(net[0] <= b[0] + 1e-12) and np.all(net[1] >= b[1] - 1e-12)
    assert net[1, 1] > 2.0 + 1e-3  # the control net box is looser


def test_finely_refined_shell_keeps_its_volume_and_box():
    """A model of many spans (60 along the arc, as a refined shell has) is sampled more sparsely per span for its box
    and starts its quadrature lower: the closed forms still hold, the rotated extreme inside a face included."""
    c = np.cos(np.pi / 4)
    vol = quarter_cylinder_shell(1.0, 2.0, 3.0).transformed(np.array([[c, -c, 0], [c, c, 0], [0, 0, 1.0]]))
    for t in np.linspace(0, 1, 62)[1:-1]:
        vol = vol.insert_knot(0, t)
    assert volume(vol) == pytest.approx(np.pi / 4 * (4 - 1) * 3, rel=1e-10)
    b = bbox(vol)
    assert b[0, 0] == pytest.approx(-2 * c, abs=1e-9) and b[1, 1] == pytest.approx(2.0, abs=1e-9)
    np.testing.assert_allclose(b[:, 2], [0, 3], atol=1e-12)
