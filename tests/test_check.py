"""The build's self-checks: closed pieces, volume sum, no overlaps."""

import sys

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle.check import (
    assert_passed,
    candidate_pairs,
    check_directory,
    check_pieces,
    closed_problem,
    overlap_volume,
    piece_solid,
    shifted_overlap,
    signed_volume,
)
from volpuzzle.errors import GeometryError, VolpuzzleError
from volpuzzle.geometry import manifold_from_mesh


def split_box(n=2, size=10.0):
    """An exact n x n x n split of a cube of side n * size, as (id, mesh) pairs."""
    out = []
    for i in range(n):
        for j in range(n):
            for k in range(n):
                b = trimesh.creation.box(extents=(size, size, size))
                b.apply_translation(np.array([i, j, k], float) * size + size / 2)
                out.append((f"p{i}-{j}-{k}", b))
    return out


def test_exact_split_passes():
    checks = check_pieces(split_box(), 8000.0)
    assert checks["passed"], checks["failures"]
    assert checks["all_closed"] and checks["closed_failures"] == []
    assert checks["volume_sum_mm3"] == pytest.approx(8000.0)
    assert abs(checks["volume_error"]) < 1e-12
    assert checks["max_overlap_mm3"] == 0.0
    assert checks["overlap_limit_mm3"] == pytest.approx(1.0)  # 1e-3 of the smallest piece (1000 mm^3)
    assert_passed(checks)


def test_moved_piece_overlaps_its_neighbour():
    pieces = split_box()
    moved = pieces[0][1].copy()
    moved.apply_translation([1.0, 0, 0])
    pieces[0] = (pieces[0][0], moved)
    checks = check_pieces(pieces, 8000.0)
    assert not checks["passed"]
    assert abs(checks["max_overlap_mm3"] - 100.0) <= checks["overlap_error_bound_mm3"] <= 0.01
    assert checks["max_overlap_pair"] == ["p0-0-0", "p1-0-0"]
    assert any("overlap by" in f for f in checks["failures"])
    with pytest.raises(GeometryError, match="p0-0-0 and p1-0-0 overlap"):
        assert_passed(checks)


def test_a_piece_the_engine_cannot_make_a_solid_of_is_named_once_and_its_pairs_not_measured(monkeypatch):
    # p0-0-0 is moved into two neighbours (two pairs to measure); the engine refuses p1-0-0's solid: it is named once,
    # its pair is left unmeasured, and the other pair is still measured
    import volpuzzle.check as C

    pieces = split_box()
    moved = pieces[0][1].copy()
    moved.apply_translation([1.0, 1.0, 0])
    pieces[0] = (pieces[0][0], moved)
    plain = check_pieces([(pid, mesh.copy()) for pid, mesh in pieces], 8000.0)
    real = C.piece_solid
    monkeypatch.setattr(C, "piece_solid", lambda mesh, pid: "piece p1-0-0: refused" if pid == "p1-0-0"
                        else real(mesh, pid))
    checks = check_pieces(pieces, 8000.0)
    assert [f for f in checks["failures"] if "not measured" in f] == [
        "piece p1-0-0: refused; its overlaps were not measured"]
    assert checks["overlap_pairs_tested"] == plain["overlap_pairs_tested"] - 1
    assert checks["max_overlap_pair"] == ["p0-0-0", "p0-1-0"] and not checks["passed"]
    # what the overlap check found of each piece's solid is remembered: the joint check asks it without a solid
    monkeypatch.setattr(C, "piece_solid", lambda _mesh, pid: pytest.fail(f"{pid}'s solid was made again"))
    measured = {"p0-0-0", "p1-0-0", "p0-1-0", "p1-1-0"}
    assert {pid: C.solid_problem(mesh, pid) for pid, mesh in pieces if pid in measured} == {
        "p0-0-0": None, "p1-0-0": "piece p1-0-0: refused", "p0-1-0": None, "p1-1-0": None}


@settings(max_examples=8, deadline=None)
@given(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0))
def test_shifted_overlap_is_within_its_bound(dx, dy):
    pieces = split_box()
    a = manifold_from_mesh(pieces[0][1].vertices, pieces[0][1].faces, "a")
    b = manifold_from_mesh(pieces[4][1].vertices, pieces[4][1].faces, "b").translate((dx, dy, 0.0))
    exact = overlap_volume(a, b)
    assert exact == pytest.approx(max(0.0, -dx) * (10 - abs(dy)) * 10, abs=1e-9)
    estimate, bound = shifted_overlap(a, b, 0.01)
    assert abs(estimate - exact) <= bound + 1e-9 and bound <= 0.01 + 1e-12


