"""label: the id's outlines (holes right), the site (inner face, jointless first, clear of joints), and the engraving
(one closed solid, the expected volume, only near the chosen face, >= 0.4 mm deep also on a curved face)."""

import dataclasses
import time
from functools import cache

import manifold3d as m3
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle import compose as C
from volpuzzle import geometry as G
from volpuzzle import joint as J
from volpuzzle import label as L
from volpuzzle.check import closed_problem
from volpuzzle.errors import GeometryError
from volpuzzle.mapping import Map
from volpuzzle.spline import Volume
from volpuzzle.tile import tile

HOLES = {"p": 1, "0": 1, "4": 1, "6": 1, "8": 2, "9": 1}


def _clamped(n, p):
    inner = np.linspace(0, 1, n - p + 1)[1:-1]
    return np.concatenate([np.zeros(p + 1), inner, np.ones(p + 1)])


def _holes(cs):
    """Contours wound clockwise (manifold's holes) of a CrossSection."""
    n = 0
    for p in cs.to_polygons():
        p = np.asarray(p)
        area = 0.5 * np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])
        n += area < 0
    return n


def _covers(cs, x, y, r=0.05):
    """Whether the cross-section covers a small square at (x, y)."""
    probe = m3.CrossSection.square((2 * r, 2 * r), True).translate((x, y))
    return (cs ^ probe).area() > 0.5 * (2 * r) ** 2


# ---------------------------------------------------------------------------------------------------------------------
# text


def test_cross_section_of_an_id_has_its_holes():
    cs = L.text_cross_section("p0-1-3", 5.0)
    assert cs is not None and cs.area() > 0
    (x0, y0, x1, y1) = cs.bounds()
    assert abs(y1 - y0 - 5.0) < 1e-6 and abs(x0 + x1) < 1e-6 and abs(y0 + y1) < 1e-6  # ink box centred, 5 mm tall
    assert _holes(cs) == 2  # the bowl of 'p' and the counter of '0'
    parts = sorted(cs.decompose(), key=lambda p: p.bounds()[0])
    assert len(parts) == 6 and [_holes(p) for p in parts] == [1, 1, 0, 0, 0, 0]
    # the counter of the '0' is empty, its ring is not
    bx0, by0, bx1, by1 = parts[1].bounds()
    cx, cy = 0.5 * (bx0 + bx1), 0.5 * (by0 + by1)
    assert not _covers(cs, cx, cy) and _covers(cs, bx0 + 0.3, cy)
    again = L.text_cross_section("p0-1-3", 5.0)
    assert [np.asarray(p).tolist() for p in again.to_polygons()] == [np.asarray(p).tolist() for p in cs.to_polygons()]


@settings(max_examples=15, deadline=None, derandomize=True)
@given(st.tuples(*[st.integers(0, 19)] * 3), st.floats(4.5, 8.0))
def test_cross_section_any_id(index, height):
    text = "p" + "-".join(map(str, index))
    cs = L.text_cross_section(text, height)
    assert cs.area() > 0
    x0, y0, x1, y1 = cs.bounds()
    assert abs(y1 - y0 - height) < 1e-6 and abs(x0 + x1) < 1e-6
    assert _holes(cs) == sum(HOLES.get(ch, 0) for ch in text)


def test_text_too_small_to_print_gives_none():
    h = L.min_height_mm("p0-1-3")
    assert L.text_cross_section("p0-1-3", 0.98 * h) is None
    assert L.text_cross_section("p0-1-3", h) is not None
    assert L.text_cross_section("", 5.0) is None
    # the stems are MIN_STROKE_MM wide at the smallest height: eroding by just under half of it leaves each glyph
    cs = L.text_cross_section("p0-1-3", h)
    assert len(cs.offset(-0.45 * L.MIN_STROKE_MM, m3.JoinType.Round).decompose()) >= 6


# ---------------------------------------------------------------------------------------------------------------------
# a box puzzle


