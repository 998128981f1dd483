"""The spec loader: defaults, round trip, and one test per kind of mistake it reports."""

import copy
import json
import re
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volpuzzle.errors import SpecError
from volpuzzle.spec import (
    CageSpec,
    JointSpec,
    OutputSpec,
    RandomizeSpec,
    Spec,
    load_spec,
    load_spec_text,
    spec_to_dict,
    with_overrides,
)

PROBLEM_RE = re.compile(r"^\S.*?: .+ \(got .+, expected .+\)$", re.S)


@pytest.fixture()
def folder(tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "vol.json").write_text("{}")
    (tmp_path / "models" / "cage.json").write_text("{}")
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "bunny.off").write_text("OFF\n0 0 0\n")
    return tmp_path


def base():
    return {"name": "t", "model": {"nurbs": "models/vol.json"}, "grid": [2, 2, 3]}


def merged(changes, drop=()):
    """base() with `changes` merged in (dicts recursively) and dotted keys in `drop` removed."""
    out = base()

    def merge(into, new):
        for k, v in new.items():
            if isinstance(v, dict) and isinstance(into.get(k), dict):
                merge(into[k], v)
            else:
                into[k] = v
    merge(out, copy.deepcopy(changes))
    for dotted in drop:
        *parents, last = dotted.split(".")
        node = out
        for p in parents:
            node = node[p]
        del node[last]
    return out


def load(folder, data):
    text = data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False)
    return load_spec_text(text, source=folder / "spec.yaml")


def problems_of(folder, data):
    with pytest.raises(SpecError) as info:
        load(folder, data)
    for p in info.value.problems:
        assert PROBLEM_RE.match(p), p
    return info.value.problems


def only_problem(folder, data, key):
    probs = problems_of(folder, data)
    assert len(probs) == 1, probs
    assert probs[0].startswith(key + ": "), probs[0]
    return probs[0]


# ----------------------------------------------------------------------------------------------------
# Valid specs


def test_minimal_spec_gets_every_default(folder, monkeypatch):
    monkeypatch.chdir(folder)
    spec = load(folder, base())
    assert spec.name == "t" and spec.grid == (2, 2, 3)
    assert spec.model.nurbs == (folder / "models" / "vol.json").resolve()
    assert spec.model.patch == 0 and spec.model.units == "mm" and spec.model.unit_scale == 1.0
    assert spec.model.size is None and spec.model.repair is False and spec.model.cage is None
    assert spec.splits == ("uniform",) * 3 and spec.periodic == () and spec.randomize is None
    assert spec.joints == JointSpec("pin", "cylinder", None, None, 0.15, 0.3, "physical")
    assert spec.output == OutputSpec(folder.resolve() / "out" / "t", "stl", 0.05, (250.0, 210.0), 4.0, True)
    assert spec.source == (folder / "spec.yaml").resolve()