def test_exact_and_shifted_checks_agree():
    pieces = split_box()
    moved = pieces[0][1].copy().apply_translation([0, 0.5, 0.25])
    pieces[0] = (pieces[0][0], moved)
    fast, exact = check_pieces(pieces, 8000.0), check_pieces(pieces, 8000.0, exact_overlaps=True)
    assert fast["max_overlap_pair"] == exact["max_overlap_pair"]
    assert abs(fast["max_overlap_mm3"] - exact["max_overlap_mm3"]) <= fast["overlap_error_bound_mm3"]


def test_open_mesh_is_not_closed():
    pieces = split_box()
    holed = pieces[3][1].copy()
    holed.update_faces(np.arange(len(holed.faces) - 1))
    pieces[3] = (pieces[3][0], holed)
    checks = check_pieces(pieces, 8000.0, volume_tolerance=0.5)
    assert not checks["all_closed"] and not checks["passed"]
    assert checks["closed_failures"] == ["p0-1-1"]
    assert any("p0-1-1 is not a closed solid: not watertight" in f for f in checks["failures"])


def test_volume_mismatch():
    checks = check_pieces(split_box(), 8100.0)
    assert not checks["passed"]
    assert checks["volume_error"] == pytest.approx(-100 / 8100)
    assert any("volumes add up to 8000" in f for f in checks["failures"])


def test_inverted_and_split_bodies_are_named():
    box = trimesh.creation.box()
    inverted = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    assert "not positive" in closed_problem(inverted)
    two = trimesh.util.concatenate([box, box.copy().apply_translation([5, 0, 0])])
    assert closed_problem(two) == "2 separate bodies, expected 1"
    opened = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    assert closed_problem(opened) == "not watertight (3 open edges)"
    flipped = box.faces.copy()
    flipped[0] = flipped[0, ::-1]
    assert closed_problem(trimesh.Trimesh(box.vertices, flipped, process=False)) == "inconsistent winding"
    assert closed_problem(box) is None


def _trimesh_verdict(mesh):
    """closed_problem's own trimesh route: what the fast path must agree with."""
    m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True, validate=False)
    if not (m.is_watertight and m.is_winding_consistent and m.volume > 0):
        return False
    # one body across edges: two parts that touch at a vertex are two (trimesh's body_count joins them)
    return len(trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(m.faces)))) == 1


def _broken(kind):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    v, f = sphere.vertices.copy(), sphere.faces.copy()
    if kind == "open":
        f = f[1:]
    elif kind == "inverted":
        f = f[:, ::-1]
    elif kind == "one flipped":
        f[7] = f[7, ::-1]
    elif kind == "two bodies":
        v, f = np.concatenate([v, v + 20.0]), np.concatenate([f, f + len(v)])
    elif kind == "unwelded":  # as an STL reads: every triangle its own three vertices, the same solid once merged
        v, f = v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)
    elif kind == "a stray vertex":
        v = np.concatenate([v, [[50.0, 0.0, 0.0]]])
    elif kind == "a repeated vertex":
        f[3, 1] = f[3, 0]
    elif kind == "a doubled triangle":
        f = np.concatenate([f, f[:1]])
    elif kind == "a pinch":  # a second sphere on top, sharing the first one's highest vertex and nothing else
        top = int(np.argmax(v[:, 2]))
        second = v + 2.0 * v[top]
        low = int(np.argmin(np.linalg.norm(second - v[top], axis=1)))  # the second sphere's lowest, on the top
        index = np.arange(len(v)) + len(v) - (np.arange(len(v)) > low)
        index[low] = top
        v, f = np.concatenate([v, np.delete(second, low, axis=0)]), np.concatenate([f, index[f]])
    elif kind == "a hair-split corner":
        # a wedge's apex split in two 0.8e-8 mm apart, where x * 1e8 has a fraction just above 0.5: trimesh's
        # merge joins them (rounding x * 1e8), its unique_rows(digits=8) would not (rounding x * 1e8 - 1e-6)
        v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0.5000001e-8, 0, 10], [1.3e-8, 0, 10]], float)
        f = np.array([[2, 1, 0], [1, 3, 0], [4, 3, 1], [2, 4, 1], [0, 3, 2], [3, 4, 2]])
    return trimesh.Trimesh(v, f, process=False)


@pytest.mark.parametrize("kind", ["closed", "open", "inverted", "one flipped", "two bodies", "unwelded",
                                  "a stray vertex", "a repeated vertex", "a doubled triangle", "a pinch",
                                  "a hair-split corner"])