def _box_model():
    cp = np.zeros((2, 2, 2, 3))
    for i, j, k in np.ndindex(2, 2, 2):
        cp[i, j, k] = (60 * i, 50 * j, 30 * k)
    return Volume((1, 1, 1), (_clamped(2, 1),) * 3, cp)


@cache
def _box_puzzle(v_joint=True):
    """Piece p0-0-0 of a 2 x 2 x 1 box puzzle; without v_joint its v-face has no joint (as assembly.py may decide)."""
    vol = _box_model()
    fmap = Map(vol)
    tiling = tile(vol, (2, 2, 1))
    joints = J.plan_joints(tiling, fmap)
    if not v_joint:
        joints = [j for j in joints if not (j.axis == 1 and tuple(j.pin_cell) == (0, 0, 0))]
    sampling = C.sample_parameters(tiling, fmap, 0.5)  # flat faces: any tolerance is exact
    cell = tiling.cell((0, 0, 0))
    body = G.from_trimesh(C.build_piece(cell, sampling, fmap, joints).mesh, cell.id)
    return tiling, fmap, joints, cell, body


def _removed(body, out):
    return G.to_trimesh(body - out)


def _axis_gap(solid, j):
    """Smallest distance mm from a solid to joint j's axis (a long thin rod along it)."""
    rod = m3.Manifold.cylinder(80.0, 0.01, -1.0, 8).translate((0, 0, -40.0)).transform(J._frame(j))
    return solid.min_gap(rod, 50.0)


def _check_engraving(body, out, site, joints, cell, depth=L.DEPTH_MM):
    assert closed_problem(G.to_trimesh(out)) is None, cell.id
    cs = L.text_cross_section(site.text, site.height_mm)
    lost = body.volume() - out.volume()
    assert abs(lost - cs.area() * depth) <= 0.2 * cs.area() * depth
    removed = _removed(body, out)
    z = (removed.vertices - site.center) @ site.normal
    assert z.min() >= -(depth + 0.02) and z.max() <= 1e-6  # only the skin under the chosen face
    mine = [j for j in joints if cell.index in (tuple(j.pin_cell), tuple(j.hole_cell))]
    assert mine
    rm = G.from_trimesh(removed, "removed")
    for j in mine:
        assert _axis_gap(rm, j) >= j.radius + j.clearance + 0.5


def test_box_piece_labelled_on_a_jointless_inner_face():
    tiling, fmap, joints, cell, body = _box_puzzle(v_joint=False)
    t0 = time.perf_counter()
    site = L.choose_label_site(cell, tiling, fmap, joints)
    t1 = time.perf_counter()
    out = L.engrave(body, site, what=cell.id)
    t2 = time.perf_counter()
    print(f"label {cell.id}: site {t1 - t0:.3f} s, engrave {t2 - t1:.3f} s")
    assert site.face == (1, +1) and not site.has_joint and site.text == "p0-0-0"
    assert np.allclose(site.normal, [0, 1, 0]) and abs(site.center[1] - 25.0) < 1e-9
    assert abs(np.dot(site.up, site.normal)) < 1e-12 and site.height_mm >= L.min_height_mm("p0-0-0")
    assert site.to_report()["face"] == "v+" and not site.to_report()["on_joint_face"]
    assert site.to_report()["mirrored"] is False  # as a bed label says True: every entry says which way it reads
    _check_engraving(body, out, site, joints, cell)


def test_box_piece_with_joints_on_every_face_keeps_clear_of_them():
    tiling, fmap, joints, cell, body = _box_puzzle()
    site = L.choose_label_site(cell, tiling, fmap, joints)
    assert site is not None and site.has_joint
    face_normals = {(0, 1): [1, 0, 0], (1, 1): [0, 1, 0]}
    assert np.allclose(site.normal, face_normals[site.face])  # an inner face, never the outside
    out = L.engrave(body, site, what=cell.id)
    _check_engraving(body, out, site, joints, cell)


