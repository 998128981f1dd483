"""joint: at most three pins and three holes per piece, joint solids that never meet inside a piece, pins that fit
their holes with the asked clearance in mm, seam-crossing joints, and the fit errors."""

from collections import Counter

import manifold3d as m3
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapes import half_cone, ring

from volpuzzle import _joint_kernels as K
from volpuzzle import joint as J
from volpuzzle.errors import GeometryError, SpecError
from volpuzzle.mapping import Map
from volpuzzle.spec import JointSpec
from volpuzzle.spline import Volume
from volpuzzle.spline.seams import find_seams
from volpuzzle.tile import tile

# ---------------------------------------------------------------------------------------------------------------------
# Small models built here (the real builtins live in volpuzzle.models)


def _box(sx=40.0, sy=30.0, sz=20.0):
    cp = np.zeros((2, 2, 2, 3))
    for i, j, k in np.ndindex(2, 2, 2):
        cp[i, j, k] = [i * sx, j * sy, k * sz]
    return Volume((1, 1, 1), ([0, 0, 1, 1],) * 3, cp)


def _bent(mirror=False):
    """A thick quarter ring, strongly curved: u along a 90-degree cubic arc, v radial (20..50 mm), w height 30 mm."""
    k = 0.5523
    arc = np.array([[1, 0], [1, k], [k, 1], [0, 1]], float)
    cp = np.zeros((4, 2, 2, 3))
    for i, j, m in np.ndindex(4, 2, 2):
        r = (20.0, 50.0)[j]
        cp[i, j, m] = [r * arc[i, 0], r * arc[i, 1], 30.0 * m]
    if mirror:
        cp[..., 0] *= -1
    return Volume((3, 1, 1), ([0, 0, 0, 0, 1, 1, 1, 1], [0, 0, 1, 1], [0, 0, 1, 1]), cp)




def _map(vol):
    _, jac = vol.evaluate_with_derivatives(np.array([[0.5, 0.5, 0.5]]))
    return Map(vol, None, int(np.sign(np.linalg.det(jac[0]))))


def _tiling(vol, grid, periodic=()):
    seams = find_seams(vol) if periodic else None
    return tile(vol, grid, periodic=periodic, seams=seams)


def _spec(**kw):
    return JointSpec(**kw)


def _roles(joints, tiling):
    return {idx: Counter(role for _, role in J.pieces_joints(joints, idx)) for idx in tiling.cells}


def _body(fmap, cell, n=12):
    """The mapped cell box as a closed Manifold: a refined cube warped through F (mirrored first for a left-handed F,
    so that the result is positively oriented)."""
    lo, hi = cell.box
    flip = fmap.orientation < 0

    def warp(p):
        p = np.array(p, dtype=float)
        if flip:
            p[:, 0] = 1.0 - p[:, 0]
        return fmap.evaluate(lo + p * (hi - lo))

    body = m3.Manifold.cube([1.0, 1.0, 1.0]).refine(n).warp_batch(warp)
    assert body.status() == m3.Error.NoError and body.volume() > 0
    return body


def _vol(m):
    assert m.status() == m3.Error.NoError
    return m.volume()


def _axial_and_radial(solid, j, flip=False):
    """Vertices of a joint solid as (distance along the joint's direction from its centre, distance from its axis)."""
    v = np.asarray(solid.to_mesh().vert_properties)[:, :3] - j.center
    d = j.direction * (-1 if flip else 1)
    z = v @ d
    return z, np.linalg.norm(v - z[:, None] * d, axis=1)


MODELS = {
    "box": lambda: (_box(), ()),
    "bent": lambda: (_bent(), ()),
    "mirrored": lambda: (_bent(mirror=True), ()),
    "torus": lambda: (ring(), (2,)),
    "twisted": lambda: (ring(twist=np.pi / 2), (2,)),
}


# ---------------------------------------------------------------------------------------------------------------------
# Counting


