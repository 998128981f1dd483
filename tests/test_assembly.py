"""assembly: the plan lists every piece once, its joints connect all pieces with at most three pins and three holes per
piece, every step obeys the joint rule (also round a periodic ring), and the real meshes come apart along it; a puzzle
that cannot be taken apart is reported welded with its stuck pieces named."""

import dataclasses
import itertools
from collections import Counter
from functools import cache

import numpy as np
import pytest
from shapes import ring

from volpuzzle import assembly as A
from volpuzzle import compose as C
from volpuzzle import joint as J
from volpuzzle.mapping import Map
from volpuzzle.spec import JointSpec
from volpuzzle.spline import Volume
from volpuzzle.spline.seams import find_seams
from volpuzzle.tile import tile

# ---------------------------------------------------------------------------------------------------------------------
# small models


def _clamped(n, p):
    inner = np.linspace(0, 1, n - p + 1)[1:-1]
    return np.concatenate([np.zeros(p + 1), inner, np.ones(p + 1)])


def _box(sx=40.0, sy=30.0, sz=20.0):
    cp = np.zeros((2, 2, 2, 3))
    for i, j, k in np.ndindex(2, 2, 2):
        cp[i, j, k] = [i * sx, j * sy, k * sz]
    return Volume((1, 1, 1), ([0, 0, 1, 1],) * 3, cp)


def _bent():
    """A thick quarter ring (left-handed): u along a 90-degree arc, v radial 20..50 mm, w height 30 mm."""
    k = 0.5523
    arc = np.array([[1, 0], [1, k], [k, 1], [0, 1]], float)
    cp = np.zeros((4, 2, 2, 3))
    for i, j, m in np.ndindex(4, 2, 2):
        cp[i, j, m] = [(20.0, 50.0)[j] * arc[i, 0], (20.0, 50.0)[j] * arc[i, 1], 30.0 * m]
    return Volume((3, 1, 1), (_clamped(4, 3), [0, 0, 1, 1], [0, 0, 1, 1]), cp)


def _warp(seed=3, amplitude=0.06):
    """R: the identity (cubic, 5 control points per axis) with its interior control points moved: bumpy cut faces."""
    n = 5
    kn = _clamped(n, 3)
    grev = np.array([kn[i + 1:i + 4].mean() for i in range(n)])
    g = np.stack(np.meshgrid(grev, grev, grev, indexing="ij"), axis=-1)
    d = np.random.default_rng(seed).uniform(-amplitude, amplitude, g.shape)
    d[[0, -1], :, :, 0] = 0
    d[:, [0, -1], :, 1] = 0
    d[:, :, [0, -1], 2] = 0
    return Volume((3, 3, 3), (kn, kn, kn), g + d)




def _map(vol, warp=None):
    _, jac = vol.evaluate_with_derivatives(np.array([[0.5, 0.5, 0.5]]))
    return Map(vol, warp, int(np.sign(np.linalg.det(jac[0]))))


SPEC = JointSpec()


def _ring_tiling(twist, grid=(2, 2, 8)):
    vol = ring(twist)
    return tile(vol, grid, periodic=(2,), seams=find_seams(vol)), _map(vol)


# ---------------------------------------------------------------------------------------------------------------------
# the plan in parameter space


def _assert_sound(tiling, plan):
    assert sorted(plan.assembly_order) == sorted(tiling.cells)
    assert len(plan.assembly_order) == len(set(plan.assembly_order))
    assert A.step_problems(tiling, plan) == []
    if len(tiling.cells) > 1:
        assert A.joint_graph_connected(tiling, plan)
        assert len(plan.steps) == len(tiling.cells) - 1
    pins, holes = Counter(), Counter()
    for n, side in plan.faces_with_joints:
        f = tiling.faces[n]
        pin, hole = (f.lower, f.upper) if side == "lower" else (f.upper, f.lower)
        pins[tuple(pin)] += 1
        holes[tuple(hole)] += 1
    assert max(pins.values(), default=0) <= 3 and max(holes.values(), default=0) <= 3
    # every piece is pinned to the rest
    jointed = {c for n, _ in plan.faces_with_joints for c in (tiling.faces[n].lower, tiling.faces[n].upper)}
    if len(tiling.cells) > 1:
        assert jointed == set(tiling.cells)


