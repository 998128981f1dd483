"""A real slicer accepts the pieces and plates (runs when PrusaSlicer is installed: `make slicer-check` installs it)."""

import shutil
import subprocess
import sys

import pytest
from conftest import REPO
from helpers_build import write_spec

import volpuzzle


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("prusa-slicer") is None,
                    reason="prusa-slicer is not installed; `make slicer-check` installs it from Debian's packages")
def test_prusaslicer_slices_every_plate_without_supports_or_warnings(tmp_path):
    spec = write_spec(tmp_path, {"name": "slicer", "model": {"builtin": {"type": "quarter-torus"}}, "grid": [2, 1, 1],
                                 "output": {"directory": str(tmp_path / "out"), "tolerance": 0.3}})
    volpuzzle.build(spec, jobs=1)
    run = subprocess.run([sys.executable, str(REPO / "scripts" / "slicer_check.py"), str(tmp_path / "out")],
                         capture_output=True, text=True, timeout=1200)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "every plate sliced without a warning" in run.stdout
    assert "out/plates/plate-01.3mf: print time" in run.stdout
    assert "under 10 mm^2 on the bed: 0;" in run.stdout and "unlabelled: 0" in run.stdout


def _script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("slicer_check", REPO / "scripts" / "slicer_check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_support_share_sums_extrusion_by_type_from_the_gcode():
    sc = _script()
    gcode = "\n".join([
        "M82 ; absolute E", "G92 E0", ";TYPE:Perimeter", "G1 X10 Y0 E2.0", "G1 X20 Y0 E5.0",
        "G1 E4.2 F2100 ; retract", "G1 X25 Y5", "G1 E5.0 ; undo the retraction", ";TYPE:Support material",
        "G1 X30 Y5 E6.5", "G92 E0", ";TYPE:Support material interface", "G1 X31 Y5 E0.5",
        ";TYPE:External perimeter", "M83 ; relative from here", "G1 X40 Y5 E1.0", "G1 X41 Y5 E-0.8", "G1 E0.8",
    ])
    used = sc.extrusion_by_type(gcode)
    assert used == {"Perimeter": 5.0, "Support material": 1.5, "Support material interface": 0.5,
                    "External perimeter": 1.0}
    assert sc.seconds("1d 2h 3m 4s") == 93784 and sc.seconds("59m 7s") == 3547 and sc.seconds(None) is None
    assert sc.hours(4 * 3600 + 36 * 60) == "4 h 36 m" and sc.hours(59 * 60) == "59 m"
    f = {"pieces": 3, "low": ["p0"], "pins": 4, "pins_up": 1, "unlabelled": []}
    assert sc.table([("gear", 3600, 0.2, f)]).splitlines()[-1] == "| gear | 1 h 00 m | 20.0 % | 1 | 1 / 4 | 0 / 3 |"
