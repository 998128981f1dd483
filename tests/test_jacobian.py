"""The exact Jacobian polynomial and the sign certificates."""

import sys
from pathlib import Path

import numpy as np
import pytest

from volpuzzle.spline import Volume
from volpuzzle.spline.jacobian import (
    Certificate,
    JacobianSpline,
    certify_negative,
    certify_positive,
    jacobian_bezier,
    orientation,
)

sys.path.insert(0, str(Path(__file__).parent))
from test_spline_volume import random_volume  # noqa: E402


def weight_function(vol):
    """W(u, v, w) as a polynomial Volume, to turn det J into the W^4 det J the rational polynomial holds."""
    cp = np.zeros(vol.shape + (3,))
    cp[..., 0] = vol.weights
    return Volume(vol.degrees, vol.knots, cp)


def identity_grid(degrees, counts, lo=0.0, hi=1.0):
    knots = [np.r_[[lo] * (p + 1), np.linspace(lo, hi, n - p + 1)[1:-1], [hi] * (p + 1)]
             for p, n in zip(degrees, counts, strict=True)]
    # Greville abscissae reproduce the identity map exactly.
    gre = [np.array([k[i + 1:i + p + 1].mean() for i in range(n)])
           for k, p, n in zip(knots, degrees, counts, strict=True)]
    cp = np.stack(np.meshgrid(*gre, indexing="ij"), axis=-1)
    return knots, cp


@pytest.mark.parametrize("rational", [False, True])
@pytest.mark.parametrize("degrees,counts", [((3, 2, 1), (5, 4, 3)), ((1, 4, 2), (3, 6, 5))])
def test_polynomial_equals_sampled_determinant(degrees, counts, rational):
    rng = np.random.default_rng(11)
    vol = random_volume(rng, degrees, counts, rational)
    js = jacobian_bezier(vol)
    assert isinstance(js, JacobianSpline)
    assert js.degrees == tuple((4 if rational else 3) * p - 1 for p in degrees)
    uvw = rng.uniform(-2, 3, (2000, 3))
    det = np.linalg.det(vol.derivatives(uvw))
    want = det * weight_function(vol).evaluate(uvw)[:, 0] ** 4 if rational else det
    np.testing.assert_allclose(js.evaluate(uvw), want, atol=1e-10 * np.abs(want).max())


@pytest.mark.parametrize("rational", [False, True])
def test_coefficients_bound_1e5_samples(rational):
    rng = np.random.default_rng(12)
    vol = random_volume(rng, (3, 3, 2), (5, 5, 4), rational)
    js = jacobian_bezier(vol)
    uvw = rng.uniform(-2, 3, (100_000, 3))
    det = np.linalg.det(vol.derivatives(uvw))
    assert js.lower <= det.min() and js.upper >= det.max()
    if rational:
        det = det * weight_function(vol).evaluate(uvw)[:, 0] ** 4
    assert js.min <= det.min() and js.max >= det.max()
    assert js.min <= js.evaluate(js.argmin_uvw[None])[0] + 1e-12 * js.scale


def test_identity_is_proved_and_fast_path_is_consistent():
    knots, cp = identity_grid((3, 3, 3), (6, 6, 6))
    cert = certify_positive(Volume((3, 3, 3), knots, cp))
    assert isinstance(cert, Certificate)
    assert cert.status == "proved" and cert.sign == 1 and cert.min_coefficient > 0
    assert cert.value == pytest.approx(1.0)


def test_planted_fold_is_disproved_with_its_place():
    knots, cp = identity_grid((3, 3, 3), (6, 6, 6))
    cp = cp.copy()
    cp[2, 2:4, 2:4, 0] = 0.95  # pushes inner points past their u-neighbours: x decreases in u there
    vol = Volume((3, 3, 3), knots, cp)
    cert = certify_positive(vol)
    assert cert.status == "disproved"
    assert cert.value <= 0
    assert np.linalg.det(vol.derivatives(cert.where_uvw[None]))[0] <= 0
    assert orientation(vol).handedness == "folded"


def near_fold():
    """x(u) with control points 0, 0.9, 0.1, 1: x' > 0 (min 0.075)
    but its Bernstein coefficients are not all positive."""
    knots, cp = identity_grid((3, 1, 1), (4, 2, 2))
    cp = cp.copy()
    cp[:, :, :, 0] = np.array([0.0, 0.9, 0.1, 1.0])[:, None, None]
    return Volume((3, 1, 1), knots, cp)


def test_near_fold_is_proved_after_subdivision():
    vol = near_fold()
    js = jacobian_bezier(vol)
    assert js.min < 0  # a negative coefficient at depth 0 ...
    uvw = np.random.default_rng(13).random((20000, 3))
    assert np.linalg.det(vol.derivatives(uvw)).min() > 0  # ... though det J > 0
    cert = certify_positive(vol)
    assert cert.status == "proved" and cert.depth >= 1 and cert.min_coefficient > 0
    assert certify_positive(vol, max_depth=0).status == "unresolved"


def test_left_handed_model_is_recognised():
    knots, cp = identity_grid((2, 3, 2), (4, 5, 3))
    mirrored = Volume((2, 3, 2), knots, cp).transformed(np.diag([1.0, -1.0, 1.0]), np.zeros(3))
    assert certify_negative(mirrored).status == "proved"
    assert certify_positive(mirrored).status == "disproved"
    o = orientation(mirrored)
    assert o.handedness == "left" and o.sign == -1 and o.upper < 0


@pytest.mark.parametrize("power", [1, 2])
def test_collapsed_face_is_degenerate(power):
    # x = u, y = u v, z = u^(power-1) w: the face u = 0 collapses; det J = u^power (a double zero for power 2,
    # so an interior Bernstein index vanishes too, which the rule must accept).
    cp = np.zeros((2, 2, 2, 3))
    for i in range(2):
        for j in range(2):
            for k in range(2):
                cp[i, j, k] = [i, i * j, (i if power == 2 else 1) * k]
    vol = Volume((1, 1, 1), [[0, 0, 1, 1]] * 3, cp)
    cert = certify_positive(vol)
    assert cert.status == "degenerate", cert
    assert orientation(vol).handedness == "right"


def test_zero_on_an_interior_face_is_not_degenerate():
    # x(u) = (u - 1/2)^3, so det J = 3 (u - 1/2)^2 vanishes on the interior plane u = 1/2.
    knots = [[0, 0, 0, 0, 1, 1, 1, 1], [0, 0, 1, 1], [0, 0, 1, 1]]
    cp = np.zeros((4, 2, 2, 3))
    xs = np.array([-1, 1, -1, 1]) / 8  # Bernstein coefficients of (u - 1/2)^3
    for j in range(2):
        for k in range(2):
            cp[:, j, k] = np.stack([xs, np.full(4, j), np.full(4, k)], axis=1)
    vol = Volume((3, 1, 1), knots, cp)
    cert = certify_positive(vol)
    assert cert.status == "disproved"
    assert abs(cert.where_uvw[0] - 0.5) < 0.05


def test_rational_quarter_shell_is_left_handed_and_its_bounds_hold():
    from test_measure import quarter_cylinder_shell
    vol = quarter_cylinder_shell()
    o = orientation(vol)
    assert o.handedness == "left" and o.certificate.status == "proved"
    uvw = np.random.default_rng(14).random((5000, 3))
    det = np.linalg.det(vol.derivatives(uvw))
    assert o.lower <= det.min() and det.max() <= o.upper < 0