def test_site_is_deterministic():
    tiling, fmap, joints, cell, body = _box_puzzle()
    a = L.choose_label_site(cell, tiling, fmap, joints)
    b = L.choose_label_site(cell, tiling, fmap, joints)
    assert a.face == b.face and np.array_equal(a.center, b.center) and np.array_equal(a.up, b.up)
    assert a.height_mm == b.height_mm


def test_single_cell_has_no_inner_face_but_outer_ones():
    vol = _box_model()
    tiling = tile(vol, (1, 1, 1))
    cell = tiling.cell((0, 0, 0))
    assert next(iter(L.label_sites(cell, tiling, Map(vol), [], outer=False)), None) is None
    site = L.choose_label_site(cell, tiling, Map(vol), [])
    assert site is not None and site.outer and site.to_report()["on_outer_face"]
    # the box's outside: the centre of one of its faces, the normal pointing away from the box
    assert np.dot(site.center - [30.0, 25.0, 15.0], site.normal) > 10.0


def test_face_too_small_gives_none():
    cp = np.zeros((2, 2, 2, 3))
    for i, j, k in np.ndindex(2, 2, 2):
        cp[i, j, k] = (12 * i, 10 * j, 10 * k)
    vol = Volume((1, 1, 1), (_clamped(2, 1),) * 3, cp)
    tiling = tile(vol, (2, 1, 1))
    cell = tiling.cell((0, 0, 0))
    assert next(iter(L.label_sites(cell, tiling, Map(vol), [], outer=False)), None) is None
    assert next(iter(L.label_sites(cell, tiling, Map(vol), [], text="p0-0-0-0-0-0-0", outer=True)), None) is None


# ---------------------------------------------------------------------------------------------------------------------
# a bent model


def _bent(radius=40.0, sweep=100.0, thick=16.0, height=14.0):
    """A slab bent round an arc (right-handed): u along the arc (cubic, near circular), v inwards, w up."""
    n = 7
    ang = np.radians(sweep) * np.linspace(0, 1, n)
    cp = np.zeros((n, 2, 2, 3))
    for i, j, k in np.ndindex(n, 2, 2):
        r = radius + thick / 2 - thick * j
        cp[i, j, k] = (r * np.cos(ang[i]), r * np.sin(ang[i]), height * k)
    return Volume((3, 1, 1), (_clamped(n, 3), _clamped(2, 1), _clamped(2, 1)), cp)


def _drop(m, origin, down, length):
    """Heights (along -down) of the first hit of a ray from origin, or None."""
    hits = m.ray_cast(tuple(origin), tuple(origin + down * length))
    return None if not hits else np.asarray(hits[0].position)


def test_curved_face_keeps_the_depth_under_all_the_text():
    vol = _bent()
    fmap = Map(vol)
    tiling = tile(vol, (1, 2, 1))  # the inner face is the curved surface at mid radius
    cell = tiling.cell((0, 1, 0))  # the inner shell: its labelled face is convex
    sampling = C.sample_parameters(tiling, fmap, 0.05)
    body = G.from_trimesh(C.build_piece(cell, sampling, fmap, []).mesh, cell.id)
    site = L.choose_label_site(cell, tiling, fmap, [])
    assert site is not None and site.face == (1, -1)
    # outward from the inner shell through its outer face: away from the arc's centre
    assert np.dot(site.normal, site.center * [1, 1, 0]) > 0
    sag = float(site.heights.max() - site.heights.min())
    assert sag > 0.5  # the face really bends under the text
    out = L.engrave(body, site, what=cell.id)
    assert closed_problem(G.to_trimesh(out)) is None, cell.id

    cs = L.text_cross_section(site.text, site.height_mm)
    inside = np.concatenate([np.asarray(p) for p in cs.offset(-0.1, m3.JoinType.Round).to_polygons()]
                            + [np.asarray(p) for p in cs.offset(-0.3, m3.JoinType.Round).to_polygons()])
    frame = site.frame()
    depths = []
    for x, y in inside:
        top = frame[:, 3] + frame[:, 0] * x + frame[:, 1] * y + frame[:, 2] * (site.heights.max() + 1.0)
        a = _drop(body, top, -site.normal, sag + 5.0)
        b = _drop(out, top, -site.normal, sag + 5.0)
        depths.append(np.dot(a - b, site.normal))
    depths = np.array(depths)
    assert depths.min() >= L.DEPTH_MM - 1e-6 and depths.max() <= L.DEPTH_MM + 0.15
    # perpendicular to the curved surface too: every vertex of the groove's floor (strictly inside the glyphs, so not
    # on a wall) is >= depth from the original surface
    skin = G.to_trimesh(body)
    engraved = G.to_trimesh(out)
    d = engraved.vertices - site.center
    core = cs.offset(-0.05, m3.JoinType.Round)
    under = np.array([_covers(core, x, y, 0.01) for x, y in zip(d @ site.right, d @ site.up, strict=True)])
    z = d @ site.normal
    under &= (z < site.heights.max() + 1e-6) & (z > site.heights.min() - 2.0)  # not the far side of the piece
    _, dist, _ = trimesh.proximity.closest_point(skin, engraved.vertices[under])
    assert under.sum() > 50 and dist.min() >= L.DEPTH_MM - 5e-3