@pytest.mark.parametrize("name,grid", [("box", (1, 1, 1)), ("box", (2, 1, 1)), ("box", (2, 2, 2)), ("box", (3, 3, 3)),
                                       ("bent", (3, 2, 2)), ("mirrored", (2, 2, 2)), ("torus", (2, 2, 4)),
                                       ("twisted", (2, 2, 4)), ("twisted", (2, 2, 1))])
def test_one_joint_per_face_and_at_most_three_pins_and_holes(name, grid):
    vol, periodic = MODELS[name]()
    t = _tiling(vol, grid, periodic)
    joints = J.plan_joints(t, _map(vol), _spec())
    assert len(joints) == len(t.faces)
    assert {(j.pin_cell, j.hole_cell, j.axis) for j in joints} == {(f.lower, f.upper, f.axis) for f in t.faces}
    for idx, c in _roles(joints, t).items():
        assert c["pin"] <= 3 and c["hole"] <= 3, (idx, c)


@settings(max_examples=12, deadline=None, derandomize=True)
@given(st.tuples(st.integers(1, 3), st.integers(1, 3), st.integers(1, 3)))
def test_at_most_three_pins_and_holes_over_grids(grid):
    vol = _box(60.0, 50.0, 40.0)
    t = _tiling(vol, grid)
    joints = J.plan_joints(t, _map(vol), _spec())
    assert len(joints) == len(t.faces)
    for c in _roles(joints, t).values():
        assert c["pin"] <= 3 and c["hole"] <= 3
    for j in joints:  # pins point along +axis: the pin cell is the lower one
        assert j.pin_cell[j.axis] + 1 == j.hole_cell[j.axis]


@settings(max_examples=4, deadline=None, derandomize=True)
@given(st.integers(1, 2), st.integers(2, 4))
def test_at_most_three_pins_and_holes_on_a_twisted_ring(n, along):
    vol = ring(twist=np.pi / 2)
    t = _tiling(vol, (n, n, along), (2,))
    joints = J.plan_joints(t, _map(vol), _spec())
    for c in _roles(joints, t).values():
        assert c["pin"] <= 3 and c["hole"] <= 3


def test_style_none_gives_no_joints():
    vol = _box()
    assert J.plan_joints(_tiling(vol, (2, 2, 2)), _map(vol), _spec(style="none")) == []


# ---------------------------------------------------------------------------------------------------------------------
# The solids, proven on the real geometry


def _cell_solids(joints, idx):
    out = []
    for j, role in J.pieces_joints(joints, idx):
        if role == "pin":
            out.append((j, role, J.pin_solid(j)))
        else:
            out.append((j, role, J.hole_solid(j, idx)))
    return out


@pytest.mark.parametrize("name,grid,spec", [
    ("box", (2, 2, 2), {}),
    ("box", (2, 2, 2), {"radius": 2.5, "length": 6.0}),
    ("box", (3, 3, 3), {"radius": 1.2, "length": 2.5, "shape": "snap"}),
    ("bent", (2, 2, 2), {}),
    ("bent", (3, 2, 2), {"radius": 2.0, "length": 4.0}),
    ("mirrored", (2, 2, 2), {"shape": "snap"}),
    ("twisted", (2, 2, 4), {}),
    ("twisted", (2, 2, 4), {"radius": 2.0, "length": 4.0}),
    ("torus", (2, 2, 2), {"style": "dowel"}),
])
def test_joint_solids_never_meet_inside_a_piece_and_holes_stay_inside(name, grid, spec):
    vol, periodic = MODELS[name]()
    fmap = _map(vol)
    t = _tiling(vol, grid, periodic)
    joints = J.plan_joints(t, fmap, _spec(**spec))
    for idx, cell in t.cells.items():
        body = _body(fmap, cell)
        parts = [(j, role, s ^ body) for j, role, s in _cell_solids(joints, idx)]
        for a in range(len(parts)):
            for b in range(a + 1, len(parts)):
                overlap = _vol(parts[a][2] ^ parts[b][2])
                assert overlap < 1e-6, (name, idx, parts[a][0].axis, parts[b][0].axis, overlap)
        for j, role, s in _cell_solids(joints, idx):
            if role != "hole":
                continue
            flip = idx == j.pin_cell  # a dowel hole in the pin cell runs backwards
            d = -j.direction if flip else j.direction
            # past the opening (the face may bulge by up to base_depth) the hole is wholly inside the piece
            deep = s.trim_by_plane(d, float(np.dot(d, j.center)) + j.base_depth)
            outside = _vol(deep - body)
            assert outside < 1e-4 * _vol(deep), (name, idx, j.axis, outside)


