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
