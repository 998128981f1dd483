"""Every puzzle holds together: on the V-rep specs every piece carries a joint, the joint graph is one part, every
contact with room is pinned (at most three pins and three holes a piece), tilted pins and holes never meet inside a
piece, and a puzzle that falls apart or is welded fails unless the user allows it."""

from collections import Counter

import numpy as np
import pytest
from conftest import REPO
from helpers_build import example_spec, write_spec
from test_assembly import _bent, _built, _map, _warp
from test_joint import _body, _cell_solids, _vol

from volpuzzle import joint as J
from volpuzzle.errors import GeometryError, SpecError
from volpuzzle.pipeline import prepare
from volpuzzle.spec import load_spec


def _prepared(name, tmp_path, **over):
    if name == "duck-blob":
        # the builtin duck-like blob, 4 x 8 x 1 as the paper's duck: its thin shell still takes printable pins
        return prepare(load_spec(write_spec(tmp_path, {
            "name": name, "model": {"builtin": {"type": "duck-shell"}}, "grid": [4, 8, 1], "periodic": ["v"],
            "output": {"tolerance": 0.5, "directory": str(tmp_path / "out")}, **over})))
    return prepare(load_spec(example_spec(name, tmp_path, tolerance=0.5, **over)))


def _assert_holds(stages):
    tiling, joints, contacts = stages.tiling, stages.joints, stages.contacts
    ids = [J.piece_id(c) for c in tiling.cells]
    parts, loose = J.joint_graph(ids, [(J.piece_id(j.pin_cell), J.piece_id(j.hole_cell)) for j in joints])
    assert loose == [] and len(parts) == 1
    assert len(contacts) == len(tiling.faces)
    room = [c for c in contacts if c["room"]]
    assert sum(c["pinned"] for c in room) >= 0.9 * len(room)
    assert all(c["reason"] for c in contacts if not c["pinned"])
    roles = Counter((J.piece_id(c), r) for c in tiling.cells for _, r in J.pieces_joints(joints, c))
    assert max(roles.values()) <= 3
    for j in joints:
        assert j.radius >= J.MIN_RADIUS - 1e-9 and j.length >= J.MIN_LENGTH - 1e-9
        assert j.tilt_deg <= J.MAX_TILT_DEG + 1e-9


@pytest.mark.parametrize("name", ["quarter-torus", "twisted-pipe", "sphere-shell", "duck-blob",
                                  pytest.param("generalized-torus", marks=pytest.mark.slow),
                                  pytest.param("twisted-torus", marks=pytest.mark.slow)])
def test_every_piece_is_jointed_and_the_puzzle_is_one_part(name, tmp_path):
    _assert_holds(_prepared(name, tmp_path))


def test_a_randomized_quarter_torus_pins_all_twelve_contacts(tmp_path):
    stages = _prepared("quarter-torus", tmp_path)
    assert stages.randomize_report["amplitude"] > 0 and len(stages.tiling.faces) == 12
    assert len(stages.joints) == 12 and all(c["pinned"] for c in stages.contacts)
    assert len(stages.plan.faces_with_joints) == 12


def test_the_twisted_pipe_in_inches_takes_a_radius_of_one_and_a_half(tmp_path):
    spec = write_spec(tmp_path, {
        "name": "pipe-in", "model": {"nurbs": str(REPO / "specs" / "models" / "gismo_twisted_pipe.xml"),
                                     "units": "in"},
        "grid": [4, 2, 2], "randomize": {"seed": 11, "amplitude": 0.2},
        "joints": {"radius": 1.5}, "output": {"directory": str(tmp_path / "out")}})
    stages = prepare(load_spec(spec))
    _assert_holds(stages)
    assert all(j.radius == 1.5 and not j.shrunk for j in stages.joints)


def test_tilted_pins_and_holes_never_meet_inside_a_piece():
    t, _, joints, _ = _built("bent")
    fmap = _map(_bent(), _warp())
    assert any(j.tilt_deg > 1.0 for j in joints)
    for idx, cell in t.cells.items():
        body = _body(fmap, cell)
        parts = [(j, s ^ body) for j, _, s in _cell_solids(joints, idx)]
        for a in range(len(parts)):
            for b in range(a + 1, len(parts)):
                assert _vol(parts[a][1] ^ parts[b][1]) < 1e-6, (idx, parts[a][0].axis, parts[b][0].axis)


def test_cylinders_apart_only_when_a_wall_fits_between_them():
    z = np.array([[0.0, 0.0, 0.0]])
    up = np.array([[0.0, 0.0, 5.0]])

    def apart(q0, q1, gap):
        return J._Cylinders(z, up, 1.0).apart_all([(q0, q1, 1.0)], gap)[0]

    # side by side: axes 3 mm apart, radii 1 + 1, so a wall of 1 fits and 1.2 does not
    q0, q1 = np.array([3.0, 0.0, 0.0]), np.array([3.0, 0.0, 5.0])
    assert apart(q0, q1, 1.0) and not apart(q0, q1, 1.2)
    # end to end on one axis: only the gap between the flat ends counts
    q0, q1 = np.array([0.0, 0.0, 6.0]), np.array([0.0, 0.0, 9.0])
    assert apart(q0, q1, 0.9) and not apart(q0, q1, 1.1)
    # crossing
    q0, q1 = np.array([-4.0, 0.0, 2.0]), np.array([4.0, 0.0, 2.0])
    assert not apart(q0, q1, 0.1)