@pytest.mark.parametrize("name,spec", [("box", {"radius": 2.5, "length": 6.0}), ("bent", {"radius": 2.0}),
                                       ("mirrored", {"radius": 1.5, "clearance": 0.2}), ("twisted", {})])
def test_sizes_hold_in_mm_and_pins_fit_holes(name, spec):
    vol, periodic = MODELS[name]()
    t = _tiling(vol, (2, 2, 2) if not periodic else (2, 2, 4), periodic)
    joints = J.plan_joints(t, _map(vol), _spec(**spec))
    for j in joints:
        pin, hole = J.pin_solid(j), J.hole_solid(j, j.hole_cell)
        assert _vol(pin - hole) < 1e-6 * _vol(pin)
        z, rad = _axial_and_radial(pin, j)
        zh, radh = _axial_and_radial(hole, j)
        assert abs(z.max() - j.length) <= 0.05 * j.length
        assert abs(rad.max() - j.radius) <= 0.05 * j.radius
        assert abs(zh.max() - j.length - j.axial_clearance) <= 0.05 * j.axial_clearance
        assert abs((radh.max() - rad.max()) - j.clearance) <= 0.05 * j.clearance
        # the same through volumes: the cylinders' mean radii over the pin's length
        seg_p = pin.trim_by_plane(j.direction, float(j.direction @ j.center))
        seg_h = hole.trim_by_plane(j.direction, float(j.direction @ j.center)).trim_by_plane(
            -j.direction, -float(j.direction @ j.center) - j.length)
        r_p = np.sqrt(_vol(seg_p) / (np.pi * j.length))
        r_h = np.sqrt(_vol(seg_h) / (np.pi * j.length))
        assert abs(r_p - j.radius) <= 0.05 * j.radius
        assert abs((r_h - r_p) - j.clearance) <= 0.05 * j.clearance
    if "radius" in spec:
        assert all(j.radius == spec["radius"] for j in joints)


def test_snap_pin_swells_and_necks_and_fits_its_hole():
    vol = _box()
    t = _tiling(vol, (2, 1, 1))
    (j,) = J.plan_joints(t, _map(vol), _spec(shape="snap", radius=2.0, length=6.0))
    pin, hole = J.pin_solid(j), J.hole_solid(j, j.hole_cell)
    assert _vol(pin - hole) < 1e-6 * _vol(pin)
    z, rad = _axial_and_radial(pin, j)
    assert abs(rad.max() - J.SNAP_SWELL * j.radius) <= 0.05 * j.radius
    near_tip = (z > 0.85 * j.length) & (z < 0.95 * j.length)
    assert rad[near_tip].max() < j.radius
    assert abs(z.max() - j.length) < 1e-6


def test_dowel_holes_in_both_pieces_hold_the_dowel():
    vol = _box()
    t = _tiling(vol, (2, 1, 1))
    (j,) = J.plan_joints(t, _map(vol), _spec(style="dowel", radius=2.0, length=5.0))
    assert [r for _, r in J.pieces_joints([j], j.pin_cell)] == ["hole"]
    with pytest.raises(GeometryError, match="style dowel has no pin"):
        J.pin_solid(j)
    dowel = J.dowel_solid(j)
    holes = J.hole_solid(j, j.pin_cell) + J.hole_solid(j, j.hole_cell)
    assert abs(_vol(dowel) - np.pi * 4.0 * 10.0) < 0.05 * np.pi * 40.0
    assert _vol(dowel - holes) < 1e-6
    z, _ = _axial_and_radial(J.hole_solid(j, j.pin_cell), j, flip=True)
    assert abs(z.max() - j.length - j.axial_clearance) < 1e-6


