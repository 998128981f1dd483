"""compose: every piece one closed outward solid, volumes adding up to the model's, no overlaps, the mapped surface
within the tolerance, shared faces identical on both sides (also across seams), and the same pieces from a pool."""

from functools import cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle import compose as C
from volpuzzle import geometry as G
from volpuzzle import workers
from volpuzzle.check import closed_problem
from volpuzzle.compose import cell_joints, pool
from volpuzzle.compose import sampling as compose_sampling
from volpuzzle.errors import GeometryError
from volpuzzle.mapping import Map
from volpuzzle.spec import JointSpec
from volpuzzle.spline import Volume
from volpuzzle.spline.seams import Seam
from volpuzzle.tile import tile

# ---------------------------------------------------------------------------------------------------------------------
# small analytic models


def _clamped(n, p):
    inner = np.linspace(0, 1, n - p + 1)[1:-1]
    return np.concatenate([np.zeros(p + 1), inner, np.ones(p + 1)])


def _box():
    """A skewed trilinear block, 30 x 20 x 10 mm."""
    cp = np.zeros((2, 2, 2, 3))
    for i, j, k in np.ndindex(2, 2, 2):
        cp[i, j, k] = (30 * i + 3 * k, 20 * j, 10 * k + 2 * i * j)
    return Volume((1, 1, 1), (_clamped(2, 1),) * 3, cp)


def _ring(twist_deg=0.0, sweep=360.0, n_w=12, radius=30.0, half=8.0, mirror=False):
    """A square section swept round a circle, cubic along w, turning by twist_deg; closes on itself for sweep 360."""
    t = np.arange(n_w) / (n_w - 1)
    ang = np.radians(sweep) * t
    centre = radius * np.stack([np.cos(ang), np.sin(ang), 0 * ang], 1)
    radial = np.stack([np.cos(ang), np.sin(ang), 0 * ang], 1)
    up = np.tile([0.0, 0.0, 1.0], (n_w, 1))
    tw = np.radians(twist_deg) * t
    e1 = np.cos(tw)[:, None] * radial + np.sin(tw)[:, None] * up
    e2 = -np.sin(tw)[:, None] * radial + np.cos(tw)[:, None] * up
    if sweep == 360.0:
        centre[-1] = centre[0]
        if twist_deg % 360 == 0:
            e1[-1], e2[-1] = e1[0], e2[0]
        elif twist_deg % 360 == 90:
            e1[-1], e2[-1] = e2[0], -e1[0]
    x = np.array([-half, half])
    cp = centre[None, None] + x[:, None, None, None] * e1[None, None] + x[None, :, None, None] * e2[None, None]
    if mirror:
        cp = cp * np.array([-1.0, 1.0, 1.0])
    return Volume((1, 1, 3), (_clamped(2, 1), _clamped(2, 1), _clamped(n_w, 3)), cp)


def _cone(n_v=9, radius=20.0, height=15.0):
    """u radial from a collapsed axis (the u=0 face is the z axis), v round (periodic, quadratic), w up; the top
    narrows, so it is a truncated cone."""
    t = np.arange(n_v) / (n_v - 1)
    ang = 2 * np.pi * t
    ring = np.stack([np.cos(ang), np.sin(ang)], 1)
    ring[-1] = ring[0]
    cp = np.zeros((2, n_v, 2, 3))
    for j, k in np.ndindex(n_v, 2):
        r = radius * (1.0 - 0.4 * k)
        cp[0, j, k] = (0.0, 0.0, height * k)
        cp[1, j, k] = (r * ring[j, 0], r * ring[j, 1], height * k)
    return Volume((1, 2, 1), (_clamped(2, 1), _clamped(n_v, 2), _clamped(2, 1)), cp)


def _pyramid():
    """The u=0 face collapses to one point (an apex, as at a sphere's pole)."""
    cp = np.zeros((2, 2, 2, 3))
    for j, k in np.ndindex(2, 2):
        cp[0, j, k] = (0.0, 0.0, 20.0)
        cp[1, j, k] = (20.0 * j - 10.0, 20.0 * k - 10.0, 0.0)
    return Volume((1, 1, 1), (_clamped(2, 1),) * 3, cp)