@pytest.mark.parametrize("grid", list(itertools.product((1, 2, 3), repeat=3)))
def test_plan_is_sound_on_every_small_grid(grid):
    _assert_sound(tile(_box(), grid), A.plan_assembly(tile(_box(), grid)))


def test_plan_with_the_map_pins_every_face_of_a_flat_split():
    t = tile(_box(), (2, 2, 2))
    plan = A.plan_assembly(t, _map(_box()))
    _assert_sound(t, plan)
    # a box's splits are flat, so every face crossing a split carries a pin: 4 + 2 + 2 + 1 * 4
    assert len(plan.faces_with_joints) == 4 + 2 * 2 + 4 * 1
    assert len(A.plan_assembly(t).faces_with_joints) == len(t.cells) - 1  # without F: one joint per split


@pytest.mark.parametrize("twist", [0.0, np.pi / 2], ids=["identity-seam", "swap-seam"])
def test_periodic_ring_is_cut_in_halves_first(twist):
    t, fmap = _ring_tiling(twist)
    if twist:
        assert t.seams[2].swap
    for plan in (A.plan_assembly(t), A.plan_assembly(t, fmap)):
        _assert_sound(t, plan)
        first = plan.steps[0]
        assert first.ring_cut and first.axis == 2 and len(first.moving) == len(first.fixed) == 16
        seam_faces = {n for n, f in enumerate(t.faces) if f.seam is not None}
        # the joints cross the seam, as on every periodic axis
        assert seam_faces & {n for n, _ in plan.faces_with_joints}


def test_odd_periodic_ring_still_plans():
    t, _ = _ring_tiling(0.0, grid=(1, 2, 5))
    _assert_sound(t, A.plan_assembly(t))


def test_step_problems_name_a_sliding_step_and_a_loose_one():
    t = tile(_box(), (2, 1, 1))
    sliding = A.AssemblyPlan(((0, "lower"),), (A.Step(((1, 0, 0),), ((0, 0, 0),), 2, +1, (0,)),),
                             ((0, 0, 0), (1, 0, 0)))
    assert any("slides along face p0-0-0|p1-0-0" in p for p in A.step_problems(t, sliding))
    loose = A.AssemblyPlan((), (A.Step(((1, 0, 0),), ((0, 0, 0),), 0, +1, ()),), ((0, 0, 0), (1, 0, 0)))
    assert any("no joint holds" in p for p in A.step_problems(t, loose))
    pushing = A.AssemblyPlan(((0, "lower"),), (A.Step(((0, 0, 0),), ((1, 0, 0),), 0, +1, (0,)),),
                             ((1, 0, 0), (0, 0, 0)))
    assert any("push into p1-0-0" in p for p in A.step_problems(t, pushing))


@pytest.mark.slow
def test_with_joints_lists_the_placed_faces():
    t = tile(_box(), (2, 2, 2))
    fmap = _map(_box())
    plan = A.plan_assembly(t)
    joints = J.plan_joints(t, fmap, SPEC, plan)
    assert len(joints) == len(t.faces)  # a box has room for a pin on every face
    placed = A.with_joints(plan, t, joints[:5])
    faces = A.joint_faces(t, placed)
    assert {(f.axis, f.lower, f.upper) for f, _ in faces} == {(j.axis, j.pin_cell, j.hole_cell) for j in joints[:5]}
    assert sorted(n for s in placed.steps for n in s.joints) == sorted(n for n, _ in placed.faces_with_joints)


# ---------------------------------------------------------------------------------------------------------------------
# real meshes


@cache
def _built(name, all_faces=False, tilt_deg=0.0, face_clearance=0.0):
    if name == "bent":
        vol, grid = _bent(), (2, 2, 2)
        fmap = _map(vol, _warp())
        t = tile(vol, grid)
    elif name == "box":
        vol = _box()
        fmap, t = _map(vol), tile(vol, (2, 2, 2))
    else:
        t, fmap = _ring_tiling(np.pi / 2, grid=(2, 2, 4))
    plan = A.plan_assembly(t, fmap)
    # all_faces: every face pinned along its own normal, ignoring the plan's sliding directions
    joints = J.plan_joints(t, fmap, SPEC, None if all_faces else plan)
    plan = A.with_joints(plan, t, joints)
    if tilt_deg:
        joints = [_tilted(j, k, tilt_deg) for k, j in enumerate(joints)]
    pieces = C.compose(t, fmap, joints, 1.0, face_clearance=face_clearance)
    return t, plan, joints, {p.id: p.mesh for p in pieces}