def _ring(radius=40.0, half=11.0, n_w=12):
    """A square section swept round a full circle, cubic along w: its w-faces meet at a periodic seam."""
    ang = 2 * np.pi * np.arange(n_w) / (n_w - 1)
    radial = np.stack([np.cos(ang), np.sin(ang), 0 * ang], 1)
    radial[-1] = radial[0]
    x = np.array([-half, half])
    cp = (radius * radial[None, None] + x[:, None, None, None] * np.array([0.0, 0.0, 1.0])
          + x[None, :, None, None] * radial[None, None])  # u up, v out, w round: right-handed
    return Volume((1, 1, 3), (_clamped(2, 1), _clamped(2, 1), _clamped(n_w, 3)), cp)


def test_label_across_a_periodic_seam():
    from volpuzzle.spline.seams import find_seams

    vol = _ring()
    fmap = Map(vol)
    tiling = tile(vol, (1, 1, 3), periodic=(2,), seams=find_seams(vol))
    joints = [j for j in J.plan_joints(tiling, fmap) if not j.across_seam]  # only the seam's face is free
    cell = tiling.cell((0, 0, 0))
    site = L.choose_label_site(cell, tiling, fmap, joints)
    assert site is not None and site.face == (2, -1) and not site.has_joint
    x0, jac = fmap.evaluate_with_jacobian(np.array([[0.5, 0.5, 0.0]]))
    assert np.dot(site.normal, jac[0][:, 2]) < 0  # out of the cell's min-w face, against growing w
    assert abs(np.dot(site.center - x0[0], site.normal)) < 1e-6  # on the seam's plane
    sampling = C.sample_parameters(tiling, fmap, 0.5)
    body = G.from_trimesh(C.build_piece(cell, sampling, fmap, joints).mesh, cell.id)
    _check_engraving(body, L.engrave(body, site, what=cell.id), site, joints, cell)


def test_left_handed_model_still_faces_out():
    vol = _box_model()
    mirrored = Volume(vol.degrees, vol.knots, vol.control_points * np.array([-1.0, 1.0, 1.0]))
    fmap = Map(mirrored, orientation=-1)
    tiling = tile(mirrored, (2, 2, 1))
    for cell in tiling.cells.values():
        site = L.choose_label_site(cell, tiling, fmap, [])
        inside = fmap.evaluate(cell.center[None])[0]
        assert np.dot(site.center - inside, site.normal) > 5.0
        assert np.isclose(np.linalg.det(site.frame()[:, :3]), 1.0)  # text reads from outside, never mirrored


# ---------------------------------------------------------------------------------------------------------------------
# failures


def _flat_site(text="p0-0-0", height=5.0):
    xs, ys = np.linspace(-12, 12, 25), np.linspace(-4, 4, 9)
    return L.LabelSite(np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]), height, (2, 1),
                       np.zeros(3), False, text, xs, ys, np.zeros((9, 25)), 0.0)