def _warp(seed=3, amplitude=0.06):
    """R: D -> D, the identity (cubic, 5 control points per axis) with its interior control points moved a little."""
    n = 5
    kn = _clamped(n, 3)
    grev = np.array([kn[i + 1:i + 4].mean() for i in range(n)])
    g = np.stack(np.meshgrid(grev, grev, grev, indexing="ij"), axis=-1)
    rng = np.random.default_rng(seed)
    d = rng.uniform(-amplitude, amplitude, g.shape)
    d[[0, -1], :, :, 0] = 0
    d[:, [0, -1], :, 1] = 0
    d[:, :, [0, -1], 2] = 0
    return Volume((3, 3, 3), (kn, kn, kn), g + d)


def _orientation(vol):
    c = np.array([[np.mean(d) for d in vol.domain]])
    return int(np.sign(np.linalg.det(vol.derivatives(c)[0])))


def _volume_by_quadrature(vol, n=6):
    """Model volume: Gauss-Legendre on every knot span of |det J| (exact up to the rational / high-degree rest)."""
    x, w = np.polynomial.legendre.leggauss(n)
    total = 0.0
    spans = [np.unique(k) for k in vol.knots]
    for a0, a1 in zip(spans[0][:-1], spans[0][1:], strict=True):
        for b0, b1 in zip(spans[1][:-1], spans[1][1:], strict=True):
            for c0, c1 in zip(spans[2][:-1], spans[2][1:], strict=True):
                pts = [0.5 * (lo + hi) + 0.5 * (hi - lo) * x for lo, hi in ((a0, a1), (b0, b1), (c0, c1))]
                uvw = np.stack(np.meshgrid(*pts, indexing="ij"), -1).reshape(-1, 3)
                ww = np.einsum("i,j,k->ijk", w, w, w).ravel()
                det = np.abs(np.linalg.det(vol.derivatives(uvw)))
                total += np.sum(ww * det) * (a1 - a0) * (b1 - b0) * (c1 - c0) / 8
    return total


CASES = {
    # name: (volume, grid, periodic, seams, tolerance, warp)
    "box": (_box, (2, 2, 1), (), {}, 0.1, False),
    "bent": (lambda: _ring(sweep=120.0, n_w=6), (2, 1, 3), (), {}, 0.1, False),
    "mirrored": (lambda: _ring(sweep=120.0, n_w=6, mirror=True), (1, 2, 3), (), {}, 0.1, False),
    "warped": (lambda: _ring(sweep=120.0, n_w=6), (2, 2, 2), (), {}, 0.1, True),
    "cone": (_cone, (1, 3, 1), (1,), {1: Seam(1, domain=((0, 1),) * 3)}, 0.1, False),
    "pyramid": (_pyramid, (2, 2, 2), (), {}, 0.1, False),
    "torus": (lambda: _ring(twist_deg=0.0), (1, 1, 4), (2,), {2: Seam(2, domain=((0, 1),) * 3)}, 0.2, False),
    "twisted": (lambda: _ring(twist_deg=90.0), (2, 2, 3), (2,),
                {2: Seam(2, swap=True, flip=(True, False), domain=((0, 1),) * 3)}, 0.2, False),
}


@cache
def _built(name, tolerance=None):
    make, grid, periodic, seams, tol, warp = CASES[name]
    vol = make()
    tol = tolerance or tol
    t = tile(vol, grid, periodic=periodic, seams=seams)
    fmap = Map(vol, _warp() if warp else None, _orientation(vol))
    sampling = C.sample_parameters(t, fmap, tol)
    pieces = C.compose(t, fmap, [], tol, sampling=sampling)
    return vol, t, fmap, sampling, pieces


# ---------------------------------------------------------------------------------------------------------------------


