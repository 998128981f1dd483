"""randomize: R keeps D's boundary, maps D onto D, is reproducible from the seed, and respects periodic seams."""

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle.errors import SpecError
from volpuzzle.randomize import family_from_spec, warp_family
from volpuzzle.spec import RandomizeSpec
from volpuzzle.spline import Volume
from volpuzzle.spline.knots import greville, uniform_knots
from volpuzzle.spline.seams import Seam

DOMAIN = np.array([[0.0, -1.0, 2.0], [1.0, 3.0, 2.5]])  # unequal extents catch mixed-up axes


def _family(seed=7, n=6, domain=DOMAIN, seams=None):
    return warp_family(domain, n, np.random.default_rng(seed), seams)


def _face_points(domain, axis, side, rng, k=200):
    uvw = domain[0] + rng.uniform(size=(k, 3)) * (domain[1] - domain[0])
    uvw[:, axis] = domain[side, axis]
    return uvw


def _edge_points(domain, rng, k=40):
    out = []
    for a in range(3):  # edges parallel to axis a
        b, c = (x for x in range(3) if x != a)
        for sb in (0, 1):
            for sc in (0, 1):
                uvw = np.empty((k, 3))
                uvw[:, a] = domain[0, a] + rng.uniform(size=k) * (domain[1, a] - domain[0, a])
                uvw[:, b] = domain[sb, b]
                uvw[:, c] = domain[sc, c]
                out.append(uvw)
    return np.concatenate(out)