def test_domain_pins_compose_to_about_the_asked_size():
    vol = _bent()
    fmap = _map(vol)
    t = _tiling(vol, (2, 2, 2))
    joints = J.plan_joints(t, fmap, _spec(space="domain", radius=1.5, length=3.0))
    for j in joints[:4]:
        pin_d = J.pin_solid_domain(j)
        composed = pin_d.warp_batch(lambda p: fmap.evaluate(np.array(p)))
        want = np.pi * j.radius ** 2 * (j.length + j.base_depth)
        assert abs(abs(_vol(composed)) - want) < 0.1 * want
        hole_d = J.hole_solid_domain(j, j.hole_cell)
        assert _vol(pin_d - hole_d) < 1e-6 * _vol(pin_d)


# ---------------------------------------------------------------------------------------------------------------------
# Directions and seams


@pytest.mark.parametrize("name", ["box", "bent", "mirrored", "torus", "twisted"])
def test_directions_are_unit_and_point_into_the_hole_piece(name):
    vol, periodic = MODELS[name]()
    fmap = _map(vol)
    t = _tiling(vol, (2, 2, 3) if periodic else (2, 2, 2), periodic)
    joints = J.plan_joints(t, fmap, _spec())
    for j in joints:
        assert abs(np.linalg.norm(j.direction) - 1) < 1e-9
        x_pin, jac_pin = fmap.evaluate_with_jacobian(j.uvw_pin[None])
        x_hole, jac_hole = fmap.evaluate_with_jacobian(j.uvw_hole[None])
        assert np.allclose(x_pin[0], j.center, atol=1e-6) and np.allclose(x_hole[0], j.center, atol=1e-6)
        # the hole cell lies on the +axis side of the face in its own parameters
        assert j.direction @ jac_hole[0][:, j.axis] > 0
        assert j.direction @ jac_pin[0][:, j.axis] > 0
        # perpendicular to the mapped face
        b, c = [x for x in range(3) if x != j.axis]
        assert abs(j.direction @ jac_pin[0][:, b]) < 1e-6 * np.linalg.norm(jac_pin[0][:, b])
        assert abs(j.direction @ jac_pin[0][:, c]) < 1e-6 * np.linalg.norm(jac_pin[0][:, c])


@pytest.mark.parametrize("twist", [0.0, np.pi / 2])
def test_joints_cross_the_seam_and_pair_the_right_cells(twist):
    vol = ring(twist=twist)
    t = _tiling(vol, (2, 2, 4), (2,))
    joints = J.plan_joints(t, _map(vol), _spec())
    seam = [j for j in joints if j.across_seam]
    assert len(seam) == 4
    for j in seam:
        assert j.pin_cell[2] == 3 and j.hole_cell[2] == 0
        pin_box, hole_box = t.cells[j.pin_cell].box, t.cells[j.hole_cell].box
        assert np.isclose(j.uvw_pin[2], pin_box[1, 2]) and np.isclose(j.uvw_hole[2], hole_box[0, 2])
        assert np.all(j.uvw_pin >= pin_box[0] - 1e-12) and np.all(j.uvw_pin <= pin_box[1] + 1e-12)
        assert np.all(j.uvw_hole >= hole_box[0] - 1e-12) and np.all(j.uvw_hole <= hole_box[1] + 1e-12)
        if twist == 0:
            assert j.pin_cell[:2] == j.hole_cell[:2]
    if twist:
        # turned by 90 degrees: (i, j) meets (1 - j, i)
        assert {(j.pin_cell[:2], j.hole_cell[:2]) for j in seam} == {((i, k), (1 - k, i)) for i in (0, 1)
                                                                         for k in (0, 1)}