def test_full_spec_round_trips_through_spec_to_dict(folder, monkeypatch):
    monkeypatch.chdir(folder)
    data = {
        "name": "twisted-torus_2",
        "model": {"nurbs": "models/vol.json", "patch": 1, "units": "cm", "size": 150},
        "grid": [2, 3, 4],
        "splits": {"u": "knots", "v": [0.25, 0.5], "w": "uniform"},
        "periodic": ["w", "u"],
        "randomize": {"seed": 7, "amplitude": 0.3, "control_points": 5},
        "joints": {"style": "dowel", "shape": "snap", "radius": 2.5, "length": 6, "clearance": 0.2,
                   "axial_clearance": 0.4, "space": "domain", "min_radius": 0.8, "min_length": 2.5,
                   "allow": ["welded"]},
        "output": {"directory": "build/x", "format": "3mf", "tolerance": 0.1, "plate": [200, 200],
                   "spacing": 3, "labels": False, "margin": 5, "face_clearance": 0.1},
    }
    spec = load(folder, data)
    assert spec.model.unit_scale == 10.0 and spec.model.patch == 1
    assert spec.splits == ("knots", (0.25, 0.5), "uniform") and spec.periodic == (0, 2)
    assert spec.randomize == RandomizeSpec(7, 0.3, 5)
    assert spec.output.directory == folder.resolve() / "build" / "x" and spec.output.labels is False
    assert spec.raw == data

    d = spec_to_dict(spec)
    json.dumps(d)  # report.json needs it serialisable
    assert set(d) == {"name", "model", "grid", "splits", "periodic", "randomize", "joints", "output"}
    assert set(d["joints"]) == {"style", "shape", "radius", "length", "clearance", "axial_clearance", "space",
                                "min_radius", "min_length", "allow"}
    assert set(d["output"]) == {"directory", "format", "tolerance", "plate", "spacing", "labels", "margin",
                                "face_clearance"}
    assert spec.output.margin == 5 and spec.output.face_clearance == 0.1
    assert load(folder, d) == spec

    minimal = spec_to_dict(load(folder, base()))
    assert minimal["joints"]["clearance"] == 0.15 and minimal["output"]["plate"] == [250.0, 210.0]
    assert minimal["model"]["units"] == "mm" and minimal["periodic"] == [] and minimal["randomize"] is None
    assert load(folder, minimal) == load(folder, base())


def test_mesh_cage_forms(folder):
    mesh = {"mesh": "meshes/bunny.off"}
    spec = load(folder, merged({"model": {**mesh, "repair": True}}, drop=["model.nurbs"]))
    assert spec.model.cage == CageSpec("box") and spec.model.repair
    spec = load(folder, merged({"model": {**mesh, "cage": "sphere"}}, drop=["model.nurbs"]))
    assert spec.model.cage.type == "sphere"
    spec = load(folder, merged({"model": {**mesh, "cage": {"type": "cylinder", "padding": 2,
                                                           "control_points": [4, 3, 2]}}}, drop=["model.nurbs"]))
    assert spec.model.cage == CageSpec("cylinder", None, 0, 2.0, (4, 3, 2))
    spec = load(folder, merged({"model": {**mesh, "cage": {"type": "box", "control_points": 5}}},
                               drop=["model.nurbs"]))
    assert spec.model.cage.control_points == (5, 5, 5)
    spec = load(folder, merged({"model": {**mesh, "cage": {"nurbs": "models/cage.json", "patch": 2}}},
                               drop=["model.nurbs"]))
    assert spec.model.cage.type == "nurbs" and spec.model.cage.patch == 2
    assert spec.model.cage.nurbs == (folder / "models" / "cage.json").resolve()
    assert load(folder, spec_to_dict(spec)) == spec


def test_builtin_and_shorthands(folder):
    spec = load(folder, merged({"model": {"builtin": {"type": "twisted-torus", "twist": 90}},
                                "periodic": "w", "randomize": {"amplitude": 0}}, drop=["model.nurbs"]))
    assert spec.model.builtin == {"type": "twisted-torus", "twist": 90}
    assert spec.periodic == (2,) and spec.randomize is None  # amplitude 0 = no randomization
    assert load(folder, merged({"randomize": {}})).randomize == RandomizeSpec(0, 0.25, 6)
    assert load(folder, merged({"model": {"builtin": "duck-shell"}}, drop=["model.nurbs"])).model.builtin == {
        "type": "duck-shell"}


def test_with_overrides(folder, monkeypatch):
    monkeypatch.chdir(folder)
    spec = load(folder, merged({"randomize": {"seed": 1}}))
    over = with_overrides(spec, output_dir="elsewhere", fmt="3mf", seed=9)
    assert over.output.directory == folder.resolve() / "elsewhere"
    assert over.output.format == "3mf" and over.randomize.seed == 9 and spec.randomize.seed == 1
    assert with_overrides(spec) == spec
    with pytest.raises(SpecError) as info:
        with_overrides(spec, fmt="obj", seed=-1)
    assert len(info.value.problems) == 2
    assert info.value.problems[0].startswith("output.format: ") and "expected one of: stl, 3mf" in str(info.value)
    assert "randomize.seed: too small (got -1" in str(info.value)


