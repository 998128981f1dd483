"""Mesh mode clean-up: pieces of a cage cut by a mesh stay closed, fragments and tiny pieces are merged with the
volume kept, and joints are moved off cavities or dropped."""

import manifold3d
import numpy as np
import pytest
import trimesh

from volpuzzle.errors import GeometryError
from volpuzzle.geometry import from_trimesh, to_trimesh
from volpuzzle.joint import Joint
from volpuzzle.meshcut import intersect_pieces, keep_joints_inside, merge_fragments

M = manifold3d.Manifold


def box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return M.cube(list(hi - lo)).translate(list(lo))


def total(pieces):
    return sum(p.volume() for p in pieces.values())


def closed_one_body(m):
    t = to_trimesh(m)
    return t.is_watertight and t.is_winding_consistent and t.volume > 0 and len(m.decompose()) == 1


@pytest.fixture(scope="module")
def ball():
    return from_trimesh(trimesh.creation.icosphere(3, radius=10), "ball")


@pytest.fixture(scope="module")
def torus():
    return from_trimesh(trimesh.creation.torus(10, 3, major_sections=48, minor_sections=16), "torus")


def test_pieces_of_a_ball_are_closed_and_sum_to_it(ball):
    cuts = [-12, 0.7, 12]
    bodies = {f"p{i}-{j}-{k}": box([cuts[i], cuts[j], cuts[k]], [cuts[i + 1], cuts[j + 1], cuts[k + 1]])
              for i in range(2) for j in range(2) for k in range(2)}
    bodies["p9-9-9"] = box([30, 30, 30], [40, 40, 40])  # a cell that misses the mesh
    pieces = intersect_pieces(bodies, ball)
    assert "p9-9-9" not in pieces and len(pieces) == 8
    assert all(closed_one_body(p) for p in pieces.values())
    assert total(pieces) == pytest.approx(ball.volume(), rel=1e-9)


def test_a_split_piece_gives_its_fragment_to_a_neighbour(torus):
    # the middle slab crosses the ring twice: two bodies
    bodies = {"p0-0-0": box([-20, -20, -5], [-3, 20, 5]), "p1-0-0": box([-3, -20, -5], [3, 20, 5]),
              "p2-0-0": box([3, -20, -5], [20, 20, 5])}
    pieces = intersect_pieces(bodies, torus)
    assert len(pieces["p1-0-0"].decompose()) == 2
    merged, records = merge_fragments(pieces)
    assert set(merged) == set(bodies)
    assert [r["reason"] for r in records] == ["fragment"] and records[0]["from"] == "p1-0-0"
    assert records[0]["to"] in ("p0-0-0", "p2-0-0")
    assert all(closed_one_body(p) for p in merged.values())
    assert total(merged) == pytest.approx(torus.volume(), rel=1e-9)


def test_a_tiny_piece_is_merged_whole(ball):
    bodies = {"p0-0-0": box([-12, -12, -12], [9.5, 12, 12]), "p1-0-0": box([9.5, -12, -12], [12, 12, 12])}
    pieces = intersect_pieces(bodies, ball)
    assert pieces["p1-0-0"].volume() < 0.05 * total(pieces) / 2
    merged, records = merge_fragments(pieces)
    assert list(merged) == ["p0-0-0"]
    assert records == [{"from": "p1-0-0", "to": "p0-0-0", "volume_mm3": pytest.approx(pieces["p1-0-0"].volume()),
                        "reason": "small piece"}]
    assert total(merged) == pytest.approx(ball.volume(), rel=1e-9)
    assert closed_one_body(merged["p0-0-0"])


def test_a_part_that_touches_nobody_is_refused_with_its_cell(ball):
    pieces = {"p0-0-0": ball, "p1-0-0": box([40, 0, 0], [41, 1, 1])}
    with pytest.raises(GeometryError, match="p1-0-0: a small piece .* touches no other piece"):
        merge_fragments(pieces)


# --- joints ---------------------------------------------------------------------------------------------------------
def joint(center, direction=(1.0, 0.0, 0.0), radius=2.0, length=5.0):
    c = np.asarray(center, float)
    return Joint(pin_cell=(0, 0, 0), hole_cell=(1, 0, 0), axis=0, across_seam=False, center=c,
                 direction=np.asarray(direction, float), radius=radius, length=length, clearance=0.15,
                 axial_clearance=0.3, shape="cylinder", style="pin", space="physical", uvw_pin=np.zeros(3),
                 uvw_hole=np.zeros(3), base_depth=1.0)