def _tilted(j, k, deg):
    """The joint with its pin turned by deg towards one of four sides (by k), so no two neighbours' pins agree."""
    d = np.asarray(j.direction)
    e1 = np.cross(np.eye(3)[int(np.argmin(np.abs(d)))], d)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    side = np.cos(k * np.pi / 2) * e1 + np.sin(k * np.pi / 2) * e2
    new = np.cos(np.radians(deg)) * d + np.sin(np.radians(deg)) * side
    new.setflags(write=False)
    return dataclasses.replace(j, direction=new)


def _assert_comes_apart(res, ids):
    assert res["welded"] is False and res["stuck"] == []
    assert sorted(res["assembly_order"]) == sorted(ids) and len(set(res["assembly_order"])) == len(ids)
    joins = [s for s in res["steps"] if s["kind"] == "join"]
    assert len(joins) == len(ids) - 1
    for s in joins:
        assert abs(np.linalg.norm(s["direction"]) - 1.0) < 1e-9
        assert s["joints"] and set(s["into"]) <= set(s["onto"])
    # a block is placed before anything joins onto it
    seen = set()
    for s in res["steps"]:
        if s["kind"] == "join":
            assert set(s["onto"]) <= seen
        seen |= set(s["pieces"])


@pytest.mark.parametrize("name", [pytest.param("bent", marks=pytest.mark.slow), "ring"])
def test_real_pieces_come_apart_along_the_plan(name):
    t, plan, joints, pieces = _built(name)
    res = A.verify_disassembly(pieces, joints, plan)
    _assert_comes_apart(res, list(pieces))
    lines = A.steps_in_words(res)
    assert lines[0] == f"1. Place {res['assembly_order'][0]} on the table."
    assert len(lines) == len(res["steps"]) and all("Slide" in x for x in lines if "place" not in x.lower())


def test_every_face_jointed_in_a_bent_block_still_comes_apart_in_blocks():
    _, plan, joints, pieces = _built("bent", all_faces=True)
    assert len(joints) == 12
    _assert_comes_apart(A.verify_disassembly(pieces, joints, plan), list(pieces))


def test_every_face_jointed_is_welded_one_piece_at_a_time():
    _, plan, joints, pieces = _built("box", all_faces=True)
    res = A.verify_disassembly(pieces, joints, plan, groups=False)
    assert res["welded"] is True and res["stuck"] == sorted(pieces)
    assert sorted(res["assembly_order"]) == sorted(pieces)
    assert A.steps_in_words(res)[-1].startswith("Warning: the puzzle is welded: p0-0-0, ")


def test_crossed_pins_weld_the_puzzle_and_name_the_pieces():
    _, plan, joints, pieces = _built("box", all_faces=True, tilt_deg=25.0)
    res = A.verify_disassembly(pieces, joints, plan)
    assert res["welded"] is True and set(res["stuck"]) == set(pieces)


@pytest.mark.parametrize("kernel", [False, True])
def test_a_sweep_into_a_neighbour_is_caught(kernel):
    _, plan, joints, pieces = _built("box")
    scene = A._Scene({k: pieces[k] for k in ("p0-0-0", "p1-0-0")}, kernel=kernel)
    ok, hit = scene.sweep_clear(["p1-0-0"], ["p0-0-0"], np.array([-1.0, 0.0, 0.0]), 1.0, 1e-4)
    assert not ok and hit[:2] == ("p1-0-0", "p0-0-0")
    ok, _ = scene.sweep_clear(["p1-0-0"], ["p0-0-0"], np.array([1.0, 0.0, 0.0]), 1.0, 1e-4)
    assert ok