def test_the_quick_closed_test_never_passes_what_trimesh_refuses(kind):
    from volpuzzle.check import _plainly_closed

    mesh = _broken(kind)
    quick = _plainly_closed(mesh)
    # the quick test may only say yes where trimesh does; a no sends the mesh to trimesh for the reason
    assert not quick or _trimesh_verdict(mesh)
    assert quick == (kind == "closed")
    assert (closed_problem(mesh) is None) == _trimesh_verdict(mesh)
    if kind == "a pinch":
        assert closed_problem(mesh) == "2 separate bodies that meet only at vertices (a pinch), expected 1"
    if kind == "a hair-split corner":  # as it is, a closed wedge; as every reader merges it, not
        assert trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).is_watertight
        assert closed_problem(mesh).startswith("not watertight")


@settings(max_examples=10, deadline=None)
@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-50, 50), st.floats(0.5, 20))
def test_signed_volume_of_a_moved_box(x, y, z, s):
    b = trimesh.creation.box(extents=(s, 2 * s, 3 * s)).apply_translation([x, y, z])
    assert signed_volume(b.vertices, b.faces) == pytest.approx(6 * s ** 3, rel=1e-9)


def test_candidate_pairs_skip_touching_boxes():
    bounds = np.array([[[0, 0, 0], [1, 1, 1]], [[1, 0, 0], [2, 1, 1]], [[0.5, 0.5, 0.5], [1.5, 1.5, 1.5]]], float)
    assert candidate_pairs(bounds) == [(0, 2), (1, 2)]


def test_check_directory_refuses_a_folder_without_report(tmp_path):
    with pytest.raises(VolpuzzleError, match="no report.json"):
        check_directory(tmp_path)


def test_a_mesh_is_converted_and_judged_once_until_it_changes():
    box = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    solid = piece_solid(box, "p0-0-0")
    assert piece_solid(box, "p0-0-0") is solid and closed_problem(box) is None
    # an equal copy is another object with its own solid
    assert piece_solid(box.copy(), "p0-0-0") is not solid
    box.apply_translation([3.0, 0.0, 0.0])
    moved = piece_solid(box, "p0-0-0")
    assert moved is not solid and moved.bounding_box()[0] == pytest.approx(-2.0)
    box.update_faces(np.arange(len(box.faces) - 1))
    assert "not watertight" in closed_problem(box)
    assert isinstance(piece_solid(box, "p0-0-0"), str)


def test_checks_on_solids_made_earlier_still_see_a_moved_piece():
    pieces = split_box()
    assert check_pieces(pieces, 8000.0)["passed"]
    pieces[0][1].apply_translation([1.0, 0.0, 0.0])  # the same mesh object, edited after its first check
    checks = check_pieces(pieces, 8000.0)
    assert not checks["passed"] and checks["max_overlap_pair"] == ["p0-0-0", "p1-0-0"]


@pytest.mark.parametrize("limit", [0.0, 20.0])
def test_candidate_pairs_are_exactly_the_boxes_sharing_more_than_the_limit(limit):
    # the vectorised sweep, in blocks small enough to split rows, against every pair tested one by one
    rng = np.random.default_rng(4)
    lo = rng.uniform(0, 60, (200, 3))
    bounds = np.stack([lo, lo + rng.uniform(1, 12, (200, 3))], axis=1)
    bounds[7] = bounds[6]  # identical boxes
    bounds[9, 0, 0] = bounds[8, 1, 0]  # touching along x
    want = []
    for i in range(len(bounds)):
        for j in range(i + 1, len(bounds)):
            common = np.minimum(bounds[i, 1], bounds[j, 1]) - np.maximum(bounds[i, 0], bounds[j, 0])
            if np.all(common > 0) and np.prod(common) > limit:
                want.append((i, j))
    assert want  # the scene has overlapping boxes to find
    assert candidate_pairs(bounds, limit) == want
    assert candidate_pairs(bounds, limit, chunk=5) == want


def _slab(x0, x1):
    """A 10 x 10 box from x0 to x1 along x, its faces finely triangulated (vertices every ~1 mm)."""
    box = trimesh.creation.box([x1 - x0, 10, 10]).subdivide().subdivide().subdivide()
    return box.apply_translation([(x0 + x1) / 2, 0, 0])


def test_face_gaps_after_a_touching_pair_keep_the_least_gap_and_its_pair():
    from volpuzzle.check import _face_gaps, piece_solid

    # p0 | p1 touch; p1 and p2 stand 0.1 apart, p2 and p3 0.2: the least gap is p0/p1's 0 whatever comes after
    meshes = {"p0": _slab(0, 10), "p1": _slab(10, 20), "p2": _slab(20.1, 30), "p3": _slab(30.2, 40)}
    gaps = _face_gaps(meshes, 0.3)
    assert [g[:2] for g in gaps] == [("p0", "p1"), ("p1", "p2"), ("p2", "p3")]
    exact = [float(piece_solid(meshes[a], a).min_gap(piece_solid(meshes[b], b), 0.9)) for a, b, *_ in gaps]
    assert exact == pytest.approx([0.0, 0.1, 0.2], abs=1e-9)
    assert gaps[0][3] == 0.0
    assert all(g[3] >= e - 1e-9 for g, e in zip(gaps, exact, strict=True))  # later pairs: an upper bound, not less
    assert min(gaps, key=lambda g: g[3])[:2] == ("p0", "p1")
    # without the touching pair every gap is the engine's
    del meshes["p0"]
    assert [g[3] for g in _face_gaps(meshes, 0.3)] == pytest.approx([0.1, 0.2], abs=1e-9)


