"""Pipeline behaviour on small specs: determinism, pieces counts, report contents, refusal of bad builds."""


import numpy as np
import pytest
from helpers_build import example_spec, write_spec

import volpuzzle
from volpuzzle.errors import ExportError, GeometryError, SpecError


def small_box_spec(tmp_path, **over):
    spec = {
        "name": "box",
        "model": {"builtin": {"type": "quarter-torus", "major_radius": 50, "minor_radius": 20}},
        "grid": [2, 1, 2],
        "randomize": {"seed": 5, "amplitude": 0.2, "control_points": 5},
        "output": {"directory": str(tmp_path / "out"), "tolerance": 0.5},
    }
    spec.update(over)
    return write_spec(tmp_path, spec)


@pytest.mark.slow
def test_report_has_every_contract_key(tmp_path):
    report = volpuzzle.build(small_box_spec(tmp_path), jobs=1)
    for key in ("volpuzzle_version", "spec", "model", "randomize", "pieces", "joints", "checks", "plates",
                "assembly_order", "timings_s"):
        assert key in report
    assert report["model"]["handedness"] in ("right", "left")
    assert report["randomize"]["bijective"] is True
    assert report["randomize"]["jacobian_min_coefficient"] > 0
    assert [p["id"] for p in report["pieces"]] == ["p0-0-0", "p0-0-1", "p1-0-0", "p1-0-1"]
    for j in report["joints"]:
        assert abs(np.linalg.norm(j["direction"]) - 1) < 1e-5  # the report rounds to 6 decimals
    for stage in ("tile", "joint", "randomize", "verify", "compose", "export"):
        assert stage in report["timings_s"]
    assert report["spec"]["output"]["tolerance"] == 0.5


@pytest.mark.slow
def test_same_seed_same_bytes(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = volpuzzle.build(small_box_spec(tmp_path / "a"), jobs=1)
    b = volpuzzle.build(small_box_spec(tmp_path / "b"), jobs=2)
    for pa, pb in zip(a["pieces"], b["pieces"], strict=True):
        fa = (tmp_path / "a" / "out" / pa["file"]).read_bytes()
        fb = (tmp_path / "b" / "out" / pb["file"]).read_bytes()
        assert fa == fb


@pytest.mark.slow
def test_existing_output_needs_force(tmp_path):
    spec = small_box_spec(tmp_path)
    volpuzzle.build(spec, jobs=1)
    with pytest.raises(ExportError, match="--force"):
        volpuzzle.build(spec, jobs=1)
    volpuzzle.build(spec, jobs=1, force=True)


def test_amplitude_that_folds_names_safe_amplitude(tmp_path):
    spec = small_box_spec(tmp_path, randomize={"seed": 5, "amplitude": 4.0, "control_points": 5})
    with pytest.raises(GeometryError, match=r"randomize.amplitude: 4 folds the map R .*at most [0-9.]+ certifies .*"
                                            r"\(got 4, expected <= [0-9.]+\)"):
        volpuzzle.build(spec, jobs=1)
    assert not (tmp_path / "out").exists()


def test_pin_that_does_not_fit(tmp_path):
    spec = small_box_spec(tmp_path, joints={"radius": 40, "min_radius": 40})
    with pytest.raises(SpecError,
                       match=r"joints: piece p\S+ gets no joint.*; between .*expected joints.min_radius at most"):
        volpuzzle.build(spec, jobs=1)
    assert not (tmp_path / "out").exists()


def test_a_pin_too_wide_shrinks_where_it_must_and_the_report_says_so(tmp_path):
    spec = small_box_spec(tmp_path, joints={"radius": 40})
    stages = volpuzzle.pipeline.prepare(volpuzzle.spec.load_spec(spec))
    assert stages.joints and all(j.shrunk and j.radius < 40 for j in stages.joints)


def test_unknown_builtin_is_a_spec_error(tmp_path):
    spec = small_box_spec(tmp_path, model={"builtin": {"type": "teapot"}})
    with pytest.raises(SpecError, match=r"model.builtin.type: unknown builtin \(got 'teapot', expected one of "
                                        r"quarter-torus, "):
        volpuzzle.build(spec, jobs=1)


@pytest.mark.slow
def test_periodic_twisted_torus_small(tmp_path):
    spec = example_spec("twisted-torus", tmp_path, tolerance=0.5, grid=[2, 2, 4])
    report = volpuzzle.build(spec, jobs=1)
    assert len(report["pieces"]) == 16
    seam_joints = [j for j in report["joints"] if j.get("across_seam")]
    assert seam_joints, "on a periodic axis the joints cross the seam"
    assert report["checks"]["passed"]
    assert not report["assembly"]["welded"]
    assert sorted(report["assembly_order"]) == sorted(p["id"] for p in report["pieces"])


def test_a_seed_without_randomize_is_said_to_change_nothing(tmp_path, capsys):
    # the folder exists, so the build stops before any work: the warning comes first, from the spec alone
    spec = write_spec(tmp_path, {"name": "q", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [2, 1, 1],
                                 "output": {"directory": str(tmp_path / "out")}})
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "x").write_text("mine")
    with pytest.raises(ExportError):
        volpuzzle.build(spec, seed=3, jobs=1)
    assert "warning: --seed 3 changes nothing: the spec does not randomize" in capsys.readouterr().err


def test_a_finishing_stage_lets_go_of_the_solids_of_the_meshes_it_replaced():
    from types import SimpleNamespace

    import trimesh

    from volpuzzle import geometry
    from volpuzzle.pipeline import _replaced

    kept, replaced, new = (trimesh.creation.box() for _ in range(3))
    for m in (kept, replaced):
        geometry.solid_of(m, "piece")
    old = [SimpleNamespace(mesh=kept), SimpleNamespace(mesh=replaced)]
    pieces, extra = _replaced(old, [SimpleNamespace(mesh=kept), SimpleNamespace(mesh=new)], 7.5)
    assert [p.mesh for p in pieces] == [kept, new] and extra == 7.5
    # the unchanged piece keeps its solid (later stages reuse it); the replaced one holds nothing any more
    assert id(replaced) not in geometry._MEMO and "solid_keep_faces" in geometry._MEMO[id(kept)][2]
