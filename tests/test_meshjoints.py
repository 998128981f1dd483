"""Mesh mode joints: a torus-knot tube (genus 1, its fragments in every cell) in box cages builds into pieces that
are all jointed, in one joint graph, with no two joints meeting; balanced splits even out the pieces."""

import networkx as nx
import numpy as np
import pytest
import trimesh
import yaml

from volpuzzle.errors import SpecError
from volpuzzle.pipeline import build
from volpuzzle.spec import load_spec


def knot_tube(p=2, q=3, scale=20.0, tube=5.0, n=240, k=16):
    """A closed (p, q) torus-knot tube, consistently wound, one body."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = np.cos(q * t) + 2.0
    c = scale * np.stack([r * np.cos(p * t), r * np.sin(p * t), -np.sin(q * t)], 1)
    tan = np.roll(c, -1, 0) - np.roll(c, 1, 0)
    tan /= np.linalg.norm(tan, axis=1)[:, None]
    n1 = np.cross(tan, [0.0, 0.0, 1.0])
    n1 /= np.linalg.norm(n1, axis=1)[:, None]
    n2 = np.cross(tan, n1)
    a = np.linspace(0, 2 * np.pi, k, endpoint=False)
    v = (c[:, None] + tube * (np.cos(a)[None, :, None] * n1[:, None] + np.sin(a)[None, :, None] * n2[:, None]))
    i, j = np.arange(n)[:, None], np.arange(k)[None]
    v00, v10 = i * k + j, ((i + 1) % n) * k + j
    v01, v11 = i * k + (j + 1) % k, ((i + 1) % n) * k + (j + 1) % k
    f = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)])
    m = trimesh.Trimesh(v.reshape(-1, 3), f, process=True)
    if m.volume < 0:
        m.invert()
    return m


def seg_distance(p0, p1, q0, q1, n=64):
    s = np.linspace(0, 1, n)[:, None]
    a, b = p0 + s * (p1 - p0), q0 + s * (q1 - q0)
    return float(np.min(np.linalg.norm(a[:, None] - b[None], axis=2)))


@pytest.mark.slow
@pytest.mark.parametrize("grid", [[2, 2, 1], [2, 2, 2]])
def test_a_knot_in_a_box_cage_holds_together(tmp_path, grid):
    # 2 x 2 x 1 leaves two arcs of the knot in every cell; chained arc to arc by their widest contacts they locked
    # each other in (welded). 2 x 2 x 2 pins 7 of its 8 contacts, and no plan can pin more: its contacts make one
    # loop of 8 flat cut faces, so the first split crosses two of them and pins both only when their normals (into
    # the moving part) agree, which three splits do; every direction within 30 deg of theirs (swept on a 0.5 deg by
    # 5 deg grid) hooks into the knot after 30 to 50 mm, and the least lean that slides clear is 32.5 deg.
    knot_tube().export(tmp_path / "knot.stl")
    spec = {"name": "knot", "model": {"mesh": "knot.stl", "cage": {"type": "box", "padding": 2}},
            "grid": grid, "output": {"tolerance": 0.2, "labels": False}}
    (tmp_path / "knot.yaml").write_text(yaml.safe_dump(spec))
    report = build(tmp_path / "knot.yaml", output_dir=tmp_path / "out", force=True, jobs=1)
    ids = [p["id"] for p in report["pieces"]]
    g = nx.Graph()
    g.add_nodes_from(ids)
    g.add_edges_from((j["pin_piece"], j["hole_piece"]) for j in report["joints"])
    assert min(dict(g.degree).values()) >= 1 and nx.is_connected(g)
    assert not report["assembly"]["welded"]
    assert report["checks"]["passed"]
    # no two joints within their holes' reach and a wall of each other
    js = report["joints"]
    for x in range(len(js)):
        for y in range(x + 1, len(js)):
            a, b = js[x], js[y]
            pa, da = np.array(a["center_mm"]), np.array(a["direction"])
            pb, db = np.array(b["center_mm"]), np.array(b["direction"])
            d = seg_distance(pa - da, pa + da * a["length_mm"], pb - db, pb + db * b["length_mm"])
            assert d >= a["radius_mm"] + a["clearance_mm"] + b["radius_mm"] + b["clearance_mm"]
    contacts = report["mesh"]["contacts"]
    assert all(c["pinned"] or c["reason"] for c in contacts)
    assert sum(c["pinned"] for c in contacts) >= 0.85 * sum(c["room"] for c in contacts)
    # every pinned contact's pin points along the slide of the step that parts its two pieces
    steps = report["assembly"]["steps"]
    for j in report["joints"]:
        step = next(s for s in steps if s["kind"] == "join" and [j["pin_piece"], j["hole_piece"]] in s["joints"])
        assert abs(float(np.dot(step["direction"], j["direction"]))) > 0.999


def test_a_slide_leaning_too_far_off_a_contact_says_how_far():
    from volpuzzle.geometry import from_trimesh
    from volpuzzle.meshcut import PinSize, _Patch, _try, contacts

    a = trimesh.creation.box(extents=[10, 20, 20])
    a.apply_translation([-5, 0, 0])
    b = trimesh.creation.box(extents=[10, 20, 20])
    b.apply_translation([5, 0, 0])
    (c,) = contacts({"a": a, "b": b})
    patch = _Patch(c, np.random.default_rng(0))
    crops = {"a": from_trimesh(a, "a"), "b": from_trimesh(b, "b")}
    size = PinSize(1.5, 4.0, 0.15, 0.3)
    lean = np.array([np.cos(np.radians(20)), np.sin(np.radians(20)), 0.0])
    option, why = _try(patch, c, crops, size, lean, True)
    assert why is None and abs(float(option.direction @ lean)) > 0.999
    for pin_a in (True, False):
        option, why = _try(patch, c, crops, size, np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0), pin_a)
        assert option is None
        assert why == ("the sliding direction of the split between a and b stands at least 45 deg off the contact "
                       "wherever a pin has room, more than the 30 deg a straight pin may lean")


def test_balanced_splits_are_the_default_for_meshes_only(tmp_path):
    knot_tube().export(tmp_path / "knot.stl")
    spec = {"name": "knot", "model": {"mesh": "knot.stl", "cage": {"type": "box"}}, "grid": [2, 2, 1]}
    (tmp_path / "a.yaml").write_text(yaml.safe_dump(spec))
    assert load_spec(tmp_path / "a.yaml").splits == ("balanced",) * 3
    spec = {"name": "t", "model": {"builtin": {"type": "torus"}}, "grid": [2, 2, 2], "splits": {"u": "balanced"}}
    (tmp_path / "b.yaml").write_text(yaml.safe_dump(spec))
    with pytest.raises(SpecError, match="splits.u: balanced splits follow a mesh's volume"):
        load_spec(tmp_path / "b.yaml")


def test_balanced_splits_even_out_the_mesh():
    from volpuzzle.cage import make_cage, mesh_mass
    from volpuzzle.mapping import Map
    from volpuzzle.spec import CageSpec
    from volpuzzle.tile import _cell_masses, tile

    mesh = trimesh.creation.cone(20.0, 60.0, sections=48)  # most of its volume near the base
    cage, _ = make_cage(mesh, CageSpec(type="box", padding=1.0))
    mass = mesh_mass(Map(cage), mesh)
    assert mass.sum() == pytest.approx(1.0)
    n = mass.shape[0]
    prefix = np.zeros((n + 1,) * 3)
    prefix[1:, 1:, 1:] = mass.cumsum(0).cumsum(1).cumsum(2)

    def ratio(t):
        pos = [np.asarray(b) * n for b in t.breaks]
        c = _cell_masses(prefix, pos)
        return c.max() / c.min()

    even = tile(cage, (2, 2, 2), ("balanced",) * 3, mass=mass)
    plain = tile(cage, (2, 2, 2), ("uniform",) * 3)
    assert ratio(even) < 0.8 * ratio(plain)


def _box(lo, hi):
    import manifold3d

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return manifold3d.Manifold.cube(list(hi - lo)).translate(list(lo))


def test_a_contact_with_room_gets_one_pin_in_its_middle_along_the_slide():
    from volpuzzle.meshcut import PinSize, joint_graph_problem, place_joints

    pieces = {"p0-0-0": _box([0, 0, 0], [20, 20, 20]), "p1-0-0": _box([20, 0, 0], [40, 20, 20])}
    cells = {"p0-0-0": (0, 0, 0), "p1-0-0": (1, 0, 0)}
    joints, records, plan = place_joints(pieces, cells, PinSize(2.0, 5.0, 0.15, 0.3))
    assert len(joints) == 1 and records[0]["pinned"] and records[0]["room"]
    j = joints[0]
    assert np.allclose(np.abs(j.direction), [1, 0, 0]) and j.center[0] == pytest.approx(20.0)
    assert np.hypot(j.center[1] - 10, j.center[2] - 10) < 2.5  # the middle of the face, farthest from its edge
    assert (j.radius, j.length) == (2.0, 5.0)
    assert joint_graph_problem(sorted(pieces), joints, records) is None
    assert [len(s.moving) for s in plan.steps] == [1]


def test_a_small_contact_takes_a_smaller_pin_down_to_the_minimum_then_none():
    from volpuzzle.meshcut import PinSize, joint_graph_problem, place_joints

    cells = {"p0-0-0": (0, 0, 0), "p1-0-0": (1, 0, 0)}
    small = {"p0-0-0": _box([0, 0, 0], [20, 5, 5]), "p1-0-0": _box([20, 0, 0], [40, 5, 5])}
    joints, records, _ = place_joints(small, cells, PinSize(2.0, 5.0, 0.15, 0.3))
    assert len(joints) == 1 and 1.0 <= joints[0].radius < 2.0
    tiny = {"p0-0-0": _box([0, 0, 0], [20, 3, 3]), "p1-0-0": _box([20, 0, 0], [40, 3, 3])}
    joints, records, _ = place_joints(tiny, cells, PinSize(2.0, 5.0, 0.15, 0.3))
    assert joints == [] and not records[0]["room"] and "no room" in records[0]["reason"]
    problem = joint_graph_problem(sorted(tiny), joints, records)
    assert problem.startswith("p") and "has no joint" in problem and "no room" in problem


def test_a_pin_never_reaches_into_a_third_piece():
    from volpuzzle.meshcut import PinSize, place_joints

    # p1 is a 4 mm slab between p0 and p2: a 5 mm pin from p0 would cross it into p2, so it shrinks to fit
    pieces = {"p0-0-0": _box([0, 0, 0], [20, 20, 20]), "p1-0-0": _box([20, 0, 0], [24, 20, 20]),
              "p2-0-0": _box([24, 0, 0], [44, 20, 20])}
    cells = {k: (i, 0, 0) for i, k in enumerate(sorted(pieces))}
    joints, records, _ = place_joints(pieces, cells, PinSize(2.0, 5.0, 0.15, 0.3))
    for j in joints:
        a, b = j.center - j.base_depth * j.direction, j.center + (j.length + j.axial_clearance) * j.direction
        xs = sorted([a[0], b[0]])
        assert xs[0] >= -1e-9 and xs[1] <= 44
        # the joint stays within its two pieces' slabs
        lo_cell, hi_cell = sorted((j.pin_cell[0], j.hole_cell[0]))
        bounds = [0, 20, 24, 44]
        assert bounds[lo_cell] - 1e-9 <= xs[0] and xs[1] <= bounds[hi_cell + 1] + 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("model, cage, grid, periodic", [
    ("specs/models/cgal_bunny00.ply", "sphere", [1, 3, 4], ["w"]),
    ("specs/models/stlmodels_gearwheel.bin.stl", "cylinder", [2, 4, 1], ["v"])])
def test_curved_cages_hold_meshes_together(tmp_path, model, cage, grid, periodic):
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / model
    spec = {"name": "b", "model": {"mesh": str(path), "cage": {"type": cage, "padding": 2}, "size": 80},
            "grid": grid, "periodic": periodic, "output": {"tolerance": 0.3, "labels": False}}
    (tmp_path / "b.yaml").write_text(yaml.safe_dump(spec))
    report = build(tmp_path / "b.yaml", output_dir=tmp_path / "out", force=True, jobs=1)
    g = nx.Graph()
    g.add_nodes_from(p["id"] for p in report["pieces"])
    g.add_edges_from((j["pin_piece"], j["hole_piece"]) for j in report["joints"])
    assert nx.is_connected(g) and min(dict(g.degree).values()) >= 1
    assert report["checks"]["passed"] and not report["assembly"]["welded"]


def test_a_fragment_prefers_the_piece_spanning_fewest_cells_among_near_widest_contacts():
    from volpuzzle.meshcut import merge_fragments

    # f (cell p2's fragment) touches p0 over 100 mm^2 and p1 over 120; p1 has taken h, p3's fragment, first (130).
    # p1 with f would span three cells, p0 with f two: a piece spread over many cells reaches round its neighbours
    # (the knot's arcs), so f goes to p0, its contact being more than half its widest.
    p0 = _box([10, 12, 0], [20, 20, 10])
    p1 = _box([20, 0, 0], [33, 12, 10])
    f = _box([10, 0, 0], [20, 12, 10])
    h = _box([20, -10, 0], [33, 0, 10])
    pieces = {"p0-0-0": p0, "p1-0-0": p1, "p2-0-0": _box([100, 0, 0], [130, 30, 30]) + f,
              "p3-0-0": _box([200, 0, 0], [230, 30, 30]) + h}
    out, records = merge_fragments(pieces)
    assert {(r["from"], r["to"]) for r in records} == {("p2-0-0", "p0-0-0"), ("p3-0-0", "p1-0-0")}
    assert out["p0-0-0"].volume() == pytest.approx(800 + 1200)
    assert all(len(p.decompose()) == 1 for p in out.values())


def test_the_exact_plan_pins_every_contact_that_one_slide_per_split_can_hold():
    from volpuzzle.meshcut import _ExactPlan

    def flat(n, area=100.0, sliver=None):
        ns, ws = [np.asarray(n, float)] * 2, [area / 2] * 2
        if sliver is not None:  # a 0.01 mm^2 triangle facing anywhere, as where the mesh meets a cut face
            ns.append(np.asarray(sliver, float))
            ws.append(0.01)
        return np.array(ns), np.array(ws)

    # a-b meet on an x plane, a-c and b-c on z planes: c must leave first (along +z, both its pins), then b (+x);
    # b first would cross one x and one z contact, which no one slide within 30 deg of both can pin
    normals = {("a", "b"): flat([1, 0, 0], sliver=[-1, 0, 0]), ("a", "c"): flat([0, 0, 1]),
               ("b", "c"): flat([0, 0, 1])}
    centre = {"a": np.zeros(3), "b": np.array([10.0, 0, 0]), "c": np.array([5.0, 0, 10])}
    plan = _ExactPlan(normals, None, centre, lambda *_: True)  # every split slides: the contacts alone decide
    steps = plan.plan(["a", "b", "c"], [10])
    assert [s[0] for s in steps] == [["c"], ["b"]]
    assert np.allclose(steps[0][2], [0, 0, 1]) and np.allclose(steps[1][2], [1, 0, 0])
    assert plan.score({"a", "b", "c"}, {"b"})[0] == 1 and plan.score({"a", "b"}, {"b"})[0] == 1