def test_engraving_that_splits_the_piece_names_it():
    # the backstop behind the wall test below: told the wall is thick, the cut itself shows the split
    slab = m3.Manifold.cube((30.0, 12.0, 0.3), True).translate((0, 0, -0.15))
    told = (np.zeros((9, 25)), np.ones((9, 25), bool), np.full((9, 25), np.inf))
    with pytest.raises(GeometryError, match=r"p0-0-0: engraving the label 'p0-0-0' splits the piece"):
        L.engrave(slab, _flat_site(), what="p0-0-0", measured=told)


@pytest.mark.parametrize("thickness", [0.3, 1.0, 1.19])
def test_a_label_is_not_engraved_where_the_piece_is_thin_behind_it(thickness):
    # a groove over a skin thinner than two nozzle lines leaves nothing a slicer keeps: the text would open through
    # (a gear's cut face with a tooth flank just behind it). Measured by rays through the body, under the whole text
    slab = m3.Manifold.cube((30.0, 12.0, thickness), True).translate((0, 0, -thickness / 2))
    with pytest.raises(GeometryError, match=rf"p0-0-0: the piece is {thickness:.2f} mm thick behind the label "
                                            r"'p0-0-0' \(expected at least 1.2 mm"):
        L.engrave(slab, _flat_site(), what="p0-0-0")
    # thin only at one end, under the text: refused as well
    step = (m3.Manifold.cube((30.0, 12.0, 5.0), True).translate((0, 0, -2.5))
            - m3.Manifold.cube((4.0, 12.0, 5.0), True).translate((11.0, 0.0, -2.5 - thickness)))
    with pytest.raises(GeometryError, match="thick behind the label"):
        L.engrave(step, _flat_site(), what="p0-0-0")
    _, near, wall = L._measured(step, _flat_site())
    # the thin end measured; the rest reaches past the rays' reach (2 mm below the face): thick enough
    assert near.all() and wall.min() == pytest.approx(thickness) and np.all(np.isclose(wall, thickness) | (wall > 2))


def test_a_label_is_engraved_where_the_piece_is_thick_enough_behind_it():
    slab = m3.Manifold.cube((30.0, 12.0, 1.25), True).translate((0, 0, -0.625))
    out = L.engrave(slab, _flat_site(), what="p0-0-0")
    assert len(out.decompose()) == 1 and out.volume() < slab.volume()


def test_engraving_too_small_a_label_names_the_piece():
    block = m3.Manifold.cube((30.0, 12.0, 5.0), True).translate((0, 0, -2.5))
    with pytest.raises(GeometryError, match=r"p1-2-3: label 'p0-0-0' at 2.00 mm is too small to print"):
        L.engrave(block, _flat_site(height=2.0), what="p1-2-3")


# ---------------------------------------------------------------------------------------------------------------------
# fast paths agree with the plain computations they replace


def test_outline_fast_path_matches_segment_by_segment():
    from matplotlib.textpath import TextPath

    for text in ("p0-1-3", "p19-8-46", "ABCxyz&%"):
        fast, box = L._outline(text)
        slow, slow_box = L._outline_slow(TextPath((0.0, 0.0), text, size=1.0, prop=L._font()))
        assert len(fast) == len(slow) and np.allclose(box, slow_box, rtol=0, atol=1e-12)
        assert all(a.shape == b.shape and np.allclose(a, b, rtol=0, atol=1e-12)
                   for a, b in zip(fast, slow, strict=True))


def _curves(text):
    """[(matplotlib Bezier segment, control points (k, 2))] of the curves (not the lines) of `text`'s glyphs, 1 em."""
    from matplotlib.path import Path as MplPath
    from matplotlib.textpath import TextPath

    return [(seg, np.asarray(seg.control_points, float))
            for seg, code in TextPath((0.0, 0.0), text, size=1.0, prop=L._font()).iter_bezier()
            if code in (MplPath.CURVE3, MplPath.CURVE4)]