def test_welded_without_opt_in_fails_the_build_and_with_it_warns(monkeypatch, capsys):
    import volpuzzle.assembly as A
    t, plan, joints, pieces = _built("box")
    stuck = sorted(pieces)[:2]
    monkeypatch.setattr(A, "verify_disassembly", lambda *_a, **_k: {
        "assembly_order": sorted(pieces), "steps": [], "welded": True, "stuck": stuck, "booleans": 0, "seconds": 0})
    with pytest.raises(GeometryError) as e:
        A.replay_assembly(plan, [], joints)
    assert str(e.value).startswith(f"assembly: the puzzle is welded: {stuck[0]}, {stuck[1]} cannot be taken out")
    assert "joints.allow: [welded]" in str(e.value) and "\n" not in str(e.value)
    res = A.replay_assembly(plan, [], joints, allow=("welded",))
    assert res["welded"] and "warning: the puzzle is welded" in capsys.readouterr().err


def test_a_puzzle_in_two_parts_fails_with_one_line():
    ids = ["p0-0-0", "p1-0-0", "p2-0-0", "p3-0-0"]
    contacts = [{"pieces": ["p1-0-0", "p2-0-0"], "pinned": False,
                 "reason": "no room: the face holds a pin of radius at most 0.6 mm with its clearance and wall"}]
    msg = J.graph_problem(ids, [("p0-0-0", "p1-0-0"), ("p2-0-0", "p3-0-0")], contacts, grid=(4, 1, 1))
    assert msg.startswith("joints: the puzzle falls apart into 2 parts")
    assert "between p1-0-0 and p2-0-0, no room" in msg and "expected joints.min_radius at most 0.6 there" in msg
    assert "\n" not in msg
    assert J.graph_problem(ids, [], contacts, style="none") is None
    assert J.graph_problem(ids, [], contacts, allow=("loose",)) is None


def test_tilt_advice_names_randomize_amplitude_only_when_the_puzzle_is_randomized():
    # an unrandomized 2 x 3 x 1 sphere shell fails on tilt: "a smaller randomize.amplitude" sent the user after a key
    # the spec does not have
    ids = ["p0-0-0", "p0-1-0"]
    contacts = [{"pieces": ["p0-0-0", "p0-1-0"], "pinned": False,
                 "reason": "tilt: its split slides at least 30.3 deg off the face's normal where a pin fits"}]
    plain = J.graph_problem(ids, [], contacts, grid=(1, 2, 1), randomized=False)
    assert "more pieces along the curved axis, or joints.allow: [loose]" in plain and "randomize" not in plain
    assert "a smaller randomize.amplitude" in J.graph_problem(ids, [], contacts, grid=(1, 2, 1), randomized=True)


def test_a_crowded_piece_is_not_sent_to_the_coarser_grid_its_neighbours_room_asks_for():
    # the 4x4x64 twisted torus: its first loose piece is crowded, other faces lack room, and the grid with room
    # (4x4x47) is crowded too, so the advice follows the reason shown, not the room of another face
    ids = ["p0-0-0", "p1-0-0", "p2-0-0"]
    contacts = [{"pieces": ["p0-0-0", "p1-0-0"], "pinned": False,
                 "reason": "crowded: every spot with room meets another joint of p0-0-0 or p1-0-0"},
                {"pieces": ["p0-0-0", "p2-0-0"], "pinned": False,
                 "reason": "no room: the face holds a pin of radius at most 0.6 mm with its clearance and wall"}]
    msg = J.graph_problem(ids, [("p1-0-0", "p2-0-0")], contacts, grid=(3, 1, 1), roomy=((2, 1, 1), 1.0, 3.0))
    assert msg.startswith("joints: piece p0-0-0 gets no joint; between p0-0-0 and p1-0-0, crowded")
    assert msg.endswith("(got grid [3, 1, 1], expected a smaller joints.radius, a larger model.size, a coarser grid, "
                        "or joints.allow: [loose])")
    assert "[2, 1, 1]" not in msg
    flipped = J.graph_problem(ids, [("p1-0-0", "p2-0-0")], contacts[::-1], grid=(3, 1, 1),
                              roomy=((2, 1, 1), 1.0, 3.0))
    assert "between p0-0-0 and p2-0-0, no room" in flipped and "grid [2, 1, 1] or coarser" in flipped


@pytest.mark.parametrize("value,path,words", [
    (["glued"], "joints.allow[0]", "unknown (got 'glued', expected one of loose, welded)"),
    (5, "joints.allow", "not a list"),
])
def test_joints_allow_names_the_bad_value(tmp_path, value, path, words):
    spec = write_spec(tmp_path, {"name": "x", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [2, 1, 1],
                                 "joints": {"allow": value}})
    with pytest.raises(SpecError) as e:
        load_spec(spec)
    assert path in str(e.value) and words.split(" (")[0] in str(e.value)


def test_joints_allow_is_read(tmp_path):
    spec = write_spec(tmp_path, {"name": "x", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [2, 1, 1],
                                 "joints": {"allow": ["welded", "loose"], "min_radius": 0.8, "min_length": 2}})
    j = load_spec(spec).joints
    assert j.allow == ("loose", "welded") and j.min_radius == 0.8 and j.min_length == 2