def test_pieces_the_face_gaps_find_apart_skip_their_overlap_boolean():
    import manifold3d as m3

    from volpuzzle.check import neighbour_gaps, pairs_apart

    def block(lo, hi):
        return m3.Manifold.cube(tuple(np.subtract(hi, lo))).translate(tuple(lo))

    def mesh(solid):
        out = solid.to_mesh()
        return trimesh.Trimesh(out.vert_properties[:, :3], out.tri_verts).subdivide().subdivide().subdivide()

    # a stepped cut, 0.1 mm apart: the boxes share 1.9 x 10 x 10 mm, so only a Boolean or the gap tells them apart
    a = block((10, -5, -5), (20, 5, 5)) + block((19, 0, -5), (22, 5, 5))
    b = block((20.1, -5, -5), (30, -0.1, 5)) + block((22.1, -0.2, -5), (30, 5, 5))
    meshes = {"p1": mesh(a), "p2": mesh(b)}
    gaps = neighbour_gaps(meshes, 0.3)
    assert [g[:2] for g in gaps] == [("p1", "p2")] and gaps[0][3] == pytest.approx(0.1, abs=1e-6)
    apart = pairs_apart(gaps, meshes)
    assert apart == {frozenset(("p1", "p2")): gaps[0][3]}
    pieces = sorted(meshes.items())
    volume = float(a.volume() + b.volume())
    plain, quick = check_pieces(pieces, volume), check_pieces(pieces, volume, apart=apart)
    assert quick["overlap_pairs_apart"] == 1 and plain["overlap_pairs_apart"] == 0
    assert quick["overlap_pairs_tested"] == plain["overlap_pairs_tested"] == 1
    assert quick["max_overlap_mm3"] == plain["max_overlap_mm3"] == 0.0 and quick["passed"]


def test_a_touching_pair_ends_what_the_face_gaps_prove():
    from volpuzzle.check import neighbour_gaps, pairs_apart

    # from the first pair that touches on, the gaps are the closest vertices', which prove nothing
    meshes = {"p0": _slab(0, 10), "p1": _slab(10, 20), "p2": _slab(20.1, 30)}
    assert pairs_apart(neighbour_gaps(meshes, 0.3), meshes) == {}
    # nor is a gap the engine could not measure (NaN) a proof
    assert pairs_apart([("p1", "p2", 0.1, float("nan"))], meshes) == {}


def test_a_piece_inside_another_is_not_proved_apart_by_its_gap():
    from volpuzzle.check import neighbour_gaps, pairs_apart

    # p1 lies inside p0, 0.1 mm under its face: their surfaces never meet, yet they overlap by all of p1
    p0 = _slab(0, 10)
    p1 = trimesh.creation.box([4, 4, 4]).subdivide().subdivide().subdivide().apply_translation([7.9, 0, 0])
    meshes = {"p0": p0, "p1": p1}
    gaps = neighbour_gaps(meshes, 0.3)
    assert [g[:2] for g in gaps] == [("p0", "p1")]
    assert pairs_apart(gaps, meshes) == {}
    # the engine says 0 here itself; a gap above 0 would not pass either, p1's box being inside p0's
    assert pairs_apart([("p0", "p1", 0.1, 0.1)], meshes) == {}
    assert pairs_apart([("p0", "p1", 0.1, 0.1)], {"p0": p0, "p1": p1.copy().apply_translation([5, 0, 0])})
    checks = check_pieces(sorted(meshes.items()), 1064.0, apart=pairs_apart(gaps, meshes))
    assert checks["max_overlap_mm3"] == pytest.approx(64.0, abs=1.0) and not checks["passed"]


def test_face_gaps_engine_gap_is_the_whole_reach_gap_where_no_vertices_face_each_other():
    from volpuzzle.check import _face_gaps, piece_solid

    # p1's vertices sit between p0's (another triangulation, shifted across the face): the least gap, 0.1 mm, is
    # between a vertex and a triangle, less than the closest vertices, and the engine's search must still reach it
    p0 = _slab(0, 10)
    p1 = trimesh.creation.box([10, 10, 10]).subdivide().subdivide().apply_translation([15.1, 0.37, 0.29])
    meshes = {"p0": p0, "p1": p1}
    (gap,) = _face_gaps(meshes, 0.3)
    full = float(piece_solid(p0, "p0").min_gap(piece_solid(p1, "p1"), 0.9))
    assert full == pytest.approx(0.1, abs=1e-9)
    assert gap[3] == full  # the same float as the engine's over the whole reach


