"""verify: certificates for the warp R (with the safe amplitude on failure) and for the model M (handedness, folds)."""

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle.errors import GeometryError, ModelError
from volpuzzle.randomize import warp_family
from volpuzzle.spline import Volume
from volpuzzle.spline.knots import uniform_knots
from volpuzzle.verify import safe_amplitude, verify_model, verify_warp

UNIT = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])


def _det(vol, uvw):
    return np.linalg.det(vol.derivatives(uvw))


def _family(seed=7, n=6):
    return warp_family(UNIT, n, np.random.default_rng(seed))


# --- the warp ----------------------------------------------------------------------------------------------------

def test_default_amplitude_certifies():
    out = verify_warp(_family(), 0.25)
    assert out["bijective"] is True and out["status"] == "proved"
    assert out["jacobian_min_coefficient"] > 0


def test_bound_below_every_sampled_det():
    fam = _family(seed=3)
    out = verify_warp(fam, 0.25)
    x = np.random.default_rng(0).uniform(size=(100_000, 3))
    d = _det(fam(0.25), x)
    assert out["jacobian_min_coefficient"] <= d.min()
    assert d.min() > 0


def test_large_amplitude_names_a_safe_one():
    fam = _family(seed=7, n=6)
    with pytest.raises(GeometryError) as err:
        verify_warp(fam, 3.0)
    msg = str(err.value)
    m = re.search(r"^randomize\.amplitude: 3 (folds the map R|flattens the map R|cannot be certified)"
                  r".*smallest Jacobian coefficient "
                  r"(-?[0-9.e+-]+) at uvw \(([^)]*)\).*at most ([0-9.e+-]+) certifies.*\(got 3, expected <= \4\)$", msg)
    assert m, msg
    assert float(m.group(2)) <= 0
    uvw = [float(x) for x in m.group(3).split(",")]
    assert len(uvw) == 3 and all(0 <= x <= 1 for x in uvw)
    safe = float(m.group(4))
    assert 0 < safe < 3.0
    assert verify_warp(fam, safe)["bijective"] is True


def test_safe_amplitude_is_hi_when_hi_certifies_and_bisects_otherwise():
    fam = _family(seed=2)
    assert safe_amplitude(fam, 0.1) == 0.1
    s = safe_amplitude(fam, 4.0)
    assert 0 < s < 4.0
    assert verify_warp(fam, s)["bijective"] is True


def test_periodic_warp_certifies():
    from volpuzzle.spline.seams import Seam
    seams = {2: Seam(2, True, (False, True), ((0.0, 1.0),) * 3), 0: Seam(0)}
    out = verify_warp(warp_family(UNIT, 6, np.random.default_rng(9), seams), 0.25)
    assert out["bijective"] is True and out["jacobian_min_coefficient"] > 0


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), amplitude=st.floats(0.0, 0.25), n=st.sampled_from([4, 6, 8]))
def test_small_amplitudes_certify(seed, amplitude, n):
    out = verify_warp(warp_family(UNIT, n, np.random.default_rng(seed)), amplitude)
    assert out["bijective"] is True and out["jacobian_min_coefficient"] > 0


# --- the model ---------------------------------------------------------------------------------------------------

def _bent_box(n=4, scale=(40.0, 30.0, 20.0)):
    """A right-handed cubic box in mm with a gentle bend, n control points per axis."""
    k = uniform_knots(n)
    g = np.array([k[i + 1:i + 4].mean() for i in range(n)])
    cp = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1) * np.array(scale)
    cp[..., 2] += 5.0 * np.sin(np.pi * cp[..., 0] / scale[0])
    return Volume((3, 3, 3), (k, k, k), cp)


def test_model_right_handed():
    out = verify_model(_bent_box())
    assert out["handedness"] == "right" and out["degenerate"] is False and out["notes"] == []
    assert 0 < out["jacobian_min_coefficient"] <= out["jacobian_max_coefficient"]