def test_report_has_the_spec_keys():
    vol = _box()
    (j,) = J.plan_joints(_tiling(vol, (2, 1, 1)), _map(vol), _spec(radius=2.5, length=6))
    r = j.to_report()
    for key in ("pin_piece", "hole_piece", "axis", "center_mm", "direction", "radius_mm", "length_mm", "clearance_mm"):
        assert key in r
    assert (r["pin_piece"], r["hole_piece"], r["axis"]) == ("p0-0-0", "p1-0-0", "u")
    assert r["radius_mm"] == 2.5 and r["length_mm"] == 6 and r["direction"] == [1.0, 0.0, 0.0]


def test_default_sizes_follow_the_typical_face_and_stay_printable():
    vol = _box()
    t = _tiling(vol, (2, 2, 2))
    r, length = J.default_sizes(t, _map(vol))
    assert r == pytest.approx(0.12 * 10.0, abs=0.1)  # the median face's short side is 10 mm
    assert J.MIN_LENGTH <= length <= 0.35 * 10.0 + 1e-9
    assert J.plan_joints(t, _map(vol), _spec())[0].radius == r
    # a 6 mm plate still gets printable pins (the old 12% rule gave 0.3 mm ones there)
    plate = _box(60.0, 60.0, 6.0)
    tp = _tiling(plate, (4, 4, 1))
    r, length = J.default_sizes(tp, _map(plate))
    assert r >= J.MIN_RADIUS and length >= J.MIN_LENGTH
    joints = J.plan_joints(tp, _map(plate), _spec())
    assert len(joints) == len(tp.faces) and all(j.radius >= J.MIN_RADIUS for j in joints)


# ---------------------------------------------------------------------------------------------------------------------
# Fit errors, with what would fit


def test_a_pin_too_wide_for_its_face_shrinks_to_fit_and_says_so():
    vol = _box()
    t = _tiling(vol, (2, 1, 1))
    (j,) = J.plan_joints(t, _map(vol), _spec(radius=12.0, length=4.0))
    assert j.shrunk and J.MIN_RADIUS <= j.radius < 12.0
    # the face is 30 x 20 mm: the pin keeps its clearance and a wall to every edge
    assert j.reach + j.wall <= 10.0 + 1e-9
    assert j.to_report()["shrunk"] is True


def test_a_pin_too_long_for_its_piece_shrinks_its_length():
    vol = _box()
    t = _tiling(vol, (2, 1, 1))
    (j,) = J.plan_joints(t, _map(vol), _spec(radius=2.0, length=25.0))
    assert j.shrunk and J.MIN_LENGTH <= j.length < 25.0
    assert j.hole_depth + j.wall <= 20.0 + 1e-9  # the hole piece is 20 mm deep along u


def _expected_at_most(msg):
    return float(msg.split("expected joints.min_radius at most ")[1].split(" ")[0])


def test_a_piece_with_no_room_names_itself_and_what_would_fit():
    vol = _box(40.0, 6.0, 6.0)  # 6 x 6 mm faces: a 3 mm pin with clearance and wall needs 8.4 mm
    t = _tiling(vol, (2, 1, 1))
    spec = _spec(radius=3.0, length=4.0, min_radius=3.0)
    layout = J.place_joints(t, _map(vol), spec)
    assert layout.joints == () and layout.contacts[0]["reason"].startswith("no room")
    with pytest.raises(SpecError) as e:
        J.require_joined(t, layout, spec)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("joints: piece p0-0-0 gets no joint")
    best = _expected_at_most(msg)
    assert 0 < best < 3.0
    again = _spec(radius=best, length=4.0, min_radius=best)
    J.require_joined(t, J.place_joints(t, _map(vol), again), again)
    # the user may allow loose pieces
    J.require_joined(t, layout, _spec(radius=3.0, length=4.0, min_radius=3.0, allow=("loose",)))


