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
