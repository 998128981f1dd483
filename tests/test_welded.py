"""Puzzles that used to be welded: a half pipe bent along its length slides straight out of its trough (not along its
area-weighted mean normal, which leans toward the outside of the bend), and a coil that no straight slide can take
apart is refused with the grid at which no piece turns more than a half turn, which builds."""

import numpy as np
import pytest
from conftest import REPO
from helpers_build import write_spec

from volpuzzle import assembly as A
from volpuzzle.errors import GeometryError
from volpuzzle.io import load_model
from volpuzzle.mapping import Map
from volpuzzle.pipeline import build
from volpuzzle.tile import tile

DATA = REPO / "tests" / "data" / "volumes"


def _half_torus_normals(bend=np.pi / 2, big=3.0, n=24):
    """Area-weighted normals (n * n, 3) of the inner face of a bent half pipe, halved through its bend's plane: a
    torus of major radius big and minor radius 1, angle theta over [0, pi] (y >= 0), bend angle over [0, bend]."""
    th, ph = np.meshgrid((np.arange(n) + 0.5) / n * np.pi, (np.arange(n) + 0.5) / n * bend, indexing="ij")
    radial = np.stack([np.cos(th) * np.cos(ph), np.sin(th), np.cos(th) * np.sin(ph)], axis=-1)
    area = (big + np.cos(th))[..., None]  # more surface on the outside of the bend
    return (radial * area).reshape(-1, 3)


def test_a_bent_half_pipe_leaves_straight_out_of_its_trough():
    ns = _half_torus_normals()
    unit = ns / np.linalg.norm(ns, axis=1)[:, None]
    mean = ns.sum(axis=0) / np.linalg.norm(ns.sum(axis=0))
    assert (unit @ mean).min() < 0  # the mean leans toward the bend's outside and drags a rim through the other half
    d = A.leave_direction(ns)
    assert abs(np.linalg.norm(d) - 1) < 1e-9 and (unit @ d).min() > 0
    assert d[1] > 0.999  # straight out of the trough, along its plane of symmetry


def test_a_split_whose_surface_stays_ahead_keeps_its_mean_normal():
    ns = _half_torus_normals()
    ns = ns[(ns / np.linalg.norm(ns, axis=1)[:, None])[:, 1] > 0.5]  # a shallow dish
    mean = ns.sum(axis=0) / np.linalg.norm(ns.sum(axis=0))
    assert np.array_equal(A.leave_direction(ns), mean)
    assert A.leave_direction(np.zeros((4, 3))) is None


def _spring(grid):
    vol = load_model(DATA / "gismo_spring.xml")
    return tile(vol, grid), Map(vol, None, -1)


def test_a_coil_is_cut_until_no_piece_turns_more_than_a_half_turn():
    # the G+Smo spring: three turns along u; 2 x 2 x 2 pieces of it span a turn and a half each
    assert A.bend_grid(*_spring((2, 2, 2))) == (6, 2, 2)
    assert A.bend_grid(*_spring((6, 2, 2))) is None
    assert A.bend_grid(*_spring((8, 1, 2))) is None


def test_a_welded_coil_names_the_grid_that_builds(monkeypatch):
    t, fmap = _spring((2, 2, 2))
    stuck = [A.piece_id(c) for c in sorted(t.cells)]
    monkeypatch.setattr(A, "verify_disassembly", lambda *_a, **_k: {
        "assembly_order": stuck, "steps": [], "welded": True, "stuck": stuck, "booleans": 0, "seconds": 0})
    with pytest.raises(GeometryError) as e:
        A.replay_assembly(A.plan_assembly(t), [], [], tiling=t, fmap=fmap)
    msg = str(e.value)
    assert msg.startswith("assembly: the puzzle is welded: p0-0-0, p0-0-1, p0-1-0, p0-1-1, p1-0-0, p1-0-1 and 2 more")
    assert "try grid [6, 2, 2], whose cells turn at most 180 deg along u" in msg and "\n" not in msg
    assert "randomize" not in msg  # not randomized: no seed or amplitude to change