def test_the_plan_cuts_a_curved_wall_so_that_every_face_holds_a_pin_along_its_split():
    # Cut across u first (its longest axis), the half cone's u faces all slide along their mean normal, 41 deg off the
    # two end faces: those lost their pins. The plan search cuts round v first, so every u face is parted alone.
    from volpuzzle import assembly as A

    vol = half_cone()
    fmap, t = _map(vol), _tiling(vol, (4, 4, 1))
    plain = J.place_joints(t, fmap, _spec(), A.plan_assembly(t, fmap))
    lost = [c for c in plain.contacts if c["room"] and not c["pinned"]]
    assert lost and all(c["reason"].startswith("tilt") for c in lost)
    layout, plan = J.place_planned_joints(t, fmap, _spec())
    assert all(c["pinned"] for c in layout.contacts if c["room"]) and sum(c["room"] for c in layout.contacts) == 24
    assert A.step_problems(t, plan) == []
    # every pin of a split points along that split's sliding direction, leaning at most MAX_TILT_DEG
    for (d, _), step in zip(A.split_directions(t, fmap, plan), plan.steps, strict=True):
        for j in A._across(layout.joints, step.moving, step.fixed):
            assert abs(float(np.dot(j.direction, d))) > 0.999999 and j.tilt_deg <= J.MAX_TILT_DEG
    # and the holes keep inside their pieces, measured on the real geometry (of the end columns, whose faces bend most)
    for idx, cell in t.cells.items():
        if idx[1] not in (0, 3):
            continue
        body = _body(fmap, cell)
        for j, role, s in _cell_solids(layout.joints, idx):
            if role == "hole":
                deep = s.trim_by_plane(j.direction, float(np.dot(j.direction, j.center)) + j.base_depth)
                assert _vol(deep - body) < 1e-4 * _vol(deep), (idx, j.axis)


@pytest.mark.parametrize("shape, grid, periodic", [("cone", (4, 4, 1), ()), ("cone", (3, 2, 2), ()),
                                                   ("ring", (2, 2, 8), (2,))])
def test_split_directions_per_face_are_those_of_every_face_tested_at_every_split(shape, grid, periodic):
    # _split_dirs looks only at the faces of the smaller side's cells; the plain scan of every face at every split
    # (n^2) must give the same faces, in the same order, with the same directions
    from volpuzzle import assembly as A

    vol = half_cone() if shape == "cone" else ring(twist=np.pi / 2)
    t = _tiling(vol, grid, periodic)
    fmap = _map(vol)
    plan = A.plan_assembly(t, fmap)
    expected = {}
    for (d, _), step in zip(A.split_directions(t, fmap, plan), plan.steps, strict=True):
        if not np.any(d):
            continue
        mv, fx = set(step.moving), set(step.fixed)
        for n, f in enumerate(t.faces):
            lo, up = tuple(f.lower), tuple(f.upper)
            if (lo in mv and up in fx) or (lo in fx and up in mv):
                expected[n] = d if up in mv else -d
    got = J._split_dirs(t, fmap, plan)
    assert list(got) == list(expected) and len(got) == len(t.faces)
    assert all(np.array_equal(got[n], expected[n]) for n in expected)


def test_side_distance_on_a_box_is_the_distance_to_the_nearest_other_face():
    # a box cell's faces are planes: across the tangent plane of the nearest sample is the exact distance
    t = _tiling(_box(), (1, 1, 1))
    sides = J._Sides(t, _map(_box()))
    rng = np.random.default_rng(5)
    p = rng.uniform([2.0, 2.0, 2.0], [38.0, 28.0, 18.0], size=(40, 3))
    size = np.array([40.0, 30.0, 20.0])
    for axis in range(3):
        for end in (0, 1):
            walls = [np.abs(p[:, a] - (size[a] if e else 0.0))
                     for a in range(3) for e in (0, 1) if (a, e) != (axis, end)]
            got = sides.distance((0, 0, 0), (axis, end), p)
            assert np.allclose(got, np.min(walls, axis=0), atol=1e-9)
    # a face farther than `beyond` from the points counts as inf; only the near one measures
    assert np.allclose(sides.distance((0, 0, 0), (0, 1), p[:1] * 0 + [1.0, 15.0, 10.0], beyond=5.0), 1.0)
    assert np.isinf(sides.distance((0, 0, 0), (0, 1), np.array([[20.0, 15.0, 10.0]]), beyond=5.0)).all()