def test_a_snap_joint_fits_its_own_necked_hole():
    # `volpuzzle check` of a built snap-pin puzzle failed every joint: its room test was a plain cylinder of the
    # pin's radius, which the snap hole's neck (0.9 r near the tip) cuts into
    import manifold3d as m3
    import trimesh

    from volpuzzle.check import check_joints
    from volpuzzle.joint import _snap_profile

    r, length, cl, axial = 1.5, 3.0, 0.15, 0.3

    def revolved(grow, extra):
        prof = _snap_profile(r, length, 1.0, grow=grow, extra=extra)
        return m3.Manifold.revolve(m3.CrossSection([[(0.0, -1.0)] + prof + [(0.0, prof[-1][1])]]), 64)

    def mesh(solid):
        out = solid.to_mesh()
        return trimesh.Trimesh(out.vert_properties[:, :3], out.tri_verts, process=True)

    below = m3.Manifold.cube([10, 10, 5], True).translate([0, 0, -2.5])
    above = m3.Manifold.cube([10, 10, 5], True).translate([0, 0, 2.5])
    meshes = {"a": mesh(below + revolved(0.0, 0.0)), "b": mesh(above - revolved(cl, axial))}
    joint = {"pin_piece": "a", "hole_piece": "b", "center_mm": [0, 0, 0], "direction": [0, 0, 1],
             "radius_mm": r, "length_mm": length, "clearance_mm": cl, "style": "pin", "shape": "snap"}
    assert check_joints(meshes, [joint]) == []
    # a hole not dug is still found
    meshes["b"] = mesh(above)
    assert "does not fit its hole in b" in check_joints(meshes, [joint])[0]


@pytest.mark.parametrize("exact", [False, True])
def test_pairs_whose_parts_lie_apart_need_no_boolean(monkeypatch, exact):
    # a bar across a box's edge, 0.5 mm off it, their boxes overlapping: the parts' extents prove them disjoint
    # without the engine, and the figures are the Boolean's (0 and the same error bound)
    from volpuzzle import check as C
    from volpuzzle.assembly import parts_apart, piece_extents
    from volpuzzle.workers import MeshRef

    near = trimesh.creation.box([10, 10, 10]).subdivide()
    bar = trimesh.creation.box([10, 2, 2]).subdivide()
    bar.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [0, 1, 0]))
    bar.apply_translation(np.array([5.0, 0.0, 5.0]) + 1.5 * np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0))
    assert np.all(np.minimum(near.bounds[1], bar.bounds[1]) > np.maximum(near.bounds[0], bar.bounds[0]))
    inside = trimesh.creation.box([4, 4, 4]).apply_translation([4, 0, 0])  # overlaps near by 3 x 4 x 4
    meshes = {0: near, 1: bar, 2: inside}
    assert parts_apart(piece_extents(near), piece_extents(bar))
    assert not parts_apart(piece_extents(near), piece_extents(inside))
    assert not parts_apart(piece_extents(near), piece_extents(bar), shift=[-0.5, 0, -0.5])  # moved onto the edge
    shared = ({k: (MeshRef(m), f"p{k}") for k, m in meshes.items()}, exact, 0.01)
    measured = C._overlaps(shared, [(0, 1), (0, 2)])
    solids = [C.piece_solid(m, f"p{k}") for k, m in meshes.items()]
    booleans = (lambda a, b: (C.overlap_volume(a, b), 0.0)) if exact else (lambda a, b: C.shifted_overlap(a, b, 0.01))
    assert [m[:2] for m in measured] == [booleans(solids[0], solids[1]), booleans(solids[0], solids[2])]
    assert [m[2] for m in measured] == [(None, None)] * 2  # the engine made every solid
    assert measured[0][0] == 0.0 and measured[1][0] == pytest.approx(48.0, abs=0.1)
    calls = []
    real = C.overlap_volume
    monkeypatch.setattr(C, "overlap_volume", lambda a, b: calls.append(1) or real(a, b))
    assert C._overlaps(shared, [(0, 1), (0, 2)]) == measured and len(calls) == 1