def test_models_close_where_the_cases_say():
    from volpuzzle.spline.seams import find_seams

    assert find_seams(_ring(twist_deg=0.0)) == {2: Seam(2)}
    assert find_seams(_ring(twist_deg=90.0)) == {2: Seam(2, swap=True, flip=(True, False))}
    assert _orientation(_ring(sweep=120.0, n_w=6, mirror=True)) == -_orientation(_ring(sweep=120.0, n_w=6))


@pytest.mark.parametrize("name", sorted(CASES))
def test_every_piece_is_one_closed_outward_solid(name):
    _, t, _, _, pieces = _built(name)
    assert [p.cell for p in pieces] == sorted(t.cells)
    for p in pieces:
        assert closed_problem(p.mesh) is None, p.id
        assert p.volume > 0 and p.volume == pytest.approx(p.body_volume)
        assert p.triangles == len(p.mesh.faces)
        assert p.id == "p" + "-".join(map(str, p.cell))


@pytest.mark.parametrize("name", sorted(CASES))
def test_volumes_add_up_to_the_model(name):
    vol, _, _, _, pieces = _built(name)
    ref = _volume_by_quadrature(vol)
    assert sum(p.volume for p in pieces) == pytest.approx(ref, rel=5e-3)


def test_volume_error_shrinks_with_the_tolerance():
    vol = _ring(twist_deg=90.0)
    ref = _volume_by_quadrature(vol)
    errors = []
    for tol in (0.8, 0.2, 0.05):
        pieces = _built("twisted", tol)[4]
        errors.append(abs(sum(p.volume for p in pieces) - ref) / ref)
    assert errors[0] > errors[1] > errors[2]


def _overlap(a, b):
    """Volume common to two pieces, measured as the build's check does: with b moved by a hair (shared faces are
    coincident, and the engine's exact-coincidence path can leave slivers along long thin triangles)."""
    from volpuzzle.check import shifted_overlap

    budget = 1e-6 * min(a.volume, b.volume)
    v, bound = shifted_overlap(G.from_trimesh(a.mesh, a.id), G.from_trimesh(b.mesh, b.id), budget)
    return max(0.0, v - bound)


@pytest.mark.parametrize("name", ["bent", "cone", "twisted", "pyramid"])
def test_neighbours_do_not_overlap(name):
    _, t, _, _, pieces = _built(name)
    by_cell = {p.cell: p for p in pieces}
    for f in t.faces:
        a, b = by_cell[f.lower], by_cell[f.upper]
        assert _overlap(a, b) <= 1e-5 * min(a.volume, b.volume)


@pytest.mark.parametrize("name", ["bent", "mirrored", "warped", "twisted", "cone"])
def test_mapped_surface_within_tolerance(name):
    _, t, fmap, sampling, _ = _built(name)
    rng = np.random.default_rng(11)
    worst = 0.0
    for index in sorted(t.cells):
        uvw, ids, tris, _ = C.cell_parameter_mesh(t.cell(index), sampling)
        pick = rng.choice(len(tris), size=min(400, len(tris)), replace=False)
        lam = rng.dirichlet((1.0, 1.0, 1.0), size=len(pick))
        corners = sampling.xyz[ids[tris[pick]]]
        lin = np.einsum("nk,nkd->nd", lam, corners)
        true = fmap.evaluate(np.einsum("nk,nkd->nd", lam, uvw[tris[pick]]))
        # how far the surface is from the triangle (across it: sliding along it is a change of parameter)
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        size = np.linalg.norm(normal, axis=1)
        ok = size > 1e-9
        off = np.abs(np.einsum("nd,nd->n", true - lin, normal)[ok] / size[ok])
        worst = max(worst, float(np.max(off, initial=0.0)))
    assert worst <= sampling.tolerance
    assert 0 < sampling.max_error_mm <= sampling.tolerance


def test_parameter_mesh_is_the_closed_box():
    _, t, _, sampling, _ = _built("twisted")
    for index in sorted(t.cells):
        cell = t.cell(index)
        uvw, _, tris, bits = C.cell_parameter_mesh(cell, sampling)
        box = G.manifold_from_mesh(uvw, tris, cell.id)
        assert box.volume() == pytest.approx(np.prod(cell.box[1] - cell.box[0]), rel=1e-9)
        assert np.all(bits != 0)


