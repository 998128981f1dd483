"""Periodic-seam detection: which axes close on themselves, and under which symmetry of the face."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import volpuzzle
from volpuzzle import models
from volpuzzle.spline.seams import Seam, find_seams, periodic_axes

DATA = Path(__file__).parent / "data" / "volumes"


def _check_coincide(vol, seam, n=50, seed=0):
    """Random points of the max face land on the same xyz on the min face, and back."""
    rng = np.random.default_rng(seed)
    lo, hi = vol.domain_array
    uvw = lo + rng.random((n, 3)) * (hi - lo)
    uvw[:, seam.axis] = hi[seam.axis]
    on_min = seam.map_max_to_min(uvw)
    assert np.allclose(on_min[:, seam.axis], lo[seam.axis])
    size = np.ptp(vol.control_points.reshape(-1, 3), axis=0).max()
    assert np.max(np.abs(vol.evaluate(uvw) - vol.evaluate(on_min))) < 1e-9 * size
    assert np.allclose(seam.map_min_to_max(on_min), uvw, atol=1e-12)


def test_torus_closes_with_the_identity_along_w_only():
    vol = models.torus()
    seams = find_seams(vol)
    assert list(seams) == [2]
    assert seams[2] == Seam(2, False, (False, False)) and seams[2].is_identity
    _check_coincide(vol, seams[2])
    assert periodic_axes(vol) == [2]


def test_quarter_torus_has_no_seam():
    assert find_seams(models.quarter_torus()) == {}


def test_sphere_shell_closes_in_azimuth_only():
    # the collapsed polar faces are segments on the z axis: +z and -z, which must not count as a seam
    seams = find_seams(models.sphere_shell())
    assert list(seams) == [1] and seams[1].is_identity


def test_twisted_torus_90_closes_with_a_swap():
    vol = models.twisted_torus(60, 15, 90)
    seams = find_seams(vol)
    assert list(seams) == [2]
    assert seams[2].swap and not seams[2].is_identity and sum(seams[2].flip) == 1
    _check_coincide(vol, seams[2])


@pytest.mark.parametrize("twist, swap, flips", [(0, False, 0), (180, False, 2), (-90, True, 1), (270, True, 1)])
def test_twisted_torus_seam_follows_the_twist(twist, swap, flips):
    vol = models.twisted_torus(50, 10, twist)
    seams = find_seams(vol)
    assert list(seams) == [2]
    assert seams[2].swap == swap and sum(seams[2].flip) == flips
    _check_coincide(vol, seams[2])


def test_gismo_cylinder_file_has_a_seam_on_a_non_unit_domain():
    vol = volpuzzle.load_model(DATA / "gismo_cylinder.xml")
    assert vol.domain[0] == (0.0, 4.0)
    seams = find_seams(vol)
    assert list(seams) == [0] and seams[0].is_identity
    _check_coincide(vol, seams[0])


def test_a_slightly_open_ring_is_not_periodic():
    vol = models.twisted_torus(60, 15, 0)
    cps = vol.control_points.copy()
    cps[:, :, -1, 2] += 1e-3  # lift the last layer by a micron
    opened = volpuzzle.spline.Volume(vol.degrees, vol.knots, cps)
    assert find_seams(opened) == {}
    assert list(find_seams(opened, rel_tol=1e-4)) == [2]


@settings(max_examples=20, deadline=None, derandomize=True)
@given(axis=st.integers(0, 2), swap=st.booleans(), f0=st.booleans(), f1=st.booleans(),
       pts=st.lists(st.tuples(*[st.floats(0, 1)] * 3), min_size=1, max_size=5))
def test_seam_maps_are_inverse(axis, swap, f0, f1, pts):
    seam = Seam(axis, swap, (f0, f1), ((0.0, 2.0), (-1.0, 1.0), (3.0, 4.0)))
    lo = np.array([0.0, -1.0, 3.0])
    uvw = lo + np.array(pts) * np.array([2.0, 2.0, 1.0])
    uvw[:, axis] = seam.domain[axis][1]
    back = seam.map_min_to_max(seam.map_max_to_min(uvw))
    assert np.allclose(back, uvw, atol=1e-12)


def _sphere_shell_spec(tmp_path, periodic):
    from helpers_build import write_spec

    spec = {"name": "ss", "model": {"builtin": {"type": "sphere-shell"}, "size": 80}, "grid": [1, 2, 1],
            "output": {"tolerance": 0.5, "labels": False, "directory": str(tmp_path / "out")}}
    if periodic:
        spec["periodic"] = periodic
    return write_spec(tmp_path, spec)


@pytest.mark.parametrize("periodic", [None, ["v"]])
def test_a_closed_axis_the_spec_leaves_out_is_joined_and_said(tmp_path, capsys, periodic):
    from volpuzzle.load import load_model_for, with_closed_axes
    from volpuzzle.spec import load_spec

    spec = load_spec(_sphere_shell_spec(tmp_path, periodic))
    model = load_model_for(spec)
    joined = with_closed_axes(spec, model, find_seams(model.volume))
    assert joined.periodic == (1,)
    err = capsys.readouterr().err
    if periodic:
        assert err == ""
    else:
        assert err.startswith("warning: periodic: the model closes on itself along v") and "expected ['v']" in err


@pytest.mark.slow
def test_a_sphere_shell_without_periodic_keeps_its_seam_apart_and_pinned(tmp_path):
    from volpuzzle.check import check_directory

    report = volpuzzle.build(_sphere_shell_spec(tmp_path, None), jobs=1)
    # both faces between the two halves, the cut and the seam, carry a pin
    assert len(report["joints"]) == 2
    printable = check_directory(tmp_path / "out")["printability"]
    assert not [w for w in printable["warnings"] if "come within" in w]


@pytest.mark.parametrize("side", ["min", "max"])
def test_a_point_across_a_twisted_seam_is_moved_into_the_cell_as_the_seam_maps_it(side):
    # the apex set-back gathers a cell's points by parameters; a point stored on the seam's other face must land in
    # the cell at the same place in space, which for the twisted torus (swap and flip) is more than a period's shift
    from types import SimpleNamespace

    from volpuzzle.compose.lattice import PeriodicSeam
    from volpuzzle.compose.surface import _in_box

    vol = models.make_builtin({"type": "twisted-torus"})
    seam = find_seams(vol)[2]
    assert seam.swap or any(seam.flip)
    sampling = SimpleNamespace(seams=(PeriodicSeam(2, seam.swap, seam.flip),), domain=np.array(vol.domain).T)
    rng = np.random.default_rng(3)
    uvw = np.column_stack([rng.uniform(0.05, 0.95, (20, 2)), np.full(20, 0.0 if side == "min" else 1.0)])
    box = np.array([[0.0, 0.0, 0.875], [1.0, 1.0, 1.0]]) if side == "min" else np.array([[0, 0, 0], [1, 1, 0.125]])
    moved = _in_box(uvw, box, sampling)
    assert np.all((moved[:, 2] >= box[0, 2]) & (moved[:, 2] <= box[1, 2]))
    assert not np.allclose(moved[:, :2], uvw[:, :2])  # the face coordinates were mapped, not only shifted
    assert np.allclose(vol.evaluate(moved), vol.evaluate(uvw), atol=1e-9)