def test_a_pieces_joints_tested_together_still_name_the_one_that_fails():
    # a piece's pins (and its holes) are first measured together on the union of their cylinders: two pins that fit
    # pass in that one Boolean, and of two where one hole was not dug only that joint fails, with its own figure
    import manifold3d as m3
    import trimesh

    from volpuzzle.check import check_joints

    def mesh(solid):
        out = solid.to_mesh()
        return trimesh.Trimesh(out.vert_properties[:, :3], out.tri_verts, process=True)

    pins = [(-3.0, 0.0), (3.0, 0.0)]
    below = m3.Manifold.cube([12, 8, 5], True).translate([0, 0, -2.5])
    above = m3.Manifold.cube([12, 8, 5], True).translate([0, 0, 2.5])
    for x, y in pins:
        below = below + m3.Manifold.cylinder(3.0, 1.0, 1.0, 48).translate([x, y, 0])
    holes = [m3.Manifold.cylinder(3.3, 1.15, 1.15, 48).translate([x, y, 0]) for x, y in pins]
    joints = [{"pin_piece": "a", "hole_piece": "b", "center_mm": [x, y, 0], "direction": [0, 0, 1], "radius_mm": 1.0,
               "length_mm": 3.0, "clearance_mm": 0.15, "style": "pin", "shape": "cylinder"} for x, y in pins]
    assert check_joints({"a": mesh(below), "b": mesh(above - holes[0] - holes[1])}, joints) == []
    failures = check_joints({"a": mesh(below), "b": mesh(above - holes[0])}, joints)
    assert len(failures) == 1 and "does not fit its hole in b" in failures[0]
    alone = check_joints({"a": mesh(below), "b": mesh(above - holes[0])}, joints[1:])
    assert failures == alone  # the same volume as when that joint is tested by itself


def test_a_test_cylinder_no_triangle_reaches_lies_wholly_inside_or_outside():
    # cylinder_side against the engine: a cylinder it places inside is wholly in the solid, one it places outside
    # shares nothing with it, and one that the surface crosses (by any share) is never placed
    import manifold3d as m3

    from volpuzzle._check_kernels import cylinder_side
    from volpuzzle.geometry import cylinder
    from volpuzzle.grid import frame_from_direction

    solid = (m3.Manifold.cube([20, 16, 12], True) - m3.Manifold.sphere(7.0, 40).translate([10, 8, 6])
             + m3.Manifold.cylinder(10, 3, 3, 24).translate([-4, 0, 6])).rotate([17, -29, 41])
    out = solid.to_mesh()
    vertices = np.ascontiguousarray(out.vert_properties[:, :3], dtype=np.float64)
    faces = np.ascontiguousarray(out.tri_verts, dtype=np.int64)
    rng = np.random.default_rng(3)
    seen = {1: 0, -1: 0, 0: 0}
    for _ in range(300):
        center = rng.uniform(-9.0, 9.0, 3)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        radius, start = rng.uniform(0.3, 2.5), rng.uniform(-2.0, 1.0)
        stop = start + rng.uniform(0.5, 6.0)
        side = cylinder_side(vertices, faces, center, *frame_from_direction(d), radius, start, stop, 1e-4)
        cyl = cylinder(center, d, radius, start, stop, "test")
        shared = (cyl ^ solid).volume()
        if side == 1:
            assert shared == pytest.approx(cyl.volume(), rel=1e-9)
        elif side == -1:
            assert shared == 0.0
        seen[side] += 1
    assert min(seen.values()) > 30, seen  # every answer was given often


def test_a_ray_through_an_edge_gives_up():
    # a box's faces split along their diagonals: the axis of a cylinder through the box's centre along z meets the
    # diagonal edges of the top and bottom faces, where the count of crossings cannot be trusted (the engine measures
    # that test); askew, the count places the cylinder
    from volpuzzle._check_kernels import cylinder_side
    from volpuzzle.grid import frame_from_direction

    box = trimesh.creation.box([10, 10, 10])
    v, f = np.ascontiguousarray(box.vertices, dtype=np.float64), np.ascontiguousarray(box.faces, dtype=np.int64)
    straight = frame_from_direction(np.array([0.0, 0.0, 1.0]))
    assert cylinder_side(v, f, np.zeros(3), *straight, 1.0, -1.0, 1.0, 1e-4) == 0
    # and one within rounding of the edge (1e-13 mm off it), where the side of the edge could be either
    assert cylinder_side(v, f, np.array([1e-13, 0.0, 0.0]), *straight, 1.0, -1.0, 1.0, 1e-4) == 0
    aslant = np.array([0.1, 0.2, 1.0]) / np.linalg.norm([0.1, 0.2, 1.0])
    assert cylinder_side(v, f, np.array([0.3, -0.2, 0.1]), *frame_from_direction(aslant), 1.0, -1.0, 1.0, 1e-4) == 1
    assert cylinder_side(v, f, np.array([9.0, 0.0, 0.0]), *frame_from_direction(aslant), 1.0, -1.0, 1.0, 1e-4) == -1