def test_load_spec_from_file(folder):
    path = folder / "spec.yaml"
    path.write_text(yaml.safe_dump(base()))
    assert load_spec(path).name == "t"


# ----------------------------------------------------------------------------------------------------
# One test per kind of mistake


def test_unknown_key_names_the_nearest_one(folder):
    p = only_problem(folder, merged({"model": {"unit": "mm"}}), "model.unit")
    assert "did you mean 'units'?" in p and "got 'unit'" in p and "expected one of: nurbs, patch" in p


def test_unknown_key_without_near_one_lists_the_accepted(folder):
    p = only_problem(folder, merged({"colour": "red"}), "colour")
    assert "did you mean" not in p and "expected one of: name, model, grid, splits" in p


def test_section_not_a_mapping(folder):
    p = only_problem(folder, merged({"joints": 5}), "joints")
    assert "not a mapping (got 5, expected a mapping with keys style, shape" in p


def test_missing_required_keys(folder):
    probs = problems_of(folder, {"splits": {"u": "uniform"}})
    assert [p.split(":")[0] for p in probs] == ["name", "model", "grid"]
    assert all("missing (got nothing, expected" in p for p in probs)


def test_boolean_for_an_integer(folder):
    p = only_problem(folder, "name: t\nmodel: {nurbs: models/vol.json, patch: yes}\ngrid: [2, 2, 2]\n",
                     "model.patch")
    assert "got true (a boolean" in p and "expected an integer >= 0" in p


def test_decimal_for_an_integer_seed(folder):
    p = only_problem(folder, merged({"randomize": {"seed": 7.0}}), "randomize.seed")
    assert "a decimal number where an integer belongs (got 7.0, expected an integer >= 0" in p


def test_not_an_integer(folder):
    p = only_problem(folder, merged({"randomize": {"seed": "seven"}}), "randomize.seed")
    assert "not an integer (got 'seven', expected an integer >= 0)" in p


def test_integer_too_small(folder):
    p = only_problem(folder, merged({"randomize": {"control_points": 3}}), "randomize.control_points")
    assert "too small (got 3, expected an integer >= 4)" in p
    p = only_problem(folder, merged({"grid": [2, 0, 2]}), "grid[1]")
    assert "(got 0, expected an integer >= 1)" in p


def test_not_a_number(folder):
    p = only_problem(folder, merged({"output": {"tolerance": "fine"}}), "output.tolerance")
    assert "not a number (got 'fine', expected a number > 0)" in p


def test_not_a_finite_number(folder):
    p = only_problem(folder, "name: t\nmodel: {nurbs: models/vol.json}\ngrid: [2, 2, 2]\n"
                             "randomize: {amplitude: .nan}\n", "randomize.amplitude")
    assert "not a finite number (got nan, expected a number >= 0)" in p


@pytest.mark.parametrize("changes, key, expected", [
    ({"randomize": {"amplitude": -1}}, "randomize.amplitude", "(got -1, expected a number >= 0)"),
    ({"output": {"tolerance": 0}}, "output.tolerance", "(got 0, expected a number > 0)"),
    ({"joints": {"radius": 0}}, "joints.radius", "(got 0, expected a number > 0, or nothing for the default)"),
    ({"joints": {"clearance": -0.1}}, "joints.clearance", "(got -0.1, expected a number >= 0)"),
    ({"output": {"plate": [250, -1]}}, "output.plate[1]", "(got -1, expected a number > 0)"),
    ({"model": {"size": -5}}, "model.size", "(got -5, expected a number > 0"),
])
def test_number_out_of_range(folder, changes, key, expected):
    p = only_problem(folder, merged(changes), key)
    assert "out of range " + expected in p


def test_not_a_boolean(folder):
    p = only_problem(folder, merged({"output": {"labels": 1}}), "output.labels")
    assert "not a boolean (got 1, expected true or false)" in p