def test_pins_of_a_split_are_parallel_lean_at_most_the_limit_and_still_come_apart():
    t, plan, joints, pieces = _built("bent")
    fmap = _map(_bent(), _warp())
    dirs = A.split_directions(t, fmap, plan)
    assert len(dirs) == len(plan.steps) and all(m > 0 for _, m in dirs)
    assert len(joints) == len(t.faces)  # every contact pinned, not one per split
    for (d, _), step in zip(dirs, plan.steps, strict=True):
        mv = set(step.moving)
        for j in A._across(joints, step.moving, step.fixed):
            way = 1.0 if tuple(j.hole_cell) in mv else -1.0
            assert np.allclose(j.direction, way * d, atol=1e-9)
            assert 0.0 <= j.tilt_deg <= J.MAX_TILT_DEG + 1e-9
    _assert_comes_apart(A.verify_disassembly(pieces, joints, plan), list(pieces))


def test_parts_of_a_piece_cover_it_along_every_direction():
    _, _, _, pieces = _built("bent")
    for pid, mesh in pieces.items():
        ext = A._chunk_extents(mesh.vertices, mesh.faces)
        pts, _ = __import__("trimesh").sample.sample_surface(mesh, 2000, seed=1)
        proj = pts @ A._DIRS.T
        # every surface point (and so every point of the solid, see _chunk_extents) lies in some part's extents
        inside = ((proj[:, None, :] >= ext[None, :, 0, :] - 1e-9) & (proj[:, None, :] <= ext[None, :, 1, :] + 1e-9))
        assert inside.all(axis=2).any(axis=1).all(), pid
        # together the parts span exactly the piece, each a good deal less
        vproj = np.asarray(mesh.vertices) @ A._DIRS.T
        assert np.allclose(ext[:, 0].min(axis=0), vproj.min(axis=0)) and np.allclose(ext[:, 1].max(axis=0),
                                                                                      vproj.max(axis=0))
        assert len(ext) > 1 and np.all(((ext[:, 1] - ext[:, 0]) < 0.8 * np.ptp(vproj, axis=0)).any(axis=1))


def _meeting_intervals(em, ef, s):
    """Per pair of parts, the open interval of offsets (lo, hi) over which they overlap in projection along every
    direction: parts_meet written as array code over every pair and direction, with no early exits."""
    a = ef[None, :, 0, :] - em[:, None, 1, :]
    b = ef[None, :, 1, :] - em[:, None, 0, :]
    along = np.abs(s) > 1e-12
    safe = np.where(along, s, 1.0)
    always = (a < 0) & (b > 0)
    t_lo = np.where(along, np.minimum(a / safe, b / safe), np.where(always, -np.inf, np.inf)).max(axis=2).ravel()
    t_hi = np.where(along, np.maximum(a / safe, b / safe), np.where(always, np.inf, -np.inf)).min(axis=2).ravel()
    return t_lo, t_hi


def _meets_by_arrays(em, ef, s, ts, near):
    t_lo, t_hi = _meeting_intervals(em, ef, s)
    return near & ((t_lo[None, :] < ts[:, None]) & (ts[:, None] < t_hi[None, :])).any(axis=1)


def test_the_compiled_meeting_test_answers_as_the_array_code():
    """Bit for bit, on parts that meet, miss and graze, along travels with directions exactly across them (s = 0)."""
    from volpuzzle._assembly_kernels import parts_meet

    rng = np.random.default_rng(5)
    met = missed = 0
    for case in range(300):
        k = int(rng.integers(1, 12))
        em = np.sort(rng.normal(0.0, 3.0, (int(rng.integers(1, 5)), 2, k)), axis=1)
        ef = np.sort(rng.normal(rng.normal(0.0, 4.0), 3.0, (int(rng.integers(1, 5)), 2, k)), axis=1)
        s = rng.normal(size=k)
        s[rng.random(k) < 0.3] = 0.0  # directions across the travel
        if case % 4 == 0:  # parts touching exactly along a direction across the travel
            s[0] = 0.0
            ef[0, 0, 0] = em[0, 1, 0]
        ts = rng.uniform(-15.0, 15.0, int(rng.integers(1, 30)))
        if case % 2 == 0:  # offsets exactly at the ends of the pairs' intervals: open intervals hold neither
            ends = np.concatenate(_meeting_intervals(em, ef, s))
            ends = ends[np.isfinite(ends)]
            ts = np.concatenate([ts, rng.choice(ends, min(len(ends), 6))]) if len(ends) else ts
        ts = np.sort(ts)
        near = rng.random(len(ts)) < 0.8
        got = parts_meet(em, ef, s, ts, near)
        want = _meets_by_arrays(em, ef, s, ts, near)
        assert np.array_equal(got, want), case
        met += int(got.sum())
        missed += int((near & ~got).sum())
    assert met > 100 and missed > 100  # both answers were asked for often