def _exact(v):
    return {tuple(x) for x in np.asarray(v)}


@pytest.mark.parametrize("name", ["bent", "torus", "twisted", "warped"])
def test_shared_faces_have_identical_vertices_and_triangles(name):
    _, t, _, sampling, pieces = _built(name)
    by_cell = {p.cell: p for p in pieces}
    lat = sampling.lattice
    seams_seen = 0
    for f in t.faces:
        a, b = by_cell[f.lower].mesh, by_cell[f.upper].mesh
        g = list(f.lower)
        g[f.axis] += 1
        key, _ = lat.face(f.axis, g)
        fm = sampling.faces[key]
        face_pts = _exact(sampling.xyz[fm.ids])
        # bit-identical coordinates on both sides
        assert face_pts <= _exact(a.vertices) and face_pts <= _exact(b.vertices)

        def on_face(mesh, face_pts=face_pts):
            tri = mesh.vertices[mesh.faces]
            keep = [all(tuple(x) in face_pts for x in tr) for tr in tri]
            return {frozenset(tuple(x) for x in tr) for tr in tri[keep]}

        ta, tb = on_face(a), on_face(b)
        assert ta == tb and len(ta) == len(fm.tris)
        seams_seen += f.seam is not None
    assert seams_seen > 0 or not t.periodic


@pytest.mark.slow
@pytest.mark.parametrize("main_takes", [False, True])
def test_pool_gives_the_same_pieces(monkeypatch, main_takes):
    # with main_takes False the workers build every piece; with True this process builds alongside them
    monkeypatch.setattr(pool, "_POOL_MIN_PIECES", 0)
    monkeypatch.setattr(pool, "_POOL_MIN_SECONDS", 0.0)
    monkeypatch.setattr(workers, "_MAIN_TAKES_ITEMS", main_takes)
    vol, t, fmap, sampling, pieces = _built("twisted")
    seen = []
    pooled = C.compose(t, fmap, [], sampling.tolerance, jobs=2, sampling=sampling,
                       progress=lambda i, n, pid: seen.append((i, n, pid)))
    assert [p.id for p in pooled] == [p.id for p in pieces]
    for p, q in zip(pieces, pooled, strict=True):
        assert np.array_equal(p.mesh.vertices, q.mesh.vertices) and np.array_equal(p.mesh.faces, q.mesh.faces)
    assert sorted(i for i, _, _ in seen) == list(range(1, len(pieces) + 1))
    assert {pid for _, _, pid in seen} == {p.id for p in pieces}


def test_small_puzzles_stay_serial(monkeypatch):
    _, t, fmap, sampling, _ = _built("twisted")
    monkeypatch.setattr(workers.concurrent.futures, "ProcessPoolExecutor", None)  # would fail if a pool were made
    assert len(C.compose(t, fmap, [], sampling.tolerance, jobs=2, sampling=sampling)) == len(t.cells)


def test_sampling_is_deterministic():
    vol, t, fmap, sampling, _ = _built("warped")
    again = C.sample_parameters(t, fmap, sampling.tolerance)
    assert np.array_equal(again.xyz, sampling.xyz)
    assert all(np.array_equal(again.faces[k].tris, f.tris) for k, f in sampling.faces.items())


def test_refinement_is_adaptive():
    # the bend is along w only: the flat w faces keep few points, the faces bent along w get many
    _, t, _, s, _ = _built("bent")
    n_u = [len(fm.ids) for k, fm in s.faces.items() if k[0] == 2]  # w faces: straight, coarse
    n_w = [len(fm.ids) for k, fm in s.faces.items() if k[0] == 0]  # u faces: bent along w
    assert max(n_u) * 2 < np.mean(n_w) and max(n_u) < min(n_w)