def test_enum_unknown_value_lists_the_accepted(folder):
    p = only_problem(folder, merged({"joints": {"style": "pins"}}), "joints.style")
    assert "unknown value, did you mean 'pin'? (got 'pins', expected one of: pin, dowel, none)" in p
    p = only_problem(folder, merged({"model": {"units": "furlong"}}), "model.units")
    assert "expected one of: mm, cm, m, in" in p


def test_enum_given_a_non_text(folder):
    p = only_problem(folder, merged({"output": {"format": 3}}), "output.format")
    assert "not one of the accepted values (got 3, expected one of: stl, 3mf)" in p


def test_model_path_not_a_text(folder):
    p = only_problem(folder, merged({"model": {"nurbs": 5}}), "model.nurbs")
    assert "not a file path (got 5, expected the path of a NURBS volume" in p


def test_model_file_of_unsupported_type(folder):
    (folder / "models" / "vol.txt").write_text("")
    p = only_problem(folder, merged({"model": {"nurbs": "models/vol.txt"}}), "model.nurbs")
    assert "unsupported file type (got 'models/vol.txt', expected a NURBS volume ending in .json, .xml, .itd)" in p


def test_model_file_is_a_folder(folder):
    (folder / "models" / "dir.json").mkdir()
    p = only_problem(folder, merged({"model": {"nurbs": "models/dir.json"}}), "model.nurbs")
    assert "is a folder, not a file" in p


def test_model_file_not_found_names_the_resolved_path(folder):
    p = only_problem(folder, merged({"model": {"nurbs": "models/../models/nope.json"}}), "model.nurbs")
    resolved = str((folder / "models" / "nope.json").resolve())
    assert f"file not found (got {resolved!r}" in p and f"spec's folder {folder.resolve()}" in p


def test_name_not_a_text(folder):
    p = only_problem(folder, merged({"name": 123}), "name")
    assert "not a text (got 123, expected letters, digits" in p and 'quote it: "123"' in p


@pytest.mark.parametrize("bad", ["a/b", "..", "../escape", "x.y"])
def test_name_not_a_plain_file_name(folder, bad):
    p = only_problem(folder, merged({"name": bad}), "name")
    assert f"not a plain file name (got {bad!r}, expected letters, digits, '-' and '_' only" in p


def test_name_with_other_characters(folder):
    p = only_problem(folder, merged({"name": "my puzzle!"}), "name")
    assert "contains characters a name cannot have (got 'my puzzle!'" in p


def test_model_with_two_sources(folder):
    p = only_problem(folder, merged({"model": {"builtin": {"type": "duck-shell"}}}), "model")
    assert ("more than one model source (got nurbs and builtin, expected exactly one of nurbs, builtin, mesh, shell)"
            in p)


def test_model_with_no_source(folder):
    p = only_problem(folder, merged({"model": {"units": "mm"}}, drop=["model.nurbs"]), "model")
    assert "no model source (got none of them, expected exactly one of nurbs, builtin, mesh, shell)" in p


def test_patch_only_with_nurbs(folder):
    p = only_problem(folder, merged({"model": {"mesh": "meshes/bunny.off", "patch": 1}}, drop=["model.nurbs"]),
                     "model.patch")
    assert "only used with a NURBS file (got patch with mesh, expected model.patch only together with" in p


def test_cage_only_with_mesh(folder):
    p = only_problem(folder, merged({"model": {"cage": "box"}}), "model.cage")
    assert "only used with a mesh (got a cage with nurbs, expected model.cage only together with model.mesh)" in p


def test_repair_only_with_mesh(folder):
    p = only_problem(folder, merged({"model": {"repair": True}}), "model.repair")
    assert "only used with a mesh (got true with nurbs, expected model.repair only together with model.mesh)" in p