@pytest.fixture(scope="module")
def block_with_pocket():
    """A 40 mm block with a pocket (radius 4) drilled from the top down to just below the joint at the origin."""
    block = box([-20, -20, -20], [20, 20, 20])
    pocket = M.cylinder(30, 4.0, -1.0, 32).translate([0, 0, -3])
    return to_trimesh(block - pocket)


def test_a_joint_in_solid_material_stays(block_with_pocket):
    j = joint([0, 10, -10])
    kept, records = keep_joints_inside([j], block_with_pocket)
    assert kept == [j] and records == []


def test_a_joint_in_a_cavity_is_moved_out_with_a_wall(block_with_pocket):
    j = joint([0, 0, 0])
    kept, records = keep_joints_inside([j], block_with_pocket, wall=1.5)
    assert len(kept) == 1 and records[0]["action"] == "moved"
    moved = kept[0]
    shift = np.asarray(moved.center) - j.center
    assert abs(shift[0]) < 1e-12  # along the face (the plane x = 0), not across it
    assert records[0]["distance"] == pytest.approx(np.linalg.norm(shift))
    # clear of the pocket by the wall: either beside it or below its floor
    side = np.hypot(moved.center[1], moved.center[2] if moved.center[2] > -3 else 0.0)
    below = moved.center[2] < -3 - (2.0 + 0.15 + 1.5)
    assert below or side >= 4.0 + 2.15 + 1.5 - 1e-6
    assert moved.pin_cell == j.pin_cell and moved.radius == j.radius


def test_a_joint_with_no_room_is_dropped():
    slab = to_trimesh(box([-20, -20, -2], [20, 20, 2]))  # 4 mm thick: no 2 mm pin fits with a 1.5 mm wall
    kept, records = keep_joints_inside([joint([0, 0, 0])], slab, wall=1.5)
    assert kept == [] and records == [{"pin_piece": "p0-0-0", "hole_piece": "p1-0-0", "action": "dropped",
                                       "distance": 0.0}]


def test_a_part_meeting_its_neighbour_only_along_an_edge_is_not_welded(monkeypatch):
    # A union across an edge contact is non-manifold: no slicer takes it, so the merge must not make it. The contact
    # score is forced, as on a sphere cage where parts meet along lines that the axis shifts do pick up. A small
    # whole piece then stays a piece of its own; a fragment (a loose body of another piece) is refused.
    import volpuzzle.meshcut as meshcut

    monkeypatch.setattr(meshcut, "_touch", lambda frag, other, grow: 1.0)
    big = manifold3d.Manifold.cube([10.0, 10.0, 10.0])
    tiny = manifold3d.Manifold.cube([0.5, 0.5, 10.0]).translate([10.0, 10.0, 0.0])
    out, records = merge_fragments({"p0-0-0": big, "p1-1-0": tiny})
    assert sorted(out) == ["p0-0-0", "p1-1-0"]
    assert records[0]["to"] is None and "kept" in records[0]["reason"]
    with pytest.raises(GeometryError, match="only along an edge or at a point"):
        merge_fragments({"p0-0-0": big, "p1-1-0": big.translate([20.0, 0, 0]) + tiny})


def test_small_pieces_merge_one_at_a_time_so_neighbours_of_small_pieces_still_count():
    # Three small slabs in a row beside a big block (widths exact in binary, so faces coincide exactly); the last
    # slab touches only the middle one, which was small itself.
    block = manifold3d.Manifold.cube([10.0, 10.0, 10.0])
    slabs = {f"p{i}-0-0": manifold3d.Manifold.cube([0.25, 10.0, 10.0]).translate([10.0 + 0.25 * (i - 1), 0, 0])
             for i in (1, 2, 3)}
    out, records = merge_fragments({"p0-0-0": block, **slabs}, min_fraction=0.5)
    assert list(out) == ["p0-0-0"]
    assert abs(out["p0-0-0"].volume() - 1075.0) < 1e-6
    assert len(out["p0-0-0"].decompose()) == 1
    assert [r["reason"] for r in records] == ["small piece"] * 3