def test_model_left_handed_mirror_is_valid():
    v = _bent_box()
    mirrored = Volume(v.degrees, v.knots, v.control_points * np.array([-1.0, 1.0, 1.0]))
    out = verify_model(mirrored)
    assert out["handedness"] == "left" and out["degenerate"] is False
    assert out["jacobian_max_coefficient"] < 0


def test_model_fold_is_refused_with_its_place():
    v = _bent_box(n=5)
    cp = np.array(v.control_points)
    cp[2, 2, 2, 0] = cp[0, 2, 2, 0] - 150.0
    # drag the middle control point far back past the u = 0 face: a planted fold
    folded = Volume(v.degrees, v.knots, cp)
    d = _det(folded, np.random.default_rng(0).uniform(size=(20_000, 3)))
    assert d.min() < 0 < d.max()  # the plant really folds
    with pytest.raises(ModelError) as err:
        verify_model(folded)
    m = re.search(r"^model folds: det J changes sign near uvw \(([^)]*)\), xyz \(([^)]*)\) mm", str(err.value))
    assert m, str(err.value)
    uvw = np.array([float(x) for x in m.group(1).split(",")])
    xyz = np.array([float(x) for x in m.group(2).split(",")])
    assert np.all((uvw >= 0) & (uvw <= 1))
    # the place is near the fold: det J is small there compared with its range, and xyz is M(uvw)
    near = _det(folded, np.clip(uvw + np.random.default_rng(1).uniform(-0.03, 0.03, (200, 3)), 0, 1))
    assert near.min() < 0 < near.max()
    np.testing.assert_allclose(folded.evaluate(uvw[None])[0], xyz, rtol=0.01, atol=0.05)


def test_model_collapsed_axis_passes_with_note():
    # x = 20u, y = 20uv, z = 10w: a wedge whose u = 0 face collapses to an edge, det J = 4000 u >= 0
    k1 = np.array([0.0, 0.0, 1.0, 1.0])
    cp = np.array([[[[20.0 * i, 20.0 * i * j, 10.0 * kk] for kk in (0, 1)] for j in (0, 1)] for i in (0, 1)])
    wedge = Volume((1, 1, 1), (k1, k1, k1), cp)
    out = verify_model(wedge)
    assert out["handedness"] == "right" and out["degenerate"] is True
    assert out["notes"] and "vanishes" in out["notes"][0]


# --- real files (the copies of the project data in tests/data/volumes; see tests/data/LICENSES.md) ---------------
from conftest import DATA  # noqa: E402


@pytest.mark.parametrize("name,patch,handedness,degenerate", [
    ("gismo_cylinder.xml", 0, "left", False),         # left-handed hollow cylinder: valid
    ("gismo_camembert.xml", 0, "right", True),        # collapses to an axis: allowed with a note
    ("gismo_bent_pipe.xml", 0, "right", False),       # rational
    ("gismo_water_passage_3p.xml", 0, "left", False),
])
def test_real_models(name, patch, handedness, degenerate):
    if not (DATA / name).exists():
        pytest.skip(f"{name} not in tests/data/volumes")
    from volpuzzle import load_model
    out = verify_model(load_model(str(DATA / name), patch=patch))
    assert out["handedness"] == handedness and out["degenerate"] is degenerate
    assert bool(out["notes"]) is degenerate


def test_real_model_that_folds():
    # Patch 1 of the G+Smo water passage is left-handed except for a sliver near its u = 0, v = 1 edge where
    # det J turns positive (about 0.02% of random samples): a real fold, refused with its place.
    name = "gismo_water_passage_3p.xml"
    if not (DATA / name).exists():
        pytest.skip(f"{name} not in tests/data/volumes")
    from volpuzzle import load_model
    with pytest.raises(ModelError, match=r"^model folds: det J changes sign near uvw \(0\.0\d*, 0\.9\d*, "):
        verify_model(load_model(str(DATA / name), patch=1))