def test_builtin_problems(folder):
    def one(builtin, key):
        return only_problem(folder, merged({"model": {"builtin": builtin}}, drop=["model.nurbs"]), key)
    assert "not a mapping (got 5, expected a mapping such as" in one(5, "model.builtin")
    assert "missing (got nothing, expected the name of a built-in shape" in one({"twist": 9}, "model.builtin.type")
    assert "not a shape name (got 5" in one({"type": 5}, "model.builtin.type")
    assert "not a simple parameter (got a mapping" in one({"type": "x", "twist": {"a": 1}}, "model.builtin.twist")


def test_cage_problems(folder):
    def one(cage, key):
        return only_problem(folder, merged({"model": {"mesh": "meshes/bunny.off", "cage": cage}},
                                           drop=["model.nurbs"]), key)
    assert "not a cage (got 5, expected one of: box" in one(5, "model.cage")
    assert "unknown value, did you mean 'sphere'? (got 'spere'" in one("spere", "model.cage")
    assert "a NURBS cage takes no shape keys (got nurbs with padding" in one(
        {"nurbs": "models/cage.json", "padding": 1}, "model.cage")
    assert "only used with a NURBS cage (got 1" in one({"type": "box", "patch": 1}, "model.cage.patch")
    assert "missing (got nothing, expected one of: box, cylinder, sphere" in one({"padding": 1}, "model.cage.type")
    assert "too small (got 1, expected an integer >= 2)" in one({"type": "box", "control_points": [4, 1, 4]},
                                                               "model.cage.control_points[1]")
    assert "out of range (got -2, expected a number >= 0)" in one({"type": "box", "padding": -2},
                                                                  "model.cage.padding")


def test_grid_wrong_length_or_type(folder):
    p = only_problem(folder, merged({"grid": [2, 2]}), "grid")
    assert "wrong number of entries (got a list [2, 2], expected 3 integers [u, v, w], each >= 1)" in p
    p = only_problem(folder, merged({"grid": 4}), "grid")
    assert "a single number (got 4, expected 3 integers" in p
    p = only_problem(folder, merged({"grid": "2x2x2"}), "grid")
    assert "not a list (got '2x2x2', expected 3 integers" in p


def test_periodic_axis_problems(folder):
    probs = problems_of(folder, merged({"periodic": ["w", "x", 2, "w", None]}))
    assert probs == [
        "periodic[1]: unknown axis (got 'x', expected an axis name: u, v or w)",
        "periodic[2]: an axis number instead of its name (got 2, expected an axis name: u, v or w)",
        "periodic[3]: axis given twice (got 'w', expected each axis at most once)",
        "periodic[4]: not an axis name (got nothing, expected an axis name: u, v or w)",
    ]


def test_periodic_not_a_list(folder):
    p = only_problem(folder, merged({"periodic": {"w": True}}), "periodic")
    assert "not a list of axes (got a mapping" in p and "expected a list of axis names" in p


def test_splits_keyed_by_axis_name(folder):
    p = only_problem(folder, merged({"splits": {"z": "uniform"}}), "splits.z")
    assert "unknown key (got 'z', expected one of: u, v, w)" in p
    p = only_problem(folder, merged({"splits": ["uniform", "uniform", "knots"]}), "splits")
    assert "not a mapping (got a list" in p and "expected a mapping by axis" in p


def test_split_rule_not_understood(folder):
    p = only_problem(folder, merged({"splits": {"u": "knot"}}), "splits.u")
    assert "unknown value, did you mean 'knots'? (got 'knot', expected one of: uniform, knots, balanced)" in p
    p = only_problem(folder, merged({"splits": {"u": 0.5}}), "splits.u")
    assert "not a split rule (got 0.5, expected uniform, knots, balanced, or a list of 1 = grid[0] - 1" in p


def test_split_parameter_count(folder):
    p = only_problem(folder, merged({"splits": {"w": [0.5]}}), "splits.w")
    assert "wrong number of interior parameters (got 1 parameters [0.5], expected 2 = grid[2] - 1" in p


def test_split_parameters_not_increasing(folder):
    p = only_problem(folder, merged({"splits": {"w": [0.6, 0.6]}}), "splits.w")
    assert "not strictly increasing (got a list [0.6, 0.6], expected each parameter larger than the one before" in p


