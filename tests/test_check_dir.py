"""`volpuzzle check DIR` on a real build, and on copies of it that were tampered with."""

import json
import shutil

import pytest
import trimesh
from click.testing import CliRunner
from helpers_build import write_spec

import volpuzzle
from volpuzzle.check import check_directory
from volpuzzle.cli import cli
from volpuzzle.errors import VolpuzzleError


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("build")
    spec = write_spec(tmp, {"name": "chk", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [2, 1, 2],
                            "output": {"directory": str(tmp / "out"), "tolerance": 0.3}})
    volpuzzle.build(spec, jobs=1)
    return tmp / "out"


@pytest.fixture
def copy(built, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(built, dst)
    return dst


def fails(directory, *words):
    result = CliRunner().invoke(cli, ["check", str(directory)])
    assert result.exit_code != 0
    assert "Traceback" not in result.output
    for w in words:
        assert w in result.output, result.output
    return result.output


def test_a_fresh_build_passes(built):
    checks = check_directory(built)
    assert checks["passed"] and checks["joints_checked"] >= 1
    assert CliRunner().invoke(cli, ["check", str(built)]).exit_code == 0


def test_a_piece_file_the_report_does_not_list_is_named(built, copy):
    assert not check_directory(built)["printability"]["warnings"]
    shutil.copy(copy / "pieces" / "p0-0-0.stl", copy / "pieces" / "old-p9.stl")
    (warning,) = check_directory(copy)["printability"]["warnings"]
    assert warning.startswith("pieces/old-p9.stl: in the folder but not a piece of report.json (expected only its 4 ")
    result = CliRunner().invoke(cli, ["check", str(copy)])
    assert result.exit_code == 0 and "warning: pieces/old-p9.stl: in the folder" in result.output


def test_piece_moved_into_its_neighbour(copy):
    report = json.loads((copy / "report.json").read_text())
    j = report["joints"][0]
    path = copy / "pieces" / f"{j['hole_piece']}.stl"
    mesh = trimesh.load(path)
    mesh.apply_translation([-3.0 * x for x in j["direction"]])
    mesh.export(path)
    fails(copy, j["hole_piece"])


def test_deleted_piece_file(copy):
    victim = sorted((copy / "pieces").iterdir())[0]
    victim.unlink()
    fails(copy, "missing", victim.name)


def test_truncated_piece_file(copy):
    victim = sorted((copy / "pieces").iterdir())[-1]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    fails(copy, victim.stem)


def test_pin_without_room_in_its_hole(copy):
    report = json.loads((copy / "report.json").read_text())
    report["joints"][0]["radius_mm"] *= 1.3  # the pin the report promises no longer fits the hole that was cut
    (copy / "report.json").write_text(json.dumps(report))
    fails(copy, "does not fit its hole")


def test_a_piece_without_a_joint_fails(copy):
    report = json.loads((copy / "report.json").read_text())
    victim = report["joints"][0]["hole_piece"]
    report["joints"] = [j for j in report["joints"] if victim not in (j["pin_piece"], j["hole_piece"])]
    (copy / "report.json").write_text(json.dumps(report))
    fails(copy, f"piece {victim} gets no joint")
    # the same folder passes when the spec allowed loose pieces
    report["spec"]["joints"]["allow"] = ["loose"]
    (copy / "report.json").write_text(json.dumps(report))
    assert check_directory(copy)["joint_graph"]["pieces_without_joint"] == [victim]


def test_a_puzzle_in_two_parts_fails(copy):
    report = json.loads((copy / "report.json").read_text())
    # keep only the joints inside the first two pieces' pair and inside the last two: two parts, no loose piece
    ids = sorted(p["id"] for p in report["pieces"])
    halves = (set(ids[:2]), set(ids[2:]))
    report["joints"] = [j for j in report["joints"]
                        if any({j["pin_piece"], j["hole_piece"]} <= h for h in halves)]
    (copy / "report.json").write_text(json.dumps(report))
    parts = check_directory(copy, raise_on_failure=False)["joint_graph"]["parts"]
    assert parts == 2
    fails(copy, "falls apart into 2 parts")


def test_a_welded_assembly_fails(copy):
    report = json.loads((copy / "report.json").read_text())
    report["assembly"]["welded"], report["assembly"]["stuck"] = True, [report["pieces"][0]["id"]]
    (copy / "report.json").write_text(json.dumps(report))
    fails(copy, "welded", report["pieces"][0]["id"])


def test_not_a_build(tmp_path):
    with pytest.raises(VolpuzzleError, match="no report.json"):
        check_directory(tmp_path)
    fails(tmp_path, "no report.json")


def _pieces_and_joints(directory):
    report = json.loads((directory / "report.json").read_text())
    meshes = {p["id"]: trimesh.load(directory / p["file"], process=False) for p in report["pieces"]}
    for mesh in meshes.values():
        mesh.merge_vertices()
    return meshes, report["joints"]


def test_joint_tests_the_surface_keeps_clear_of_need_no_engine(built, monkeypatch):
    # the pins of a real build sit in their holes with room all round: each test passes on the count of one ray, and
    # the engine measures nothing; with every test left to the engine the answer is the same
    from volpuzzle import check as C

    meshes, joints = _pieces_and_joints(built)
    measured = []
    real = C._measured
    monkeypatch.setattr(C, "_measured", lambda *a: measured.append(1) or real(*a))
    assert C.check_joints(meshes, joints) == [] and not measured
    monkeypatch.setattr(C, "_left_to_measure", lambda _mesh, tests: tests)
    assert C.check_joints(meshes, joints) == [] and len(measured) >= len(joints)


def test_joints_that_fail_are_measured_by_the_engine_alike(built, monkeypatch):
    # pins moved 0.6 mm across their axes stick out of their pieces' cores and into the holes' walls: the engine
    # measures each of those tests, and every sentence (its volume too) is what the engine alone gives
    from volpuzzle import check as C

    meshes, joints = _pieces_and_joints(built)
    moved = [dict(j, center_mm=[c + 0.6 * s for c, s in zip(j["center_mm"], (0.6, -0.8, 0.0), strict=True)])
             for j in joints]
    with_shortcut = C.check_joints(meshes, moved)
    monkeypatch.setattr(C, "_left_to_measure", lambda _mesh, tests: tests)
    assert with_shortcut == C.check_joints(meshes, moved)
    assert len(with_shortcut) >= len(joints)


def test_a_small_folder_is_checked_without_starting_numba(built):
    # numba takes ~0.5 s to start: `volpuzzle check` of a few pieces measures their joints with the engine alone
    import subprocess
    import sys

    code = (f"import sys; from volpuzzle.check import check_directory; "
            f"print(check_directory({str(built)!r})['passed'], 'numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["True", "False"]


def _edit_report(directory, change):
    report = json.loads((directory / "report.json").read_text())
    change(report)
    (directory / "report.json").write_text(json.dumps(report))
    return report


def _truncate(path):
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


@pytest.mark.parametrize("edit, words", [
    # the files printed besides the pieces: the plates, the assembled puzzle
    (lambda d: (d / "plates" / "plate-01.3mf").unlink(), ["missing file plates/plate-01.3mf (plates[0].file)"]),
    (lambda d: (d / "puzzle.3mf").write_bytes(b""), ["puzzle.3mf: empty file (puzzle.3mf)"]),
    (lambda d: _truncate(d / "plates" / "plate-01.3mf"), ["plates/plate-01.3mf: not a readable 3MF file"]),
    # what report.json (and report.md) says of the pieces against their files
    (lambda d: _edit_report(d, lambda r: r["pieces"][0].update(triangles=5)),
     ["pieces[0].triangles: report.json gives p0-0-0 5, its file holds"]),
    (lambda d: _edit_report(d, lambda r: r["pieces"][1].update(bbox_mm=[[0, 0, 0], [1, 1, 1]])),
     ["pieces[1].bbox_mm: report.json gives", "its file spans"]),
    (lambda d: _edit_report(d, lambda r: r["pieces"][2].update(plate=7)),
     ["pieces[2].plate: report.json gives", "plate 7, plates lists it on plate 1"]),
    (lambda d: _edit_report(d, lambda r: r["plates"][0]["pieces"].pop(0)), ["is on no plate"]),
    (lambda d: _edit_report(d, lambda r: r.update(plates=[])), ["is on no plate"]),
    (lambda d: _edit_report(d, lambda r: r["plates"].append({"file": "plates/plate-01.3mf",
                                                              "pieces": [r["pieces"][0]["id"]]})),
     ["is on plates 1, 2 (expected one)"]),
])
def test_check_fails_a_folder_whose_other_files_or_report_disagree(copy, edit, words):
    edit(copy)
    fails(copy, *words)


@pytest.mark.parametrize("change", ["mirror", "scale"])
def test_a_placement_that_mirrors_or_scales_the_piece_is_refused(copy, change):
    # a mirrored piece prints as its mirror image, which fits nowhere; a scaled one at another size
    def edit(report):
        t = report["pieces"][2]["print"]["plate_transform"]
        for row in t[:3]:
            row[0] *= -1.0 if change == "mirror" else 1.5

    _edit_report(copy, edit)
    fails(copy, "pieces[2].print.plate_transform: not a rotation and a move",
          "a mirror or a scale would print another shape")


def test_a_broken_3mf_piece_and_dowel_are_named_by_their_own_files(tmp_path):
    from test_export import make_pieces, make_report

    from volpuzzle.export import write_build

    pieces = make_pieces()
    dowel = trimesh.creation.cylinder(radius=2, height=10, sections=16)
    target = write_build(tmp_path / "c", pieces, make_report(pieces), fmt="3mf", dowels=[("dowel-00", dowel)])
    assert check_directory(target)["passed"]
    _truncate(target / "pieces" / "p0-0-0.3mf")
    _truncate(target / "dowels" / "dowel-00.3mf")
    failures = check_directory(target, raise_on_failure=False)["failures"]
    assert any(f.startswith(f"{target / 'pieces' / 'p0-0-0.3mf'}: not a readable 3MF file") for f in failures)
    assert not any("/tmp/tmp" in f for f in failures)
    assert any(f.startswith("dowels/dowel-00.3mf: not a readable 3MF file") for f in failures)
    (target / "dowels" / "dowel-00.3mf").unlink()
    assert "missing file dowels/dowel-00.3mf (dowels[0].file)" in check_directory(target, raise_on_failure=False)[
        "failures"]


def test_a_dowel_build_passes_and_each_dowel_must_be_on_one_plate(tmp_path):
    # dowels are printed as the pieces are: on a plate each, and their files there and whole
    spec = write_spec(tmp_path, {"name": "dow", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [2, 1, 2],
                                 "joints": {"style": "dowel"},
                                 "output": {"directory": str(tmp_path / "out"), "tolerance": 0.3}})
    volpuzzle.build(spec, jobs=1)
    out = tmp_path / "out"
    assert check_directory(out)["passed"]
    report = json.loads((out / "report.json").read_text())
    name, rel = report["dowels"][0]["name"], report["dowels"][0]["file"]
    _edit_report(out, lambda r: [p["pieces"].remove(name) for p in r["plates"] if name in p["pieces"]])
    fails(out, f"plates: dowel {name} is on 0 plates (expected one)")
    (out / rel).unlink()
    fails(out, f"missing file {rel} (dowels[0].file)")


@pytest.mark.parametrize("value, token", [(float("nan"), "NaN"), (float("-inf"), "-Infinity")])
def test_a_number_json_does_not_have_is_named_by_its_field(copy, value, token):
    # a hand-edited report.json: the line names the field that holds it, not only the file
    def edit(report):
        report["pieces"][2]["print"]["plate_transform"][0][0] = value

    _edit_report(copy, edit)
    fails(copy, f"report.json: pieces[2].print.plate_transform[0][0]: {token} is not a JSON number")
