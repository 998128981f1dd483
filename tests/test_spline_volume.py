"""Volume evaluation against geomdl (an independent implementation), and exactness of refinement."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle.errors import ModelError
from volpuzzle.spline import Volume


def random_volume(rng, degrees, counts, rational, lo=-2.0, hi=3.0, repeat=True):
    """Knots off [0, 1] with, where room allows, one repeated interior knot."""
    knots = []
    for p, n in zip(degrees, counts, strict=True):
        inner = np.sort(rng.uniform(lo, hi, n - p - 1))
        if repeat and len(inner) >= 2 and p >= 2:
            inner[1] = inner[0]
        knots.append(np.r_[[lo] * (p + 1), inner, [hi] * (p + 1)])
    cps = rng.normal(size=tuple(counts) + (3,))
    w = rng.uniform(0.5, 2.0, counts) if rational else None
    return Volume(degrees, knots, cps, w)


def geomdl_volume(vol):
    from geomdl import NURBS
    g = NURBS.Volume(normalize_kv=False)
    g.degree_u, g.degree_v, g.degree_w = vol.degrees
    g.ctrlpts_size_u, g.ctrlpts_size_v, g.ctrlpts_size_w = vol.shape
    # geomdl orders control points v fastest, then u, then w, and takes them premultiplied by the weight.
    g.ctrlptsw = vol.homogeneous().transpose(2, 0, 1, 3).reshape(-1, 4).tolist()
    g.knotvector_u, g.knotvector_v, g.knotvector_w = (k.tolist() for k in vol.knots)
    return g


CASES = [((1, 1, 1), (2, 3, 2)), ((2, 3, 1), (5, 6, 3)), ((3, 3, 3), (6, 5, 7)), ((4, 2, 5), (6, 4, 7)),
         ((5, 5, 2), (7, 6, 4))]


@pytest.mark.parametrize("rational", [False, True])
@pytest.mark.parametrize("degrees,counts", CASES)
def test_evaluate_matches_geomdl(degrees, counts, rational):
    rng = np.random.default_rng(hash((degrees, rational)) % 2**32)
    vol = random_volume(rng, degrees, counts, rational)
    g = geomdl_volume(vol)
    uvw = rng.uniform(-2, 3, (20, 3))
    uvw[0] = [-2, -2, -2]
    uvw[1] = [3, 3, 3]
    uvw[2] = [vol.knots[0][degrees[0] + 1], vol.knots[1][degrees[1] + 1], 0.5]  # on knots
    want = np.array([g.evaluate_single(t.tolist()) for t in uvw])
    np.testing.assert_allclose(vol.evaluate(uvw), want, atol=1e-12)
    # the compiled path (large batch) and the numpy path (tiny batch) agree
    big = np.repeat(uvw, 30, axis=0)
    np.testing.assert_allclose(vol.evaluate(big)[::30], want, atol=1e-12)
    ref_p, ref_d = vol._project(*vol._numpy_sums(big, True))
    p, d = vol.evaluate_with_derivatives(big)
    np.testing.assert_allclose(p, ref_p, atol=1e-12)
    np.testing.assert_allclose(d, ref_d, atol=1e-9 * (1 + np.abs(ref_d).max()))


@pytest.mark.parametrize("rational", [False, True])
def test_derivatives_match_central_differences(rational):
    rng = np.random.default_rng(3)
    vol = random_volume(rng, (3, 2, 4), (6, 5, 6), rational, repeat=False)
    uvw = rng.uniform(-1.5, 2.5, (300, 3))
    _, d = vol.evaluate_with_derivatives(uvw)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (vol.evaluate(uvw + e) - vol.evaluate(uvw - e)) / (2 * h)
        # points within h of a knot see the kink of a C^1 knot: skip them
        np.testing.assert_allclose(d[:, :, k], fd, atol=1e-5 * (1 + np.abs(fd).max()))


def test_clamps_outside_domain_and_nan():
    rng = np.random.default_rng(4)
    vol = random_volume(rng, (2, 2, 2), (4, 4, 4), True)
    inside = np.array([[-2.0, 3.0, 0.5]])
    outside = np.array([[-9.0, 7.0, 0.5]])
    np.testing.assert_allclose(vol.evaluate(outside), vol.evaluate(inside))
    big = np.tile(outside, (5000, 1))
    np.testing.assert_allclose(vol.evaluate(big)[-1], vol.evaluate(inside)[0])
    nan = np.tile([[np.nan, 0.0, 0.0]], (5000, 1))
    assert np.all(np.isnan(vol.evaluate(nan)))


@pytest.mark.parametrize("rational", [False, True])
@pytest.mark.parametrize("degrees,counts", [((3, 3, 3), (7, 24, 5)), ((2, 3, 1), (21, 6, 3)), ((2, 5, 4), (4, 8, 30))])
def test_compiled_kernels_match_numpy(degrees, counts, rational):
    # the tricubic kernel, the general one and the one for degree > 3, in the serial (small batch) and parallel
    # (large batch) runs, with
    # few elements (branch-free search) and many (binary search); NaN stays NaN and outside points clamp
    rng = np.random.default_rng(11)
    vol = random_volume(rng, degrees, counts, rational)
    uvw = rng.uniform(-2.5, 3.5, (6000, 3))
    uvw[:50] = vol.knots[1][rng.integers(0, len(vol.knots[1]), 50)][:, None]  # exactly on knots
    uvw[50, 1] = np.nan
    want, want_d = vol._project(*vol._numpy_sums(np.nan_to_num(uvw, nan=0.0), True))
    for batch in (uvw, uvw[:300]):
        got = vol.evaluate(batch)
        got2, got_d = vol.evaluate_with_derivatives(batch)
        assert np.all(np.isnan(got[50])) and np.all(np.isnan(got_d[50]))
        ok = np.ones(len(batch), dtype=bool)
        ok[50] = False
        np.testing.assert_allclose(got[ok], want[:len(batch)][ok], atol=1e-12)
        np.testing.assert_allclose(got2[ok], want[:len(batch)][ok], atol=1e-12)
        np.testing.assert_allclose(got_d[ok], want_d[:len(batch)][ok], atol=1e-9 * np.abs(want_d).max())
    # the serial and the parallel runs give the very same bits, so a point's place in a batch never matters
    np.testing.assert_array_equal(vol.evaluate(uvw)[:1000], vol.evaluate(uvw[:1000]))
    np.testing.assert_array_equal(vol.evaluate_with_derivatives(uvw)[1][:1000],
                                  vol.evaluate_with_derivatives(uvw[:1000])[1])


def test_kernel_tables_say_what_they_hold():
    # the named fields are what the kernels read: element ends, their inverse widths, each element's first control
    # point, and extraction matrices whose rows are the non-zero basis functions; as_args is u's four, v's, w's
    rng = np.random.default_rng(5)
    vol = random_volume(rng, (2, 3, 1), (6, 7, 3), False)
    tables = vol._tables
    for axis, (knots, p, tab) in enumerate(zip(vol.knots, vol.degrees, tables, strict=True)):
        np.testing.assert_array_equal(tab.breaks, np.unique(knots))
        np.testing.assert_allclose(tab.inv_width, 1.0 / np.diff(tab.breaks))
        assert tab.first.dtype == np.int64 and np.all(np.diff(tab.first) >= 0)
        assert tab.first[0] == 0 and tab.first[-1] == vol.shape[axis] - p - 1
        assert tab.extraction.shape == (len(tab.breaks) - 1, p + 1, p + 1)
        # partition of unity: on every element the basis rows sum to the Bernstein polynomials' sum, 1
        np.testing.assert_allclose(tab.extraction.sum(axis=1), 1.0, atol=1e-12)
    args = tables.as_args()
    assert len(args) == 12
    assert all(a is b for a, b in zip(args, (*tables.u, *tables.v, *tables.w), strict=True))
    assert args[0] is tables.u.breaks and args[7] is tables.v.extraction and args[10] is tables.w.first


@pytest.mark.parametrize("rational", [False, True])
def test_grid_matches_scattered(rational):
    rng = np.random.default_rng(5)
    vol = random_volume(rng, (3, 1, 2), (5, 3, 6), rational)
    u, v, w = rng.uniform(-2, 3, 7), rng.uniform(-2, 3, 4), np.linspace(-2, 3, 5)
    pts, der = vol.derivatives_grid(u, v, w)
    uu, vv, ww = np.meshgrid(u, v, w, indexing="ij")
    p2, d2 = vol.evaluate_with_derivatives(np.stack([uu.ravel(), vv.ravel(), ww.ravel()], 1))
    np.testing.assert_allclose(pts.reshape(-1, 3), p2, atol=1e-12)
    np.testing.assert_allclose(der.reshape(-1, 3, 3), d2, atol=1e-9)
    np.testing.assert_allclose(vol.evaluate_grid(u, v, w), pts, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.integers(0, 2), t=st.floats(0.01, 0.99), times=st.integers(1, 3),
       rational=st.booleans())
def test_knot_insertion_keeps_the_volume(seed, axis, t, times, rational):
    rng = np.random.default_rng(seed)
    vol = random_volume(rng, (3, 2, 4), (5, 4, 6), rational)
    lo, hi = vol.domain[axis]
    t = lo + t * (hi - lo)
    from volpuzzle.spline.knots import multiplicity
    times = min(times, vol.degrees[axis] - multiplicity(vol.knots[axis], t))
    ref = vol.insert_knot(axis, t, times)
    assert ref.shape[axis] == vol.shape[axis] + times
    assert ref.is_rational == vol.is_rational
    uvw = rng.uniform(-2, 3, (200, 3))
    np.testing.assert_allclose(ref.evaluate(uvw), vol.evaluate(uvw), atol=1e-11)


def test_knot_insertion_refuses_too_many():
    vol = Volume((2, 1, 1), [[0, 0, 0, 1, 1, 1], [0, 0, 1, 1], [0, 0, 1, 1]], np.zeros((3, 2, 2, 3)))
    with pytest.raises(ModelError, match="more than the degree 2"):
        vol.insert_knot("u", 0.5, 3)
    with pytest.raises(ModelError, match="not inside the domain"):
        vol.insert_knot(0, 1.0)


@pytest.mark.parametrize("rational", [False, True])
def test_bezier_elements_reproduce_the_volume(rational):
    from math import comb
    rng = np.random.default_rng(6)
    vol = random_volume(rng, (3, 2, 1), (6, 5, 4), rational)
    breaks, hp = vol.bezier_elements()
    assert hp.shape[:3] == tuple(len(b) - 1 for b in breaks)
    assert hp.shape[3:] == (4, 3, 2, 4)
    uvw = rng.uniform(-2, 3, (100, 3))
    idx = [np.clip(np.searchsorted(b, uvw[:, a], side="right") - 1, 0, len(b) - 2) for a, b in enumerate(breaks)]
    loc = [(uvw[:, a] - b[i]) / (b[i + 1] - b[i]) for a, (b, i) in enumerate(zip(breaks, idx, strict=True))]
    bern = [np.stack([comb(p, j) * s**j * (1 - s)**(p - j) for j in range(p + 1)], 1)
            for p, s in zip(vol.degrees, loc, strict=True)]
    h = np.einsum("ni,nj,nk,nijkd->nd", *bern, hp[idx[0], idx[1], idx[2]])
    np.testing.assert_allclose(h[:, :3] / h[:, 3:], vol.evaluate(uvw), atol=1e-11)


@pytest.mark.parametrize("rational", [False, True])
def test_subvolume_reproduces_the_volume(rational):
    rng = np.random.default_rng(7)
    vol = random_volume(rng, (3, 2, 2), (6, 5, 4), rational)
    box = np.array([[-1.3, vol.knots[1][3], -2.0], [2.2, 2.9, 3.0]])  # one end on a knot, one on the boundary
    sub = vol.subvolume(box)
    np.testing.assert_allclose(sub.domain_array, box)
    s = rng.uniform(size=(200, 3))
    uvw = box[0] + s * (box[1] - box[0])
    np.testing.assert_allclose(sub.evaluate(uvw), vol.evaluate(uvw), atol=1e-11)
    with pytest.raises(ModelError, match="subvolume: box along u"):
        vol.subvolume([[1, 0, 0], [0, 1, 1]])


def test_transformed_and_scaled():
    rng = np.random.default_rng(8)
    vol = random_volume(rng, (2, 2, 2), (4, 3, 3), True)
    m = rng.normal(size=(3, 3))
    o = rng.normal(size=3)
    uvw = rng.uniform(-2, 3, (50, 3))
    np.testing.assert_allclose(vol.transformed(m, o).evaluate(uvw), vol.evaluate(uvw) @ m.T + o, atol=1e-12)
    np.testing.assert_allclose(vol.scaled(2.5).evaluate(uvw), 2.5 * vol.evaluate(uvw), atol=1e-12)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), rational=st.booleans(),
       lo=st.lists(st.floats(0.0, 0.45), min_size=3, max_size=3),
       hi=st.lists(st.floats(0.55, 1.0), min_size=3, max_size=3))
def test_subvolume_and_extraction_keep_the_volume(seed, rational, lo, hi):
    rng = np.random.default_rng(seed)
    degrees = tuple(int(d) for d in rng.integers(1, 4, 3))
    vol = random_volume(rng, degrees, tuple(d + 3 for d in degrees), rational)
    dom = vol.domain_array
    box = dom[0] + np.array([lo, hi]) * (dom[1] - dom[0])
    sub = vol.subvolume(box)
    uvw = box[0] + rng.random((100, 3)) * (box[1] - box[0])
    np.testing.assert_allclose(sub.evaluate(uvw), vol.evaluate(uvw), atol=1e-10)
    breaks, hp = sub.bezier_elements()
    for a in range(3):
        assert breaks[a][0] == box[0, a] and breaks[a][-1] == box[1, a]
    # every element's corner Bezier points interpolate the volume
    corner = hp[0, 0, 0, 0, 0, 0]
    np.testing.assert_allclose(corner[:3] / corner[3], vol.evaluate(box[:1])[0], atol=1e-10)


_FIRST_CALL = """
import numpy as np, sys
sys.path.insert(0, {root!r})
from tests.test_spline_volume import random_volume
vol = random_volume(np.random.default_rng(5), (2, 2, 2), (5, 6, 4), True)
uvw = np.random.default_rng(6).uniform(-2.0, 3.0, (400, 3))
one = np.concatenate([vol.evaluate_with_derivatives(uvw[i:i + 1])[1] for i in range(20)])  # before any batch
many = vol.evaluate_with_derivatives(uvw)[1][:20]
print(int(np.array_equal(one, many)), int(np.array_equal(vol.evaluate(uvw[:1]), vol.evaluate(uvw)[:1])))
"""


def test_a_points_bits_do_not_depend_on_what_the_process_evaluated_before():
    # A fresh process, whose first calls are single points (as bbox's polish makes on a model from a file): they
    # must give the bits a batch gives later, so a build's pieces do not depend on the order of work in the process
    # (a batch building several specs in one worker, a spec that loads the kernels sooner or later)
    import subprocess
    import sys
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[1])
    out = subprocess.run([sys.executable, "-c", _FIRST_CALL.format(root=root)], capture_output=True, text=True,
                         check=True, cwd=root)
    assert out.stdout.split() == ["1", "1"]


def test_each_kernel_compiles_one_version_per_net_kind():
    # Arguments of every dtype and layout callers pass (float64 C arrays, but also int, Fortran-ordered, strided or
    # read-only parameters) reach the kernels as one array type each: a second type would be a second compilation
    # (seconds on an empty cache). Polynomial (d = 3) and rational (d = 4) nets differ only in `mode` by design.
    from volpuzzle.spline import _fast

    rng = np.random.default_rng(3)
    for degrees in ((3, 3, 3), (2, 2, 2)):
        for rational in (False, True):
            vol = random_volume(rng, degrees, (5, 5, 5), rational)
            base = rng.uniform(-2.0, 3.0, (40, 3))
            ro = base.copy()
            ro.setflags(write=False)
            for uvw in (base, np.asfortranarray(base), base[::2], ro, np.zeros((3, 3), dtype=np.int32), base[:1]):
                vol.evaluate(uvw)
                vol.evaluate_with_derivatives(uvw)
    for name in ("values", "derivatives", "values_cubic", "derivatives_cubic"):
        sigs = getattr(_fast, name).signatures
        assert 1 <= len(sigs) <= 2, (name, sigs)
        assert len({s[:-1] for s in sigs}) == 1, (name, sigs)  # all but `mode` the same
        assert len({s[-1] for s in sigs}) == len(sigs)