def test_split_parameter_not_a_number(folder):
    p = only_problem(folder, merged({"splits": {"w": [0.2, "half"]}}), "splits.w[1]")
    assert "not a number (got 'half', expected a number)" in p


def test_clearance_must_be_smaller_than_radius(folder):
    p = only_problem(folder, merged({"joints": {"radius": 1, "clearance": 1.5}}), "joints.clearance")
    assert "not smaller than the pin radius (got 1.5, expected >= 0 and < joints.radius = 1; or a radius > 1.5)" in p


def test_output_directory_problems(folder, monkeypatch):
    monkeypatch.chdir(folder)
    p = only_problem(folder, merged({"output": {"directory": 5}}), "output.directory")
    assert "not a folder path (got 5, expected a folder path" in p
    (folder / "afile").write_text("")
    p = only_problem(folder, merged({"output": {"directory": "afile"}}), "output.directory")
    assert "is a file, not a folder" in p


def test_plate_not_two_numbers(folder):
    p = only_problem(folder, merged({"output": {"plate": [250]}}), "output.plate")
    assert "not a width and a depth (got a list [250], expected 2 numbers [x, y] in mm, each > 0)" in p


def test_spacing_leaves_no_room(folder):
    p = only_problem(folder, merged({"output": {"plate": [100, 50], "spacing": 30}}), "output.spacing")
    assert "leaves no room on the plate (got 30, expected less than half the plate's smaller side, < 25)" in p


def test_python_tag_constructs_nothing(folder):
    target = folder / "pwned"
    text = f"name: t\nmodel: !!python/object/apply:os.mkdir [{target}]\ngrid: [2, 2, 2]\n"
    p = only_problem(folder, text, "spec")
    assert not target.exists()
    assert "YAML tag not allowed at line 2, column 8 (got '!!python/object/apply:os.mkdir'" in p


def test_invalid_yaml_names_the_line(folder):
    p = only_problem(folder, "name: t\ngrid: [2, 2\nmodel: {}\n", "spec")
    assert re.search(r"not valid YAML at line \d+, column \d+ \(got .+, expected a YAML mapping\)", p)


def test_impossible_date(folder):
    p = only_problem(folder, "name: 2020-13-45\n", "spec")
    assert "a value shaped like a date is not a real date (got 'month must be in 1..12', expected a valid date" in p


def test_key_given_twice(folder):
    text = "name: t\nmodel: {nurbs: models/vol.json}\ngrid: [2, 2, 2]\ngrid: [3, 3, 3]\n"
    p = only_problem(folder, text, "grid")
    assert "given more than once (got lines 3, 4, expected each key once)" in p


def test_empty_file(folder):
    p = only_problem(folder, "# only a comment\n", "spec")
    assert "the file is empty (got nothing, expected a mapping" in p


def test_top_level_not_a_mapping(folder):
    p = only_problem(folder, "- name: t\n", "spec")
    assert "the top level is not a mapping (got a list" in p and "expected a mapping with keys name, model" in p


def test_spec_file_not_found(folder):
    with pytest.raises(SpecError) as info:
        load_spec(folder / "missing.yaml")
    assert info.value.problems[0].startswith("spec: file not found (got ")
    assert str((folder / "missing.yaml").resolve()) in info.value.problems[0]


def test_spec_file_is_a_folder(folder):
    with pytest.raises(SpecError, match=r"spec: is a folder \(got .*, expected a YAML file\)"):
        load_spec(folder / "models")


def test_spec_file_not_text(folder):
    path = folder / "binary.yaml"
    path.write_bytes(b"name: \xff\xfe\n")
    with pytest.raises(SpecError, match=r"spec: not a text file \(got undecodable byte at offset 6, expected UTF-8"):
        load_spec(path)


def test_spec_file_unreadable(folder, monkeypatch):
    # chmod 0 does not stop root (CI runs as root), so the read itself fails as it would without permission
    path = folder / "locked.yaml"
    path.write_text("name: t\n")
    real = Path.read_text

    def denied(self, *args, **kwargs):
        if self == path:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "read_text", denied)
    with pytest.raises(SpecError, match=r"spec: cannot read the file \(got Permission denied, expected a readable YAML "
                                        r"file\)"):
        load_spec(path)