def test_side_faces_two_cells_share_are_evaluated_once_and_as_each_cell_alone_gives_them():
    # a face the cell beside evaluated is reused: the same samples each cell finds evaluating its own six alone
    vol = ring(twist=np.pi / 2)
    t = _tiling(vol, (2, 2, 4), (2,))
    fmap = _map(vol)
    calls = []
    sides = J._Sides(t, fmap)
    plain = fmap.evaluate_with_jacobian
    sides.fmap = type("Counting", (), {"evaluate_with_jacobian": lambda _, uvw: calls.append(len(uvw)) or plain(uvw)})()
    for idx in t.cells:
        alone = J._Sides(t, fmap)
        for axis in range(3):
            for end in (0, 1):
                for got, want in zip(sides._face(idx, axis, end), alone._face(idx, axis, end), strict=True):
                    assert np.array_equal(got, want)
    # every distinct face (its axis, place and parameter box) evaluated once: fewer than the cells' 6 each, as the
    # inner faces are shared; the seam's two sides have parameters of their own and are two faces
    faces = {(a, round(float(c.box[e, a]), 12), *(round(float(c.box[k, b]), 12) for b in range(3) if b != a
                                                 for k in (0, 1)))
             for c in t.cells.values() for a in range(3) for e in (0, 1)}
    assert sum(calls) == len(faces) * sides.count ** 2 < 6 * len(t.cells) * sides.count ** 2


def test_face_shapes_of_all_faces_at_once_are_each_faces_own():
    # _face_shapes works on every face at once and evaluates the upper cell only where its points differ (the seam):
    # each face's figures must be what its own points give
    vol = ring(twist=np.pi / 2)
    t = _tiling(vol, (2, 2, 4), (2,))
    fmap = _map(vol)
    lengths = J._measure(t, fmap)
    shapes = J._face_shapes(t, fmap, lengths, 1.5)
    assert [s.face for s in shapes] == list(t.faces) and any(f.seam is not None for f in t.faces)
    for shape in shapes:
        f = shape.face
        for side, idx in ((-1, f.lower), (+1, f.upper)):
            x, jac = fmap.evaluate_with_jacobian(shape.uvw[side])
            assert np.array_equal(shape.jac[side], jac)
            assert np.array_equal(shape.lens[side], J._lens_at(lengths, idx, shape.fr[side]))
            rows = np.transpose(jac, (0, 2, 1))
            assert np.allclose(shape.tangents[side], rows / np.linalg.norm(rows, axis=2)[..., None], atol=1e-12)
        b, c = (f.axis + 1) % 3, (f.axis + 2) % 3
        nrm = np.cross(shape.jac[-1][:, :, b], shape.jac[-1][:, :, c])
        assert np.array_equal(shape.x, x if f.seam is None else fmap.evaluate(shape.uvw[-1]))
        assert np.allclose(np.abs(np.einsum("ki,ki->k", shape.nrm, nrm / np.linalg.norm(nrm, axis=1)[:, None])), 1.0)
        assert np.allclose(np.linalg.norm(shape.ring, axis=2).max(axis=1), 1.2 * 1.5, rtol=0.2)
    # default_sizes measures the same faces at their centres
    sides, depths = J._face_sides(lengths, t.faces)
    for n, f in enumerate(t.faces):
        b, c = (f.axis + 1) % 3, (f.axis + 2) % 3
        lo = J._lens_at(lengths, f.lower, np.array([[1.0 if a == f.axis else 0.5 for a in range(3)]]))[0]
        up = J._lens_at(lengths, f.upper, np.array([[0.0 if a == f.axis else 0.5 for a in range(3)]]))[0]
        assert sides[n] == min(lo[b], lo[c], up[b], up[c])
        assert list(depths[2 * n:2 * n + 2]) == [J._center_len(lengths, idx, f.axis) for idx in (f.lower, f.upper)]