def test_the_sweep_skips_only_samples_that_cannot_collide():
    """Every sample the broad phase rules out is measured anyway: none overlaps beyond the limit, also along
    directions that drive the blocks into each other, and the sweep reports the earliest collision."""
    _, plan, joints, pieces = _built("bent")
    scene = A._Scene(pieces)
    skipped = collided = 0
    for step in plan.steps[:3]:
        moving, fixed = [A.piece_id(c) for c in step.moving], [A.piece_id(c) for c in step.fixed]
        d0, _ = A._direction(A._across(joints, step.moving, step.fixed), step.moving, step.fixed)
        side = np.cross(d0, [0.3, 0.5, 0.8])
        for d in (d0, -d0, side / np.linalg.norm(side)):
            ts = scene.samples(moving, fixed, d, 1.0)
            first = None
            for k, t in enumerate(ts):
                for pm in moving:
                    for pf in fixed:
                        lim = 1e-4 * min(scene.vol[pm], scene.vol[pf])
                        if scene._may_meet(pm, pf, ts[k:k + 1], d, lim)[0]:
                            continue
                        skipped += 1
                        assert A._overlap(scene.man[pm].translate(tuple(t * d)), scene.man[pf]) <= lim
                    if first is None:
                        hits = [pf for pf in fixed
                                if A._overlap(scene.man[pm].translate(tuple(t * d)), scene.man[pf])
                                > 1e-4 * min(scene.vol[pm], scene.vol[pf])]
                        if hits:
                            first = t
            ok, hit = scene.sweep_clear(moving, fixed, d, 1.0, 1e-4)
            assert ok == (first is None)
            if not ok:
                collided += 1
                assert hit[2] == pytest.approx(first)
    assert skipped > 50 and collided >= 3


@pytest.mark.parametrize("kernel", [False, True])
def test_a_collision_halfway_along_the_sweep_is_caught(kernel):
    """Two boxes with a gap: the moving one is clear for 5 mm, then runs into the fixed one; pruning must not hide
    the hit, and the first colliding sample is the one reported."""
    import trimesh

    a = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    b = trimesh.creation.box(extents=(10.0, 10.0, 10.0)).apply_translation([15.0, 3.0, 0.0])
    scene = A._Scene({"p0-0-0": a, "p1-0-0": b}, kernel=kernel)
    ok, hit = scene.sweep_clear(["p0-0-0"], ["p1-0-0"], np.array([1.0, 0.0, 0.0]), 1.0, 1e-4)
    assert not ok and hit[:2] == ("p0-0-0", "p1-0-0") and hit[2] == pytest.approx(5.05)
    ok, _ = scene.sweep_clear(["p0-0-0"], ["p1-0-0"], np.array([0.0, 0.0, 1.0]), 1.0, 1e-4)
    assert ok


