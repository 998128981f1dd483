"""Built-in models: exact volumes, handedness, a positive Jacobian inside, knots, fit accuracy, spec errors."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle import models
from volpuzzle.errors import ModelError, SpecError
from volpuzzle.spline import knots as knotlib

try:  # the kernel's measure and certificate, when they exist; plain quadrature and sampling otherwise
    from volpuzzle.spline.measure import volume as measured_volume
except ImportError:  # pragma: no cover - depends on the kernel's progress
    measured_volume = None


def _volume(vol, n=10):
    """Gauss-Legendre quadrature of det J over each knot span box (rational: converges fast, not exact)."""
    if measured_volume is not None:
        return abs(measured_volume(vol))
    x, w = np.polynomial.legendre.leggauss(n)
    axes = []
    for a in range(3):
        br = knotlib.breaks(vol.knots[a], vol.degrees[a])
        h = np.diff(br)
        pts = (br[:-1, None] + (x[None] + 1) / 2 * h[:, None]).ravel()
        wts = (w[None] * h[:, None] / 2).ravel()
        axes.append((pts, wts))
    g = np.stack(np.meshgrid(*(p for p, _ in axes), indexing="ij"), -1).reshape(-1, 3)
    wt = np.einsum("i,j,k->ijk", *(w for _, w in axes)).ravel()
    return abs(float(np.sum(np.linalg.det(vol.derivatives(g)) * wt)))


@pytest.fixture(scope="module")
def built():
    return {name: make(**defaults) for name, (make, defaults) in models.BUILTINS.items()}


def test_torus_volume_is_exact():
    R, r = 60.0, 20.0
    assert _volume(models.torus(R, r)) == pytest.approx(2 * math.pi ** 2 * R * r ** 2, rel=1e-8)


def test_quarter_torus_is_a_quarter_of_the_torus():
    R, r = 50.0, 12.0
    assert _volume(models.quarter_torus(R, r)) == pytest.approx(math.pi ** 2 * R * r ** 2 / 2, rel=1e-8)


def test_sphere_shell_volume_is_exact():
    R, r = 50.0, 40.0
    assert _volume(models.sphere_shell(R, r)) == pytest.approx(4 / 3 * math.pi * (R ** 3 - r ** 3), rel=1e-8)


def test_torus_surface_is_a_true_torus():
    R, r = 60.0, 20.0
    vol = models.torus(R, r)
    rng = np.random.default_rng(1)
    uvw = rng.random((200, 3))
    for a in (0, 1):  # all four sides of the square-to-disk section lie on the torus surface
        for end in (0.0, 1.0):
            side = uvw.copy()
            side[:, a] = end
            xyz = vol.evaluate(side)
            rho = np.hypot(xyz[:, 0], xyz[:, 1])
            assert np.allclose(np.hypot(rho - R, xyz[:, 2]), r, atol=1e-9)


@pytest.mark.parametrize("name", list(models.BUILTINS))
def test_every_builtin_is_right_handed_with_positive_interior_jacobian(built, name):
    vol = built[name]
    n = 12
    s = (np.arange(n) + 0.5) / n  # interior points, off the collapsed boundary
    g = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    det = np.linalg.det(vol.derivatives(g))
    assert det.min() > 0
    # and on the boundary faces it never goes negative (it may touch zero on collapsed edges / poles)
    e = np.linspace(0, 1, 9)
    faces = np.stack(np.meshgrid(e, e, [0.0, 1.0], indexing="ij"), -1).reshape(-1, 3)
    for a in range(3):
        f = np.roll(faces, a + 1, axis=1)
        assert np.linalg.det(vol.derivatives(f)).min() > -1e-6 * det.max()


@pytest.mark.parametrize("name", list(models.BUILTINS))
def test_every_builtin_is_certified_right_handed(built, name):
    from volpuzzle.spline.jacobian import certify_positive, orientation

    vol = built[name]
    cert = certify_positive(vol)
    # 'degenerate': det J > 0 in the open domain, zero only on collapsed boundary (disk corners, poles)
    expected = "proved" if name == "twisted-torus" else "degenerate"
    assert cert.status == expected, cert.message
    assert orientation(vol).handedness == "right"


def test_a_left_handed_construction_is_turned_right_handed():
    from volpuzzle.spline.jacobian import orientation

    right = models.quarter_torus(50.0, 20.0)
    left = models._reverse_axis(right, 0)
    assert orientation(left).handedness == "left"
    fixed = models._right_handed(left)
    assert orientation(fixed).handedness == "right"
    assert models._right_handed(right) is right  # a right-handed one is passed through untouched
    uvw = np.random.default_rng(3).random((50, 3))
    assert np.allclose(fixed.evaluate(uvw), right.evaluate(uvw), atol=1e-9)  # the same solid


def test_generalized_torus_has_c1_breaks_at_nine_interior_knots(built):
    vol = built["generalized-torus"]
    assert vol.degrees[2] == 3
    k = vol.knots[2]
    interior = knotlib.breaks(k, 3)[1:-1]
    assert len(interior) == 9
    assert all(knotlib.multiplicity(k, t) == 2 for t in interior)
    # C1 in space too: the w-derivative from both sides of each break agrees
    rng = np.random.default_rng(2)
    uv = rng.random((20, 2))
    for t in interior:
        left = np.column_stack([uv, np.full(20, t - 1e-9)])
        right = np.column_stack([uv, np.full(20, t + 1e-9)])
        dl, dr = vol.derivatives(left)[:, :, 2], vol.derivatives(right)[:, :, 2]
        assert np.allclose(dl, dr, rtol=1e-5, atol=1e-4 * np.abs(dl).max())


def test_generalized_torus_goes_from_square_to_circle(built):
    vol = built["generalized-torus"]
    s = np.linspace(0, 1, 41)
    for w, shape in ((0.0, "square"), (0.5, "circle")):
        g = np.stack(np.meshgrid(s, [0.0, 1.0], [w], indexing="ij"), -1).reshape(-1, 3)
        xyz = vol.evaluate(g)
        centre = vol.evaluate(np.array([[0.5, 0.5, w]]))[0]
        d = np.linalg.norm(xyz - centre, axis=1)
        if shape == "circle":
            assert np.allclose(d, 15.0, atol=1e-6)
        else:
            assert d.max() == pytest.approx(15.0 * math.sqrt(2), rel=1e-9)


def test_twisted_torus_stays_within_1e4_of_the_size():
    R, r, twist = 60.0, 15.0, 90.0
    vol = models.twisted_torus(R, r, twist)
    size = 2 * (R + r * math.sqrt(2))
    rng = np.random.default_rng(3)
    uvw = rng.random((4000, 3))
    uvw[:1000, 0] = np.round(uvw[:1000, 0])  # plenty on the boundary, where the corners are
    uvw[:1000, 1] = np.round(uvw[:1000, 1])
    err = np.linalg.norm(vol.evaluate(uvw) - models.twisted_torus_point(R, r, twist, uvw), axis=1)
    assert err.max() < 1e-4 * size


@settings(max_examples=8, deadline=None, derandomize=True)
@given(R=st.floats(30, 120), ratio=st.floats(0.05, 0.65), quarter_turns=st.integers(-2, 3))
def test_twisted_torus_closes_for_any_quarter_turn(R, ratio, quarter_turns):
    from volpuzzle.spline.seams import find_seams

    vol = models.twisted_torus(R, ratio * R, 90 * quarter_turns)
    assert list(find_seams(vol)) == [2]
    g = np.array([[0.5, 0.5, w] for w in np.linspace(0.01, 0.99, 15)])
    assert np.linalg.det(vol.derivatives(g)).min() > 0


def test_duck_shell_is_a_thin_closed_shell(built):
    vol = built["duck-shell"]
    from volpuzzle.spline.seams import find_seams

    assert list(find_seams(vol)) == [1]
    cps = vol.control_points
    assert np.ptp(cps[:, :, 1].reshape(-1, 3), axis=0).max() == pytest.approx(120.0)
    # the two surfaces are `thickness` apart at the control points
    assert np.allclose(np.linalg.norm(cps[:, :, 1] - cps[:, :, 0], axis=-1), 8.0)
    # both poles are collapsed rows
    for row in (0, -1):
        assert np.ptp(cps[row, :, 1], axis=0).max() < 1e-9


def test_make_builtin_uses_defaults_and_overrides():
    vol = models.make_builtin({"type": "twisted-torus", "major_radius": 60, "minor_radius": 15, "twist": 90})
    ref = models.twisted_torus()
    assert np.array_equal(vol.control_points, ref.control_points)
    small = models.make_builtin({"type": "torus", "major_radius": 30})
    assert np.ptp(small.control_points[..., 0]) < np.ptp(models.torus().control_points[..., 0])


def _problems(params):
    with pytest.raises(SpecError) as info:
        models.make_builtin(params)
    return info.value.problems


def test_error_minor_not_smaller_than_major():
    assert _problems({"type": "torus", "major_radius": 60, "minor_radius": 70}) == [
        "model.builtin.minor_radius: must be smaller than major_radius (got 70, expected < 60)"]


def test_error_unknown_key_names_the_nearest():
    (p,) = _problems({"type": "torus", "minor_radus": 5})
    assert p.startswith("model.builtin.minor_radus: unknown key") and "'minor_radius'" in p


def test_error_wrong_type():
    assert _problems({"type": "sphere-shell", "outer_radius": "big"}) == [
        "model.builtin.outer_radius: must be a number (got 'big', expected e.g. 50)"]


def test_error_non_positive_size():
    assert _problems({"type": "duck-shell", "thickness": 0}) == [
        "model.builtin.thickness: must be positive (got 0, expected > 0)"]


def test_error_unknown_type():
    (p,) = _problems({"type": "twisted_torus"})
    assert p.startswith("model.builtin.type: unknown builtin (got 'twisted_torus'") and "'twisted-torus'" in p


def test_error_missing_type():
    (p,) = _problems({"major_radius": 3})
    assert p.startswith("model.builtin.type: missing")


def test_error_twist_not_a_quarter_turn():
    assert _problems({"type": "twisted-torus", "twist": 45}) == [
        "model.builtin.twist: must be a multiple of 90 degrees so the square section closes on itself "
        "(got 45, expected e.g. 0 or 90)"]


def test_error_generalized_torus_too_fat_for_its_corners():
    assert _problems({"type": "generalized-torus", "minor_radius": 40}) == [
        "model.builtin.minor_radius: must be smaller than 0.4 * major_radius (got 40, expected < 24)"]


def test_largest_allowed_generalized_torus_still_certifies():
    models.make_builtin({"type": "generalized-torus", "major_radius": 60, "minor_radius": 23.9})


def test_all_problems_are_listed_at_once():
    probs = _problems({"type": "torus", "major_radius": -1, "minor_radius": True, "colour": "red"})
    assert len(probs) == 3


def test_error_a_folded_result_is_refused(monkeypatch):
    def folded(major_radius=60.0, minor_radius=20.0):
        vol = models.quarter_torus(major_radius, minor_radius)
        cps = vol.control_points.copy()
        cps[2, 2, 1] = cps[0, 0, 1]  # pull an outer control point across the section: det J changes sign
        return type(vol)(vol.degrees, vol.knots, cps, vol.weights)

    monkeypatch.setitem(models.BUILTINS, "quarter-torus", (folded, {"major_radius": 60.0, "minor_radius": 20.0}))
    with pytest.raises(ModelError, match=r"model.builtin: the quarter-torus with major_radius: 60, minor_radius: 20 "
                                         r"folds or is not certified"):
        models.make_builtin({"type": "quarter-torus"})