def _gismo_spec(tmp_path, name, grid):
    return write_spec(tmp_path, {"name": name, "model": {"nurbs": str(DATA / f"gismo_{name}.xml"), "size": 150},
                                 "grid": grid, "output": {"tolerance": 0.3, "labels": False,
                                                          "directory": str(tmp_path / "out" / name)}})


def _assert_built_and_held(report):
    assert report["checks"]["passed"] and not report["assembly"]["welded"] and report["assembly"]["stuck"] == []
    contacts = report["contacts"]
    room = [c for c in contacts if c["room"]]
    assert room and sum(c["pinned"] for c in room) >= 0.9 * len(room)
    with_joint = {p for j in report["joints"] for p in (j["pin_piece"], j["hole_piece"])}
    assert with_joint == {p["id"] for p in report["pieces"]}


@pytest.mark.slow
def test_the_bent_pipe_2x2x2_builds_and_comes_apart(tmp_path):
    # was welded: the elbow's inner half pipe was pushed 19.5 deg toward the bend's outside, through the outer rims
    report = build(_gismo_spec(tmp_path, "bent_pipe", [2, 2, 2]), progress=None)
    _assert_built_and_held(report)
    assert len(report["pieces"]) == 8


@pytest.mark.slow
def test_the_spring_at_the_grid_its_refusal_names_builds(tmp_path):
    report = build(_gismo_spec(tmp_path, "spring", [6, 2, 2]), progress=None)
    _assert_built_and_held(report)
    assert len(report["pieces"]) == 24


def test_cells_too_shallow_for_the_smallest_pin_name_a_shorter_pin_and_a_coarser_grid_that_fits():
    from test_joint import _box, _map, _spec, _tiling

    from volpuzzle import joint as J
    from volpuzzle.errors import SpecError

    vol = _box(24.0, 30.0, 30.0)  # 8 cells 3 mm deep: a 3 mm pin's hole and its wall need 4.1 mm
    t, spec = _tiling(vol, (8, 1, 1)), _spec()
    with pytest.raises(SpecError) as e:
        J.place_planned_joints(t, _map(vol), spec)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("joints: piece p0-0-0 gets no joint")
    assert "holds a pin of radius at most 0.9 mm and 1 mm long" in msg
    assert "expected joints.min_radius at most 0.9 and joints.min_length at most 1 there" in msg
    assert "grid [4, 1, 1] or coarser (cells with room for a pin of 1 mm by 3 mm)" in msg
    # both are true: the shorter pin fits at 8 cells, the smallest pin at the grid named
    shorter = _spec(min_radius=0.9, min_length=1.0)
    layout, _ = J.place_planned_joints(t, _map(vol), shorter)
    assert len(layout.joints) == len(t.faces)
    coarse = _tiling(vol, (4, 1, 1))
    layout, _ = J.place_planned_joints(coarse, _map(vol), spec)
    assert len(layout.joints) == len(coarse.faces) and all(j.length >= 3.0 for j in layout.joints)


@pytest.mark.slow
def test_every_split_of_the_256_piece_twisted_torus_leaves_with_its_whole_surface_ahead(tmp_path):
    # 4 x 4 x 16 at seed 7 was welded (p3-2-4, p3-2-5, p3-3-4, p3-3-5 stuck): a split's mean normal faced away from
    # part of its surface (least cosine -0.14), and its pins drove the block through its neighbour
    from helpers_build import example_spec

    from volpuzzle.pipeline import prepare
    from volpuzzle.spec import load_spec

    s = prepare(load_spec(example_spec("twisted-torus", tmp_path, tolerance=0.05, grid=[4, 4, 16])))
    dirs = A.split_directions(s.tiling, s.fmap, s.plan)
    assert len(dirs) == 255 and min(m for _, m in dirs) > 0
    for (d, _), step in zip(dirs, s.plan.steps, strict=True):
        mv = set(step.moving)
        for j in A._across(s.joints, step.moving, step.fixed):
            assert np.allclose(j.direction, (1.0 if tuple(j.hole_cell) in mv else -1.0) * d, atol=1e-9)