def _to_segments(p, a, b):
    """Distance (n,) of each point p (n, 2) to the nearest segment a -> b (m, 2)."""
    ab = b - a
    t = np.clip(np.einsum("nmi,mi->nm", p[:, None] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p[:, None] - a[None] - t[..., None] * ab[None], axis=2).min(axis=1)


def test_glyph_curves_are_flattened_to_the_tolerance_and_no_finer():
    # Every glyph curve lies within _FLAT_EM of the outline's polygon; and the budget is used: a rule that took every
    # curve as tight as the tightest (as one did) put 1.7x the points on '0'-'9' for errors far below it, and each
    # point costs a labelled piece about five triangles
    text = "0123456789p@&S"
    loops, _ = L._outline(text)
    a = np.concatenate(loops)
    b = np.concatenate([np.roll(loop, -1, axis=0) for loop in loops])
    dense = np.concatenate([seg(np.linspace(0.0, 1.0, 40)) for seg, _ in _curves(text)])
    assert _to_segments(dense, a, b).max() <= L._FLAT_EM * (1 + 1e-9)
    # each curve's own steps: the largest chord error of each, as the rule spaces them
    errors = []
    for seg, cp in _curves(text):
        dd = np.linalg.norm(cp[:-2] - 2.0 * cp[1:-1] + cp[2:], axis=1).max()
        ts = np.linspace(0.0, 1.0, int(L._flat_steps(np.array([dd]), len(cp) - 1)[0]) + 1)
        for t0, t1 in zip(ts[:-1], ts[1:], strict=True):
            ends = seg(np.array([t0, t1]))
            errors.append(_to_segments(seg(np.linspace(t0, t1, 32)), ends[:1], ends[1:]).max())
    assert len(errors) > 100 and max(errors) <= L._FLAT_EM * (1 + 1e-9)
    assert max(errors) >= 0.9 * L._FLAT_EM and np.median(errors) >= 0.3 * L._FLAT_EM


def test_pruned_heights_equal_the_brute_force_minimum():
    rng = np.random.default_rng(7)
    # a wavy closed outline and two joint axes, as _candidates builds them
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    edge = np.stack([30 * np.cos(t), 12 * np.sin(t) + 0.5 * np.sin(9 * t), 0.3 * np.cos(3 * t)], 1)
    axes = np.concatenate([np.stack([np.full(120, x), np.full(120, y), np.linspace(-15, 15, 120)], 1)
                           for x, y in ((-12.0, 2.0), (14.0, -3.0))])
    r = np.full(len(axes), 3.5)
    pts = np.concatenate([edge, axes])
    pad = np.concatenate([np.full(len(edge), L.MARGIN_MM), r])
    lo = np.concatenate([np.full(len(edge), -np.inf), -(L.DEPTH_MM + 2.0 + r)])
    hi = np.concatenate([np.full(len(edge), np.inf), L.TOP_MM + 2.0 + r])
    x0 = np.concatenate([rng.uniform([-25, -9, -0.2], [25, 9, 0.2], (300, 3)), np.zeros((1, 3))])
    normal = rng.normal([0, 0, 1], 0.1, (len(x0), 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    up = np.cross(normal, rng.normal(size=(len(x0), 3)))
    up /= np.linalg.norm(up, axis=1)[:, None]
    right = np.cross(up, normal)
    aspect, cap, hmin = 3.7, 8.0, 2.0
    got = L._heights_allowed(L._keep_out(pts, pad, lo, hi), x0, normal, right, up, aspect, cap, hmin)
    lim = L._limit(pts, x0, right, up, pad, aspect)
    z = pts @ normal.T - np.einsum("ki,ki->k", x0, normal)
    lim[(z <= lo[:, None]) | (z >= hi[:, None])] = np.inf
    want = np.minimum(lim.min(axis=0), cap)
    held = want >= hmin
    assert held.sum() > 20 and (~held).sum() > 20  # both kinds of centre are tried
    assert np.allclose(got[held], want[held], rtol=0, atol=1e-9)
    assert np.all(got[~held] < hmin)


def test_measured_heights_match_one_ray_per_sample():
    vol = _bent()
    fmap = Map(vol)
    tiling = tile(vol, (1, 2, 1))
    cell = tiling.cell((0, 1, 0))
    body = G.from_trimesh(C.build_piece(cell, C.sample_parameters(tiling, fmap, 0.05), fmap, []).mesh, cell.id)
    site = L.choose_label_site(cell, tiling, fmap, [])
    got = L._measured(body, site)[0]
    frame, want = site.frame(), np.array(site.heights, dtype=float)
    span = float(want.max() - want.min()) + 2.0
    for j, y in enumerate(site.grid_y):
        for i, x in enumerate(site.grid_x):
            top = frame[:, 3] + frame[:, 0] * x + frame[:, 1] * y + frame[:, 2] * (site.heights[j, i] + span)
            hits = body.ray_cast(tuple(top), tuple(top - frame[:, 2] * (2 * span)))
            if hits:
                z = float((np.asarray(hits[0].position) - frame[:, 3]) @ frame[:, 2])
                if abs(z - want[j, i]) < 0.5:
                    want[j, i] = z
    assert np.abs(got - site.heights).max() > 1e-4  # the body's facets, not F
    assert np.allclose(got, want, rtol=0, atol=1e-9)


def test_faces_and_joints_by_cell_are_what_the_whole_lists_give():
    # label_pieces hands each piece only its cell's joints and faces: the per-cell questions must not change
    vol = _box_model()
    fmap = Map(vol)
    tiling = tile(vol, (2, 2, 2))
    joints = J.plan_joints(tiling, fmap)
    touching = J.joints_by_cell(joints)
    per_cell = J.cell_joints(joints)
    assert sum(map(len, per_cell.values())) == 2 * len(joints)  # each joint with both of its cells, once
    for index, cell in tiling.cells.items():
        # the report's and the mesh cutter's per-piece joints from the cell's own list, as from the whole list
        assert J.pieces_joints(per_cell.get(tuple(index), []), index) == J.pieces_joints(joints, index)
        assert J.piece_joints_report(per_cell.get(tuple(index), []), index) == J.piece_joints_report(joints, index)
        # the tiling's per-cell index gives what a scan of all its faces gives, in the same order
        scan = [(f, side) for f in tiling.faces for side, end in ((+1, f.lower), (-1, f.upper)) if end == index]
        assert tiling.faces_of(index) == scan
        mine = [joints[k] for k in touching.get(tuple(index), [])]
        assert mine == [j for j in joints if tuple(index) in (tuple(j.pin_cell), tuple(j.hole_cell))]
        for face, _ in tiling.faces_of(index):
            assert L._face_joints(face, mine) == L._face_joints(face, joints)
        for a, b in zip(L._joint_axes(tuple(index), mine), L._joint_axes(tuple(index), joints), strict=True):
            assert np.array_equal(a, b)
        full = list(L.label_sites(cell, tiling, fmap, joints, tries=4))
        own = list(L.label_sites(cell, tiling, fmap, mine, tries=4))
        assert full and [(s.face, s.height_mm, s.center.tobytes()) for s in full] == \
            [(s.face, s.height_mm, s.center.tobytes()) for s in own]


def test_heights_kept_for_a_coarser_stroke_give_the_finer_strokes_sites():
    # a finer stroke reuses the heights measured for a coarser one and measures only the centres below its floor:
    # the sites must be those a search of its own finds, in the same order, also for text that fits only finely
    tiling, fmap, joints, cell, _ = _box_puzzle()
    found = {}
    for text in ("p0-0-0", "p0-0-0-0-0-0-0"):
        memo = {}
        for stroke in L.STROKES_MM:
            kept = list(L.label_sites(cell, tiling, fmap, joints, text=text, stroke=stroke, tries=8, measured=memo,
                                      outer=False))
            fresh = list(L.label_sites(cell, tiling, fmap, joints, text=text, stroke=stroke, tries=8, outer=False))
            assert [(s.face, s.height_mm, s.center.tobytes(), s.up.tobytes()) for s in kept] == \
                [(s.face, s.height_mm, s.center.tobytes(), s.up.tobytes()) for s in fresh]
            found[text, stroke] = len(kept)
        assert any(k[0] == "height" for k in memo)
    # the long text fits only with the finest stroke: its sites are centres measured again below the coarse floor
    assert found["p0-0-0", L.MIN_STROKE_MM] > 0
    assert found["p0-0-0-0-0-0-0", L.MIN_STROKE_MM] == 0 and found["p0-0-0-0-0-0-0", L.HAIR_STROKE_MM] > 0


def test_a_label_keeps_clear_of_a_snap_pin_where_it_swells():
    # the keep-out round a joint's axis is the pin's widest radius as the joint module gives it (a snap pin swells),
    # its clearance and the text's own wall
    vol = _box_model()
    tiling = tile(vol, (2, 2, 2))
    joint = J.plan_joints(tiling, Map(vol))[0]
    for shape in ("cylinder", "snap"):
        j = dataclasses.replace(joint, shape=shape)
        _, radii = L._joint_axes(tuple(j.pin_cell), [j])
        want = J.outer_radius(j.radius, shape) + j.clearance + L.JOINT_CLEAR_MM
        assert np.allclose(radii, want)
    assert J.outer_radius(1.0, "snap") > J.outer_radius(1.0, "cylinder")


def test_a_piece_cut_by_a_mesh_is_labelled_on_its_own_faces_from_the_start(monkeypatch):
    # a mesh model's piece: the cage cell cut below z = 11, so its inner faces cover only their lowest third
    tiling, fmap, joints, cell, body = _box_puzzle(v_joint=False)
    piece = body ^ m3.Manifold.cube((40.0, 40.0, 12.0)).translate((-5.0, -5.0, -1.0))
    mine = [j for j in joints if cell.index in (tuple(j.pin_cell), tuple(j.hole_cell))]
    cover = []
    measured = L._measured

    def counted(*args, **kwargs):
        out = measured(*args, **kwargs)
        cover.append(float(np.mean(out[1])))
        return out

    monkeypatch.setattr(L, "_measured", counted)
    out, site, note = L.label_piece(piece, cell, tiling, fmap, mine, texts=("p0-0-0", "1"), cut_by_mesh=True)
    assert note is None and site.text == "p0-0-0" and site.center[2] < 11.0 - site.height_mm / 2
    assert cover == [1.0]  # one site measured, on the piece: none lost off it
    ink = L.text_cross_section(site.text, site.height_mm).area() * L.DEPTH_MM
    assert abs(piece.volume() - out.volume() - ink) <= 0.2 * ink
    assert closed_problem(G.to_trimesh(out)) is None, cell.id
    # searched on the cage cell's faces first, sites in the middle of the face are measured and found off the piece
    cover.clear()
    L.label_piece(piece, cell, tiling, fmap, mine, texts=("p0-0-0", "1"))
    assert min(cover) < 0.5 and len(cover) > 1


def test_no_piece_number_reads_as_another_turned_upside_down():
    # a loose piece has no up: '6' and '9' (or '16' and '91') would pass for each other, so such numbers get a dot
    turned = {"0": "0", "1": "1", "6": "9", "8": "8", "9": "6", ".": "."}
    texts = [L.number_text(k) for k in range(2000)]
    assert texts[:12] == ["1", "2", "3", "4", "5", "6.", "7", "8", "9.", "10.", "11", "12"]
    assert L.number_text(15) == "16." and L.number_text(68) == "69" and L.number_text(87) == "88"
    known = set(texts)
    for t in texts:
        if all(c in turned for c in t):
            upside_down = "".join(turned[c] for c in reversed(t))
            assert upside_down == t or upside_down not in known, t
