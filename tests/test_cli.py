"""The command line through click's CliRunner: one-line errors, exit codes, no tracebacks, no half-written output."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import DATA
from helpers_build import write_spec

from volpuzzle.cli import cli


def run(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result


def assert_one_line_error(result):
    assert result.exit_code == 1, result.output
    text = result.output.strip()
    assert "Traceback" not in text
    assert text.startswith("error: ")
    assert len(text.splitlines()) == 1


def spec_dict(tmp_path, **over):
    d = {"name": "t", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [1, 1, 2],
         "output": {"directory": str(tmp_path / "out"), "tolerance": 0.5}}
    d.update(over)
    return d


def test_info_json_on_gismo_file():
    result = run("info", DATA / "gismo_cylinder.xml", "--json")
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    for key in ("degrees", "control_points", "domain", "periodic", "bbox", "volume", "handedness", "jacobian_min",
                "jacobian_max"):
        assert key in data
    assert data["handedness"] == "left"
    assert data["volume"] == pytest.approx(9.424778, rel=1e-6)


def test_info_text():
    result = run("info", DATA / "gismo_twisted_pipe.xml")
    assert result.exit_code == 0, result.output
    lines = dict(line.split(None, 1) for line in result.output.splitlines() if line.strip() and " " in line)
    assert lines["degrees"].split() == ["u", "2", "v", "2", "w", "2"]
    assert lines["handedness"].strip() == "right"
    # 2.075661 in REFERENCE_VALUES.tsv, from an independent implementation
    assert float(lines["volume"].split()[0]) == pytest.approx(2.075661, rel=1e-5)


def test_info_bad_model_one_line():
    result = run("info", DATA / "gismo_thbcube.xml")
    assert_one_line_error(result)
    assert "Geometry type 'THBSpline3' is not supported" in result.output


def test_info_missing_file():
    assert_one_line_error(run("info", "does/not/exist.json"))


def test_validate_ok(tmp_path):
    result = run("validate", write_spec(tmp_path, spec_dict(tmp_path)))
    assert result.exit_code == 0, result.output
    assert "valid" in result.output
    assert not (tmp_path / "out").exists()


def test_validate_lists_every_mistake(tmp_path):
    bad = spec_dict(tmp_path, grid=[0, 1, 2], gird=3)
    bad["output"]["tolerance"] = -1
    result = run("validate", write_spec(tmp_path, bad))
    assert_one_line_error(result)
    for part in ("grid", "gird", "output.tolerance"):
        assert part in result.output


def test_yaml_python_tag_constructs_nothing(tmp_path):
    marker = tmp_path / "pwned"
    spec = tmp_path / "spec.yaml"
    spec.write_text(f"name: !!python/object/apply:os.system ['touch {marker}']\ngrid: [1,1,1]\n")
    result = run("validate", spec)
    assert_one_line_error(result)
    assert not marker.exists()


def test_build_refuses_existing_folder_without_force(tmp_path):
    spec = write_spec(tmp_path, spec_dict(tmp_path))
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    result = run("build", spec, "--jobs", "1")
    assert_one_line_error(result)
    assert "--force" in result.output
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


@pytest.mark.slow
def test_build_then_check(tmp_path):
    spec = write_spec(tmp_path, spec_dict(tmp_path))
    result = run("build", spec, "--jobs", "1")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "out" / "report.json").exists()
    assert run("check", tmp_path / "out").exit_code == 0


def test_folding_model_refused_without_output(tmp_path):
    from volpuzzle.io import save_model
    from volpuzzle.spline import Volume

    g = np.linspace(0, 10, 4)
    cp = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1)
    # Drags an interior point far past its neighbours: dx/du >= 10 - 90 * max|B1'| * B1(v) * B1(w) < 0 near it.
    cp[1, 1, 1, 0] = 100.0
    k = [0, 0, 0, 0, 1, 1, 1, 1]
    save_model(Volume((3, 3, 3), (k, k, k), cp), tmp_path / "fold.json")
    spec = write_spec(tmp_path, spec_dict(tmp_path, model={"nurbs": "fold.json"}))
    result = run("build", spec, "--jobs", "1")
    assert_one_line_error(result)
    assert "fold" in result.output
    assert not (tmp_path / "out").exists()


def test_folding_model_message_names_the_file(tmp_path):
    from volpuzzle.io import save_model
    from volpuzzle.spline import Volume

    g = np.linspace(0, 10, 4)
    cp = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1)
    cp[1, 1, 1, 0] = 100.0  # folds, as in test_folding_model_refused_without_output
    k = [0, 0, 0, 0, 1, 1, 1, 1]
    save_model(Volume((3, 3, 3), (k, k, k), cp), tmp_path / "fold.json")
    spec = write_spec(tmp_path, spec_dict(tmp_path, model={"nurbs": "fold.json"}))
    result = run("validate", spec)
    assert_one_line_error(result)
    # the user has to know which file to mend: the key and the path come before the place of the fold
    assert result.output.startswith(f"error: model.nurbs: {tmp_path / 'fold.json'}: model folds")


def test_bad_model_file_in_spec(tmp_path):
    spec = write_spec(tmp_path, spec_dict(tmp_path, model={"nurbs": str(DATA / "gismo_thbcube.xml")}))
    result = run("build", spec)
    assert_one_line_error(result)
    assert "Geometry type 'THBSpline3' is not supported" in result.output
    assert not (tmp_path / "out").exists()


def test_amplitude_that_folds_via_cli(tmp_path):
    spec = write_spec(tmp_path, spec_dict(tmp_path, randomize={"seed": 1, "amplitude": 5.0, "control_points": 5}))
    result = run("build", spec, "--jobs", "1")
    assert_one_line_error(result)
    assert "amplitude" in result.output
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_the_command_leaves_at_once_after_a_build_with_its_output_and_message_whole(tmp_path):
    # volpuzzle build, as the command, skips the interpreter's teardown (cli._leave_at_once): the message is still
    # flushed, the exit status 0, and nothing (the pool, its semaphores) reported left behind
    import subprocess
    import sys

    from helpers_build import example_spec

    spec = example_spec("twisted-torus", tmp_path, tolerance=0.5)
    run = subprocess.run([sys.executable, "-m", "volpuzzle.cli", "build", str(spec), "--jobs", "2"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("built 32 pieces"), run.stdout
    assert "leaked" not in run.stderr and "Traceback" not in run.stderr, run.stderr
    assert json.loads((tmp_path / "out" / "twisted-torus" / "report.json").read_text())["pieces"]


# --- the progress line never swallows a warning or the last message ------------------------------------------------
def test_a_warning_and_the_final_message_start_lines_of_their_own_after_a_progress_line(capsys):
    # on a terminal, a stop showed as "joint ...terminated" and a warning as "compose 32/32 p1-1-7warning: ..."
    from volpuzzle import cli as cli_mod
    from volpuzzle.errors import SpecError
    from volpuzzle.progress import Progress, warn

    shown = Progress(enabled=True)

    def failing():
        shown.stage("compose")
        shown.piece(3, 8, "p0-1-0")
        warn("output.face_clearance: not applied")
        shown.stage("label")
        raise SpecError("grid: got [2, 0, 1], expected whole numbers >= 1")

    with pytest.raises(SystemExit) as e:
        cli_mod._run(failing)
    assert e.value.code == 1
    err = capsys.readouterr().err
    # each message follows a clear of the line ("\r\033[K"), and ends with its own newline
    assert err == ("\r\033[Kcompose ...\r\033[Kcompose 3/8 p0-1-0\r\033[Kwarning: output.face_clearance: not applied\n"
                   "\r\033[Klabel ...\r\033[Kerror: grid: got [2, 0, 1], expected whole numbers >= 1\n")
    # after a line was ended nothing more is cleared: output without a progress line stays as it was
    warn("alone")
    assert capsys.readouterr().err == "warning: alone\n"


_WHAT_INSTALL_SAW = """
import sys
from volpuzzle import cli, stop
original = stop.install
def install():
    heavy = [m for m in ("volpuzzle.pipeline", "volpuzzle.check", "volpuzzle.batch", "volpuzzle.io", "numpy")
             if m in sys.modules]
    print("loaded when the stop was installed:", heavy, file=sys.stderr)
    return original()
stop.install = install
sys.argv = ["volpuzzle"] + sys.argv[1:]
cli.main()
"""


@pytest.mark.parametrize("command", [["build", "missing.yaml"], ["validate", "missing.yaml"], ["check", "missing"],
                                     ["info", "missing.itd"], ["batch", "missing.yaml"]])
def test_every_command_imports_its_stages_after_ctrl_c_is_handled(tmp_path, command):
    # the stage modules take half a second to import: a Ctrl-C then must be "interrupted", not a traceback
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", _WHAT_INSTALL_SAW, *command], capture_output=True, text=True,
                         cwd=tmp_path, timeout=120)
    assert run.returncode == 1, run.stderr
    assert "loaded when the stop was installed: []" in run.stderr, run.stderr
