"""Mesh mode clean-up: pieces of a cage cut by a mesh stay closed, fragments and tiny pieces are merged with the
volume kept, each by its largest contact."""

import manifold3d
import numpy as np
import pytest
import trimesh

from volpuzzle.errors import GeometryError
from volpuzzle.geometry import from_trimesh, to_trimesh
from volpuzzle.meshcut import intersect_pieces, merge_fragments

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


def test_a_fragment_that_touches_nobody_is_refused_with_its_cell(ball):
    far = box([40, 0, 0], [41, 1, 1])
    with pytest.raises(GeometryError, match="p1-0-0: a fragment of 1 mm.3 touches no other piece"):
        merge_fragments({"p0-0-0": ball, "p1-0-0": box([12, -5, -5], [20, 5, 5]) + far})
    # a small whole piece that touches nobody is no fragment: it stays a piece of its own (the joint stage says so)
    out, records = merge_fragments({"p0-0-0": ball, "p1-0-0": far})
    assert sorted(out) == ["p0-0-0", "p1-0-0"] and records == []


def test_a_part_meeting_its_neighbour_only_along_an_edge_is_no_contact():
    # A union across an edge contact is non-manifold: no slicer takes it, so an edge is no contact at all.
    big = M.cube([10.0, 10.0, 10.0])
    tiny = M.cube([0.5, 0.5, 10.0]).translate([10.0, 10.0, 0.0])
    with pytest.raises(GeometryError, match="p1-1-0: a fragment .* touches no other piece"):
        merge_fragments({"p0-0-0": big, "p1-1-0": big.translate([20.0, 0, 0]) + tiny})


def test_fragments_follow_their_largest_contact_also_through_a_chain():
    # Faces that touch share their corners, as compose's cells do. p2's fragment f touches p0 over 10 x 12 and p1
    # over 10 x 10; p3's fragment g touches only f. f goes to p0, its largest contact, and g follows f there.
    p0 = box([0, 0, 0], [10, 10, 12])
    p1 = box([10, 0, 12], [20, 10, 15])
    f = box([10, 0, 0], [20, 10, 12])
    g = box([20, 0, 0], [25, 10, 12])
    p2 = box([50, 0, 0], [80, 10, 12]) + f
    p3 = box([50, 20, 0], [80, 30, 12]) + g
    out, records = merge_fragments({"p0-0-0": p0, "p1-0-0": p1, "p2-0-0": p2, "p3-0-0": p3})
    assert sorted(out) == ["p0-0-0", "p1-0-0", "p2-0-0", "p3-0-0"]
    assert {(r["from"], r["to"], round(r["volume_mm3"])) for r in records} == {("p2-0-0", "p0-0-0", 1200),
                                                                               ("p3-0-0", "p0-0-0", 600)}
    assert out["p0-0-0"].volume() == pytest.approx(1200 + 1200 + 600)
    assert all(closed_one_body(p) for p in out.values())


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


# --- face clearance ---------------------------------------------------------------------------------------------------
def _cells_and_shrunk(cuts, c):
    """Box cells between x cuts, and the same cells with every inner face set back by c / 2 (as compose does)."""
    cells, shrunk = {}, {}
    for i in range(len(cuts) - 1):
        lo, hi = cuts[i], cuts[i + 1]
        pid = f"p{i}-0-0"
        cells[pid] = box([lo, -20, -20], [hi, 20, 20])
        shrunk[pid] = box([lo + (c / 2 if i > 0 else 0.0), -20, -20],
                          [hi - (c / 2 if i < len(cuts) - 2 else 0.0), 20, 20])
    return cells, shrunk


def test_face_clearance_sets_mesh_pieces_apart_and_the_volumes_add_up(ball):
    from volpuzzle.meshcut import set_back_faces

    c = 0.3
    cells, shrunk = _cells_and_shrunk([-12, 0.7, 12], c)
    pieces, merges = merge_fragments(intersect_pieces(cells, ball))
    out, taken = set_back_faces(pieces, cells, shrunk, merges, c)
    a, b = out["p0-0-0"], out["p1-0-0"]
    assert a.min_gap(b, 1.0) == pytest.approx(c, abs=1e-6)  # apart by the clearance, half on each side
    assert all(closed_one_body(p) for p in out.values())
    # what the clearance took is the contact (the ball's section at x = 0.7) times the clearance
    assert taken == pytest.approx(np.pi * (10.0 ** 2 - 0.7 ** 2) * c, rel=0.03)
    assert total(out) + taken == pytest.approx(ball.volume(), rel=1e-9)


def test_face_clearance_keeps_a_merged_fragment_joined_to_its_piece(torus):
    from volpuzzle.meshcut import set_back_faces

    c = 0.3
    cells, shrunk = _cells_and_shrunk([-20, -3, 3, 20], c)
    pieces, merges = merge_fragments(intersect_pieces(cells, torus))
    assert [r["reason"] for r in merges] == ["fragment"]
    out, taken = set_back_faces(pieces, cells, shrunk, merges, c)
    assert all(closed_one_body(p) for p in out.values())  # the fragment still holds to the piece that took it
    names = sorted(out)
    for i, x in enumerate(names):
        for y in names[i + 1:]:
            assert out[x].min_gap(out[y], 1.0) >= 0.9 * c, (x, y)
    assert 0 < taken and total(out) + taken == pytest.approx(torus.volume(), rel=1e-9)


def test_vertex_row_ranks_are_numpys_unique_inverse():
    from volpuzzle.meshcut import _row_ranks

    rng = np.random.default_rng(1)
    rows = rng.integers(-3, 3, size=(5000, 3))  # many repeats, negative values, ties in the first columns
    _, want = np.unique(rows, axis=0, return_inverse=True)
    assert np.array_equal(_row_ranks(rows), want.ravel())
    assert len(_row_ranks(np.zeros((0, 3), np.int64))) == 0