def test_pairs_the_face_gaps_prove_apart_are_not_measured_over_their_first_gap(monkeypatch):
    from volpuzzle.check import neighbour_gaps, pairs_apart

    monkeypatch.setattr(A, "_use_kernel", lambda _pieces: False)  # the Booleans counted are every sample's

    _, plan, joints, pieces = _built("ring", face_clearance=0.3)
    apart = pairs_apart(neighbour_gaps(pieces, 0.3), pieces)
    assert len(apart) >= 16 and all(g > 0.1 for g in apart.values())  # a pin stands 0.15 from its hole
    plain = A.verify_disassembly(pieces, joints, plan)
    quick = A.verify_disassembly(pieces, joints, plan, apart=apart)
    _assert_comes_apart(quick, list(pieces))
    for key in ("assembly_order", "steps", "welded", "stuck"):
        assert quick[key] == plain[key], key
    # the first sample (0.05 mm of travel) of every such pair is spared
    assert quick["booleans"] < plain["booleans"]
    # a sweep into a neighbour is still caught once the travel exceeds the gap
    scene = A._Scene({k: pieces[k] for k in ("p0-0-0", "p1-0-0")}, apart)
    into = np.asarray(pieces["p0-0-0"].centroid - pieces["p1-0-0"].centroid)
    ok, hit = scene.sweep_clear(["p1-0-0"], ["p0-0-0"], into / np.linalg.norm(into), 1.0, 1e-4)
    assert not ok and hit[2] >= apart[frozenset(("p0-0-0", "p1-0-0"))]


def test_a_worker_process_takes_blocks_apart_to_the_same_steps(monkeypatch):
    # the threshold lowered so that the 16-piece ring sends its moving halves to the (started) worker
    import time

    from volpuzzle.check import neighbour_gaps, pairs_apart
    from volpuzzle.workers import Workers

    # with the face gaps' proofs, which travel with each block to the worker
    _, plan, joints, pieces = _built("ring", face_clearance=0.3)
    apart = pairs_apart(neighbour_gaps(pieces, 0.3), pieces)
    monkeypatch.setattr(A, "_use_kernel", lambda _pieces: True)  # and the worker spares Booleans as this process
    here = A.verify_disassembly(pieces, joints, plan, apart=apart)
    monkeypatch.setattr(A, "_REMOTE_MIN_PIECES", 2)
    with Workers(2) as workers:
        deadline = time.monotonic() + 120
        while not workers.started and time.monotonic() < deadline:
            time.sleep(0.05)
        pooled = A.verify_disassembly(pieces, joints, plan, workers=workers, apart=apart)
    assert here["blocks_in_workers"] == 0 and pooled["blocks_in_workers"] >= 1
    for key in ("assembly_order", "steps", "welded", "stuck", "booleans"):
        assert pooled[key] == here[key], key
    _assert_comes_apart(pooled, list(pieces))


def test_samples_whose_surfaces_do_not_meet_need_no_boolean(monkeypatch):
    # surfaces_meet proves most samples apart (a pin sliding out of its hole 0.15 mm from its wall): the same steps
    _, plan, joints, pieces = _built("ring", face_clearance=0.3)
    monkeypatch.setattr(A, "_use_kernel", lambda _pieces: False)
    plain = A.verify_disassembly(pieces, joints, plan)
    monkeypatch.setattr(A, "_use_kernel", lambda _pieces: True)
    quick = A.verify_disassembly(pieces, joints, plan)
    for key in ("assembly_order", "steps", "welded", "stuck"):
        assert quick[key] == plain[key], key
    assert plain["booleans"] > 20 and quick["booleans"] < plain["booleans"] / 4
    # without a face clearance too (the cut faces touch before the first sample, 0.05 mm on)
    _, plan, joints, pieces = _built("ring")
    quick = A.verify_disassembly(pieces, joints, plan)
    monkeypatch.setattr(A, "_use_kernel", lambda _pieces: False)
    plain = A.verify_disassembly(pieces, joints, plan)
    assert quick["steps"] == plain["steps"] and quick["booleans"] < plain["booleans"]


def test_a_piece_inside_the_others_box_is_left_to_the_boolean():
    # surfaces apart and one box inside the other: the one solid may lie inside the other, which only the Boolean
    # can tell (here it does: the sweep must fail at once)
    import trimesh

    big = trimesh.creation.box(extents=(20.0, 20.0, 20.0))
    small = trimesh.creation.box(extents=(4.0, 4.0, 4.0))
    scene = A._Scene({"p0-0-0": big, "p1-0-0": small}, kernel=True)
    ok, hit = scene.sweep_clear(["p1-0-0"], ["p0-0-0"], np.array([0.0, 0.0, 1.0]), 1.0, 1e-4)
    assert not ok and hit[:2] == ("p1-0-0", "p0-0-0") and hit[2] == pytest.approx(0.05)