def _check_boundary(R, domain, rng):
    corners = np.array([[domain[i, 0], domain[j, 1], domain[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    np.testing.assert_allclose(R.evaluate(corners), corners, rtol=0, atol=1e-12)
    edges = _edge_points(domain, rng)
    np.testing.assert_allclose(R.evaluate(edges), edges, rtol=0, atol=1e-12)
    for a in range(3):
        for side in (0, 1):
            face = _face_points(domain, a, side, rng)
            img = R.evaluate(face)
            assert np.max(np.abs(img[:, a] - domain[side, a])) <= 1e-12
            assert np.all(img >= domain[0] - 1e-12) and np.all(img <= domain[1] + 1e-12)


def test_identity_at_greville_and_zero_amplitude():
    k = uniform_knots(6, 0.0, 1.0)
    np.testing.assert_allclose(greville(k), [0, 1 / 9, 1 / 3, 2 / 3, 8 / 9, 1], atol=1e-15)
    R = _family()(0.0)
    x = DOMAIN[0] + np.random.default_rng(0).uniform(size=(500, 3)) * (DOMAIN[1] - DOMAIN[0])
    np.testing.assert_allclose(R.evaluate(x), x, atol=1e-12)


def test_warp_is_cubic_on_D_and_actually_moves():
    fam = _family()
    R = fam(0.25)
    assert isinstance(R, Volume) and R.degrees == (3, 3, 3) and R.shape == (6, 6, 6)
    assert np.array_equal(R.domain_array, DOMAIN)
    moved = np.abs(R.control_points - fam(0.0).control_points)
    spacing = (DOMAIN[1] - DOMAIN[0]) / 5
    assert moved.max() > 0
    # |displacement_a| <= amplitude * spacing_a, and the interior reaches a good part of it
    assert np.all(moved <= 0.25 * spacing + 1e-15)
    assert np.all(moved[1:-1, 1:-1, 1:-1].max(axis=(0, 1, 2)) > 0.15 * spacing)


def test_boundary_kept():
    _check_boundary(_family()(0.25), DOMAIN, np.random.default_rng(1))


def test_boundary_kept_even_when_large():
    # Past the certifiable range the map may fold, but the boundary and R(D) inside D still hold (clamped net).
    R = _family(n=8)(3.0)
    _check_boundary(R, DOMAIN, np.random.default_rng(2))
    assert np.all(R.control_points >= DOMAIN[0]) and np.all(R.control_points <= DOMAIN[1])


def test_maps_D_onto_D():
    R = _family()(0.25)
    cp = R.control_points.reshape(-1, 3)
    assert np.all(cp >= DOMAIN[0]) and np.all(cp <= DOMAIN[1])  # convex hull: R(D) inside D
    # onto: Newton finds a preimage in D for random targets, interior and on faces
    rng = np.random.default_rng(3)
    y = DOMAIN[0] + rng.uniform(size=(300, 3)) * (DOMAIN[1] - DOMAIN[0])
    y[:50, 0] = DOMAIN[1, 0]
    y[50:100, 2] = DOMAIN[0, 2]
    x = y.copy()
    for _ in range(40):
        p, J = R.evaluate_with_derivatives(x)
        x = np.clip(x - np.linalg.solve(J, (p - y)[:, :, None])[:, :, 0], DOMAIN[0], DOMAIN[1])
    np.testing.assert_allclose(R.evaluate(x), y, atol=1e-10)


def test_same_seed_same_net_bitwise_and_seeds_differ():
    a = _family(seed=11)(0.25).control_points
    b = _family(seed=11)(0.25).control_points
    assert a.tobytes() == b.tobytes()
    c = _family(seed=12)(0.25).control_points
    assert not np.array_equal(a, c)
    spec = RandomizeSpec(seed=11, amplitude=0.25, control_points=6)
    d = family_from_spec(DOMAIN, spec, np.random.default_rng(11))(spec.amplitude)
    assert d.control_points.tobytes() == a.tobytes()


def test_amplitude_scales_one_field():
    fam = _family()
    d1 = fam(0.1).control_points - fam(0.0).control_points
    d2 = fam(0.2).control_points - fam(0.0).control_points
    np.testing.assert_allclose(d2, 2 * d1, atol=1e-14)


def test_randomize_none_and_zero():
    assert family_from_spec(DOMAIN, None, np.random.default_rng(0)) is None
    assert family_from_spec(DOMAIN, RandomizeSpec(1, 0.0, 6), np.random.default_rng(0)) is None
    spec = RandomizeSpec(seed=1, amplitude=0.2, control_points=5)
    R = family_from_spec(DOMAIN.T, spec, np.random.default_rng(1))(spec.amplitude)  # ((u0, u1), ...) form too
    assert R.shape == (5, 5, 5) and np.array_equal(R.domain_array, DOMAIN)


def test_too_few_control_points():
    with pytest.raises(SpecError, match=r"randomize.control_points: .*got 3, expected >= 4"):
        warp_family(DOMAIN, 3, np.random.default_rng(0))


def test_negative_amplitude_refused():
    with pytest.raises(SpecError, match=r"randomize.amplitude: must be a finite number >= 0 \(got -0.1"):
        family_from_spec(DOMAIN, RandomizeSpec(1, -0.1, 6), np.random.default_rng(0))


SYMMETRIES = [(s, (f0, f1)) for s in (False, True) for f0 in (False, True) for f1 in (False, True)]


@pytest.mark.parametrize("amplitude", [0.25, 3.0])  # 3.0: control points clamped into D, the seam must still hold
@pytest.mark.parametrize("axis", [0, 2])
@pytest.mark.parametrize("swap,flip", SYMMETRIES)
def test_periodic_faces_agree_under_seam(axis, swap, flip, amplitude):
    dom = tuple(tuple(r) for r in DOMAIN.T)
    seam = Seam(axis, swap, flip, dom)
    R = _family(seed=5, seams={axis: seam})(amplitude)
    rng = np.random.default_rng(4)
    on_max = _face_points(DOMAIN, axis, 1, rng)
    # the point at (s, t) on the max face is the point g(s, t) on the min face: R must respect that
    lhs = seam.map_max_to_min(R.evaluate(on_max))
    rhs = R.evaluate(seam.map_max_to_min(on_max))
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=1e-12)
    _check_boundary(R, DOMAIN, rng)


def test_periodic_seam_any_object_with_swap_and_flip():
    seam = SimpleNamespace(swap=True, flip=(True, False))
    R = _family(seed=6, seams={1: seam})(0.25)
    real = Seam(1, True, (True, False), tuple(tuple(r) for r in DOMAIN.T))
    on_max = _face_points(DOMAIN, 1, 1, np.random.default_rng(5))
    np.testing.assert_allclose(real.map_max_to_min(R.evaluate(on_max)), R.evaluate(real.map_max_to_min(on_max)),
                               rtol=0, atol=1e-12)


def test_two_periodic_axes():
    dom = tuple(tuple(r) for r in DOMAIN.T)
    seams = {0: Seam(0, False, (False, False), dom), 2: Seam(2, True, (False, True), dom)}
    R = _family(seed=8, seams=seams)(0.25)
    rng = np.random.default_rng(6)
    for a, seam in seams.items():
        on_max = _face_points(DOMAIN, a, 1, rng)
        np.testing.assert_allclose(seam.map_max_to_min(R.evaluate(on_max)), R.evaluate(seam.map_max_to_min(on_max)),
                                   rtol=0, atol=1e-12)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), amplitude=st.floats(0.0, 0.25), n=st.integers(4, 8))
def test_boundary_holds_over_seeds(seed, amplitude, n):
    R = warp_family(DOMAIN, n, np.random.default_rng(seed))(amplitude)
    _check_boundary(R, DOMAIN, np.random.default_rng(seed % 1000))