@pytest.mark.parametrize("ulps", [0, 1, 3, 1000])
def test_a_surface_crossing_the_cylinder_is_seen_when_a_corner_lies_on_the_slabs_bound(ulps):
    # a tetrahedron whose face ABC crosses the pin's cylinder (z 0..1, radius 1) at z ~ 0.3, with corner B at (or a
    # hair below) the slab's lower bound: clipping leaves an edge of no length there, which once made the polygon's
    # inside test fail and the kernel place the cylinder inside, a test the engine finds 30% outside
    from volpuzzle import check
    from volpuzzle._check_kernels import cylinder_side
    from volpuzzle.geometry import kernel_arrays

    radius, start, stop = 1.0, 0.0, 1.0
    margin = check._CLEAR_MARGIN + 1e-9 * 100.0  # as _left_to_measure gives it for a piece 100 mm across
    lo = start - margin
    zb = lo - ulps * np.spacing(lo)
    corners = np.array([[-100, -100, -1.3999], [100, -100, zb], [0, 100, 1.3], [5, 3, 50.0]])
    mesh = trimesh.Trimesh(corners, [[0, 1, 2], [0, 1, 3], [1, 2, 3], [2, 0, 3]], process=False)
    trimesh.repair.fix_normals(mesh)
    assert mesh.is_watertight and mesh.volume > 0
    v, f = kernel_arrays(mesh)
    frame = (np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    assert cylinder_side(v, f, np.zeros(3), *frame, radius, start, stop, margin) == 0
    test = (0, 0, "inside", [((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), radius, start, stop)])
    outside = check._measured("inside", check._test_shape(test[3]), check.piece_solid(mesh, "p"))
    assert outside > 0.25 * np.pi * radius ** 2 * (stop - start)  # what the engine then measures, and fails


def test_the_joint_check_keeps_to_the_engine_until_its_kernel_is_ready(monkeypatch):
    # compiling the kernel (~1.7 s) would cost a first build of a few pieces on a new machine more than it saves
    from volpuzzle import precompile

    monkeypatch.setattr(precompile, "ready", lambda _dispatcher: False)
    assert not precompile.usable("volpuzzle._check_kernels", "cylinder_side")
    monkeypatch.setattr(precompile, "ready", lambda _dispatcher: True)
    assert precompile.usable("volpuzzle._check_kernels", "cylinder_side")
    monkeypatch.delitem(sys.modules, "numba")  # `volpuzzle check` of a few pieces does not start numba for it
    assert not precompile.usable("volpuzzle._check_kernels", "cylinder_side")


def _solid_arrays(solid):
    out = solid.to_mesh()
    return (np.ascontiguousarray(out.vert_properties[:, :3], dtype=np.float64),
            np.ascontiguousarray(out.tri_verts, dtype=np.int64))


def test_the_surface_gap_kernel_gives_the_engines_gap():
    # surface_gap against the engine's min_gap, two non-convex solids in 240 random placements: apart, within the
    # search, overlapping (0) and crossing without a corner inside the other (the edge-through-triangle test)
    import manifold3d as m3

    from volpuzzle._check_kernels import surface_gap

    a = (m3.Manifold.cube([6, 5, 4], True) - m3.Manifold.sphere(2.5, 24).translate([3, 2.5, 2])).rotate([11, 23, -7])
    b = (m3.Manifold.cylinder(5, 1.5, 0.8, 20).translate([0, 0, -2.5])
         + m3.Manifold.cube([1, 7, 1], True)).rotate([-31, 5, 60])
    va, fa = _solid_arrays(a)
    rng = np.random.default_rng(11)
    seen = {"overlap": 0, "near": 0, "far": 0}
    for _ in range(240):
        moved = b.rotate(tuple(rng.uniform(-180, 180, 3))).translate(tuple(rng.uniform(-7.5, 7.5, 3)))
        vb, fb = _solid_arrays(moved)
        engine = float(a.min_gap(moved, 2.0))
        kernel = surface_gap(va, fa, vb, fb, np.zeros(3), 2.0, 0.0)
        if (a ^ moved).volume() > 0.0:
            assert kernel == 0.0 and engine == 0.0
            seen["overlap"] += 1
        elif engine < 2.0:
            # the engine's own is off by up to ~2e-7 mm here, where two edges lie nearly parallel (checked by hand
            # at five such pairs: the kernel's agreed with a minimization over both triangles to 1e-11)
            assert abs(kernel - engine) <= 1e-6
            seen["near"] += 1
        else:
            assert kernel == 2.0
            seen["far"] += 1
    assert min(seen.values()) > 30, seen
    # a thin plate through a cube's face, no corner of either inside the other's triangles: only edges cross faces
    plate = m3.Manifold.cube([0.2, 8, 8], True).rotate([0, 0, 30])
    cube = m3.Manifold.cube([4, 4, 4], True).translate([0, 0, 5.5])
    assert surface_gap(*_solid_arrays(plate), *_solid_arrays(cube), np.zeros(3), 1.0, 0.0) == 0.0


def test_the_surface_gap_of_a_moved_mesh_is_that_of_the_mesh_moved_there():
    import manifold3d as m3

    from volpuzzle._check_kernels import surface_gap

    va, fa = _solid_arrays(m3.Manifold.sphere(3.0, 32))
    vb, fb = _solid_arrays(m3.Manifold.cube([2, 2, 2], True).translate([6.5, 0, 0]))
    shift = np.array([0.7, 0.1, -0.2])
    moved = surface_gap(va, fa, vb, fb, shift, 5.0, 0.0)
    assert moved == surface_gap(va + shift, fa, vb, fb, np.zeros(3), 5.0, 0.0)
    assert 1.3 < moved < surface_gap(va, fa, vb, fb, np.zeros(3), 5.0, 0.0)


def test_the_surface_gap_kernel_finds_the_nearest_pair_of_all():
    # the pairs it passes over by their bounds hold none nearer than the one it finds: every pair, measured
    import manifold3d as m3

    from volpuzzle._check_kernels import _triangles_apart, surface_gap

    a = m3.Manifold.sphere(2.0, 16).scale([1.5, 1.0, 0.7])
    rng = np.random.default_rng(5)
    for _ in range(3):
        b = m3.Manifold.cube([1.5, 1, 2], True).rotate(tuple(rng.uniform(-90, 90, 3))).translate([3.4, 0.3, 0.2])
        (va, fa), (vb, fb) = _solid_arrays(a), _solid_arrays(b)
        every = min(_triangles_apart(va[f].copy(), vb[g].copy(), 0.0) for f in fa for g in fb)
        assert surface_gap(va, fa, vb, fb, np.zeros(3), 5.0, 0.0) == every < 5.0


@pytest.mark.parametrize("kernel", [False, True])
def test_face_gaps_by_the_kernel_are_the_engines(monkeypatch, kernel):
    from volpuzzle import check as C

    monkeypatch.setattr(C, "_SHORTCUT_MIN_PIECES", 1 if kernel else 10 ** 9)
    meshes = {"p0": _slab(0, 10), "p1": _slab(10.12, 20), "p2": _slab(20.1, 30), "p3": _slab(30.2, 40)}
    gaps = C._face_gaps(meshes, 0.3)
    assert [g[:2] for g in gaps] == [("p0", "p1"), ("p1", "p2"), ("p2", "p3")]
    assert [g[3] for g in gaps] == pytest.approx([0.12, 0.1, 0.2], abs=1e-12)
    assert min(gaps, key=lambda g: g[3])[:2] == ("p1", "p2")
    # pieces that touch: 0, and the gaps after it are the closest vertices'
    touching = C._face_gaps({"p0": _slab(0, 10), "p1": _slab(10, 20), "p2": _slab(20.1, 30)}, 0.3)
    assert [g[3] for g in touching] == pytest.approx([0.0, 0.1], abs=1e-12) and touching[0][3] == 0.0


def test_surfaces_meet_at_every_shift_where_the_solids_overlap_and_nowhere_apart():
    # surfaces_meet over many shifts at once, against surface_gap one shift at a time and the engine's overlap
    import manifold3d as m3

    from volpuzzle._check_kernels import surface_gap, surfaces_meet

    a = (m3.Manifold.cube([6, 5, 4], True) - m3.Manifold.sphere(2.5, 24).translate([3, 2.5, 2])).rotate([11, 23, -7])
    b = m3.Manifold.cylinder(5, 1.5, 0.8, 20).translate([0, 0, -2.5]).rotate([-31, 5, 60]).translate([3.5, 0, 0])
    (va, fa), (vb, fb) = _solid_arrays(a), _solid_arrays(b)
    rng = np.random.default_rng(2)
    shifts = np.ascontiguousarray(rng.uniform(-3.0, 3.0, (120, 3)))
    meet = surfaces_meet(va, fa, vb, fb, shifts, 1e-6)
    seen = {True: 0, False: 0}
    for shift, met in zip(shifts, meet, strict=True):
        gap = surface_gap(va, fa, vb, fb, shift, 1.0, 1e-6)
        assert met == (gap == 0.0)
        if (a.translate(tuple(shift)) ^ b).volume() > 0.0:
            assert met
        seen[bool(met)] += 1
    assert min(seen.values()) > 20, seen
    assert not surfaces_meet(va, fa, vb, fb, np.zeros((0, 3)), 1e-6).any()