def test_every_mistake_is_reported_at_once(folder):
    data = {"name": "a b", "model": {"nurbs": "models/vol.json", "unit": "mm"}, "grid": [2, 2.5, 0],
            "randomize": {"seed": True, "amplitude": -1}, "joints": {"style": "pins"},
            "output": {"format": "obj", "tolerance": 0}}
    probs = problems_of(folder, data)
    keys = [p.split(":")[0] for p in probs]
    assert keys == ["name", "model.unit", "grid[1]", "grid[2]", "randomize.seed", "randomize.amplitude",
                    "joints.style", "output.format", "output.tolerance"]
    with pytest.raises(SpecError) as info:
        load(folder, data)
    assert "9 problems" in str(info.value) and str(folder / "spec.yaml") in str(info.value)


# ----------------------------------------------------------------------------------------------------
# Garbage never escapes as anything but SpecError

_SECTION_KEYS = {
    "model": ["nurbs", "patch", "builtin", "mesh", "cage", "units", "size", "repair", "type", "padding",
              "control_points"],
    "splits": ["u", "v", "w"], "randomize": ["seed", "amplitude", "control_points"],
    "joints": ["style", "shape", "radius", "length", "clearance", "axial_clearance", "space", "min_radius",
               "min_length", "allow"],
    "output": ["directory", "format", "tolerance", "plate", "spacing", "labels"],
}
_scalars = (st.none() | st.booleans() | st.integers(-3, 10) | st.floats(allow_nan=True, allow_infinity=True)
            | st.sampled_from(["", "w", "box", "pin", "stl", "models/vol.json", "meshes/bunny.off", "../x", "t"])
            | st.text(max_size=6))
_values = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
    st.sampled_from(sum(_SECTION_KEYS.values(), [])) | st.text(max_size=3) | st.integers(), inner, max_size=3),
    max_leaves=8)
_sections = {key: _values | st.dictionaries(st.sampled_from(keys), _values, max_size=len(keys))
             for key, keys in _SECTION_KEYS.items()}
_garbage = st.fixed_dictionaries({}, optional={
    "name": _values, "grid": _values | st.lists(_scalars, min_size=3, max_size=3), "periodic": _values,
    "junk": _values, **_sections})


@pytest.mark.slow
@settings(max_examples=80, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(_garbage)
def test_garbage_mappings_raise_only_spec_errors(folder, garbage):
    data = {**base(), **garbage}  # mostly valid, so the garbage reaches the deeper checks
    try:
        spec = load(folder, data)
    except SpecError as exc:
        assert exc.problems and all(PROBLEM_RE.match(p) for p in exc.problems), exc.problems
    else:
        assert isinstance(spec, Spec)
        json.dumps(spec_to_dict(spec))


@settings(max_examples=100, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.text(alphabet=st.sampled_from(list("ab:-[]{}!&*|>'\"#%@`\n ,?.0123456789")), max_size=40))
def test_garbage_text_raises_only_spec_errors(folder, text):
    try:
        load(folder, text)
    except SpecError as exc:
        assert exc.problems


def test_a_builtin_parameter_out_of_range_is_a_spec_problem_of_the_file(folder):
    # checked while the spec is read, not when the model is built, so it names the spec file and comes with the
    # spec's other problems in one round
    data = {"name": "t", "model": {"builtin": {"type": "twisted-torus", "minor_radius": -3}}, "grid": [2, 0, 8]}
    with pytest.raises(SpecError) as info:
        load(folder, data)
    assert str(info.value).startswith(f"{folder / 'spec.yaml'}: 2 problems: ")
    assert "model.builtin.minor_radius: must be positive (got -3, expected > 0)" in info.value.problems
    assert any(p.startswith("grid[1]: ") for p in info.value.problems)