@pytest.mark.parametrize("style", ["pin", "dowel"])
def test_fits_of_all_faces_at_once_are_each_faces_own(style):
    # placement measures every face at once (_fits_each on _stacks): each face's points must fit exactly where _fits
    # of that face alone says they do, for every size tried, leaning or upright, with and without the tilt limit
    vol = ring(twist=np.pi / 2)
    t = _tiling(vol, (3, 3, 4), (2,))
    fmap = _map(vol)
    setup = J._setup(t, fmap, _spec(style=style))
    rng = np.random.default_rng(5)
    # pins along the faces' normals, and along directions leaning up to ~40 degrees, past the tilt limit
    data = [J._directed(shape, None if n % 3 == 0 else shape.nrm[len(shape.nrm) // 2] + rng.uniform(-0.7, 0.7, 3))
            for n, shape in enumerate(setup.shapes)]
    assert {fd.face.axis for fd in data} == {0, 1, 2}
    stacks = J._stacks(data)
    assert sorted(n for st in stacks for n in st.numbers) == list(range(len(data)))
    seen = set()
    for s in setup.steps:
        for lean, limit in ((True, True), (True, False), (False, True)):
            each = J._fits_each(stacks, s, lean, limit)
            assert sorted(each) == list(range(len(data)))
            for n, fd in enumerate(data):
                alone = J._fits(fd, s, lean, limit)
                assert each[n].shape == alone.shape and np.array_equal(each[n], alone)
                seen.add(bool(alone.any()))
    assert seen == {True, False}  # some faces fit somewhere and some nowhere: the comparison means something


def test_side_distance_beside_a_face_goes_straight_to_its_rim():
    # one face, its samples on a 3 x 3 grid in z = 0; the rim samples are not inside it
    g = np.array([0.0, 1.0, 2.0])
    x = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(1, 9, 3)
    nrm = np.tile([0.0, 0.0, 1.0], (1, 9, 1))
    inner = np.zeros((1, 9), bool)
    inner[0, 4] = True
    p = np.array([[1.1, 0.9, 0.5], [5.0, 1.0, 3.0]])
    # above the middle: its tangent plane; beside the face: the nearest rim sample (2, 1, 0)
    assert np.allclose(K.face_distance(p, x, nrm, inner, np.ones(1, bool)), [0.5, np.hypot(3.0, 3.0)])
    # a face left out is not measured
    assert np.isinf(K.face_distance(p, x, nrm, inner, np.zeros(1, bool))).all()


def test_cylinders_said_apart_are_apart_by_the_gap():
    # any two cylinders apart_all passes have every point of one at least gap from every point of the other
    rng = np.random.default_rng(11)

    def solid(p0, p1, r, n=3000):
        d = p1 - p0
        u = d / np.linalg.norm(d)
        a = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(u, a)
        t, phi, rho = rng.uniform(0, 1, n), rng.uniform(0, 2 * np.pi, n), r * np.sqrt(rng.uniform(0, 1, n))
        return p0 + t[:, None] * d + (rho * np.cos(phi))[:, None] * a + (rho * np.sin(phi))[:, None] * b

    passed = failed = 0
    for _ in range(60):
        p0, q0 = rng.uniform(-4, 4, (2, 3))
        p1, q1 = p0 + rng.uniform(-5, 5, 3), q0 + rng.uniform(-5, 5, 3)
        rp, rq, gap = rng.uniform(0.5, 1.5, 3)
        ok = J._Cylinders(p0[None], p1[None], rp).apart_all([(q0, q1, rq)], gap)[0]
        if ok:
            from scipy.spatial import cKDTree

            near, _ = cKDTree(solid(q0, q1, rq)).query(solid(p0, p1, rp))
            assert near.min() >= gap - 0.05
            passed += 1
        else:
            failed += 1
    assert passed > 5 and failed > 5  # both answers were exercised


def test_reading_joints_does_not_load_the_compiled_kernels():
    # `volpuzzle check` reads a build's joints through this module: numba (~0.5 s to import) is only for placing them
    import subprocess
    import sys

    code = "import sys, volpuzzle.joint, volpuzzle.check; print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