@settings(max_examples=5, deadline=None)
@given(st.tuples(st.integers(1, 3), st.integers(1, 2), st.integers(1, 3)), st.sampled_from([0.3, 0.6]))
def test_any_grid_tiles_the_bent_bar(grid, tol):
    vol = _ring(sweep=120.0, n_w=6)
    t = tile(vol, grid)
    pieces = C.compose(t, Map(vol, None, _orientation(vol)), [], tol)
    for p in pieces:
        assert closed_problem(p.mesh) is None, p.id
    assert sum(p.volume for p in pieces) == pytest.approx(_volume_by_quadrature(vol), rel=1e-2)


def test_tolerance_must_be_positive():
    vol = _box()
    with pytest.raises(GeometryError, match=r"output.tolerance: must be > 0 mm \(got 0\)"):
        C.sample_parameters(tile(vol, (1, 1, 1)), Map(vol), 0.0)


def test_tolerance_too_fine(monkeypatch):
    monkeypatch.setattr(compose_sampling, "_MAX_EDGE_SAMPLES", 8)
    vol = _ring(sweep=120.0, n_w=6)
    with pytest.raises(GeometryError, match="needs more than 8 samples along w on one cell edge"):
        C.sample_parameters(tile(vol, (1, 1, 1)), Map(vol, None, _orientation(vol)), 0.01)


# ---------------------------------------------------------------------------------------------------------------------
# joints


def _joint_spec(style="pin", space="physical"):
    return JointSpec(style=style, space=space)


@pytest.mark.parametrize("style,space", [("pin", "physical"), ("dowel", "physical"), ("pin", "domain")])
def test_joints_keep_pieces_single_closed_solids(style, space):
    from volpuzzle import joint as J

    vol, t, fmap, sampling, plain = _built("twisted")
    joints = J.plan_joints(t, fmap, _joint_spec(style, space))
    assert joints
    pieces = C.compose(t, fmap, joints, sampling.tolerance, sampling=sampling)
    by_cell = {p.cell: p for p in pieces}
    for p, q in zip(pieces, plain, strict=True):
        assert closed_problem(p.mesh) is None, p.id
        assert p.body_volume == pytest.approx(q.body_volume)
    for j in joints:
        for c in (j.pin_cell, j.hole_cell):
            assert by_cell[c].volume != pytest.approx(by_cell[c].body_volume, rel=1e-6)
    # a hole is wider and deeper than its pin, so the joints take volume away overall
    assert sum(p.volume for p in pieces) < sum(p.body_volume for p in pieces)
    # pins fit into holes with clearance: neighbours still do not overlap. In the domain a pin that crosses the
    # seam of this (kinked, C0) ring is mapped through the other side's Jacobian, so only inner faces are held to it.
    for f in t.faces:
        if space == "domain" and f.seam is not None:
            continue
        a, b = by_cell[f.lower], by_cell[f.upper]
        assert _overlap(a, b) <= 1e-5 * min(a.volume, b.volume)
    if space == "domain":
        # the mapped pins were split until their edges bend by less than the tolerance: many more triangles
        assert sum(p.triangles for p in pieces) > sum(p.triangles for p in plain)


def test_domain_refinement_splits_bent_edges():
    # one long straight edge in the domain across a curved map gets split until its mapped midpoints fit
    vol = _ring(sweep=120.0, n_w=6)
    fmap = Map(vol, None, _orientation(vol))
    q = np.array([[0.5, 0.5, 0.0], [0.5, 0.5, 1.0], [0.2, 0.5, 0.5]])
    f = np.array([[0, 1, 2]])
    q2, xyz, f2 = cell_joints._refine(q, fmap.evaluate(q), f, np.zeros(3, dtype=int), fmap.evaluate, 0.05)
    assert len(f2) > 8
    e = np.concatenate([f2[:, [0, 1]], f2[:, [1, 2]], f2[:, [2, 0]]])
    mid = fmap.evaluate(0.5 * (q2[e[:, 0]] + q2[e[:, 1]]))
    assert np.max(np.linalg.norm(mid - 0.5 * (xyz[e[:, 0]] + xyz[e[:, 1]]), axis=1)) <= 0.05
