"""A real slicer as a test: PrusaSlicer must call every piece and plate of a build manifold, and slice a plate.

Usage: python scripts/slicer_check.py OUT_DIR   (exit 0 when every file passes; prints the slicer's verdicts)
"""

import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path


def info(path):
    """PrusaSlicer's --info blocks for one file -> list of dicts (one per object)."""
    out = subprocess.run(["prusa-slicer", "--info", str(path)], capture_output=True, text=True, timeout=600)
    blocks, cur = [], None
    for line in out.stdout.splitlines():
        if line.startswith("[") and line.endswith("]"):
            cur = {}
            blocks.append(cur)
        elif cur is not None and "=" in line:
            k, v = (s.strip() for s in line.split("=", 1))
            cur[k] = v
    if out.returncode != 0 or not blocks:
        raise RuntimeError(f"{path}: prusa-slicer --info failed (exit {out.returncode}): {out.stderr[-500:]}")
    return blocks


def main(directory):
    if shutil.which("prusa-slicer") is None:
        print("prusa-slicer is not installed (make slicer-check installs it with apt-get)", file=sys.stderr)
        return 2
    directory = Path(directory)
    files = sorted((directory / "pieces").glob("*")) + sorted((directory / "plates").glob("*.3mf"))
    if not files:
        print(f"{directory}: no pieces or plates to check", file=sys.stderr)
        return 1
    bad = 0
    for f in files:
        for b in info(f):
            ok = b.get("manifold") == "yes" and int(b.get("open_edges", "0") or 0) == 0
            bad += not ok
            print(f"{'ok  ' if ok else 'FAIL'} {f.relative_to(directory)}: manifold = {b.get('manifold')}, "
                  f"facets = {b.get('number_of_facets')}, volume = {b.get('volume')}"
                  + ("" if ok else f", open_edges = {b.get('open_edges')}"))
    plate = sorted((directory / "plates").glob("*.3mf"))[:1]
    if plate:
        with tempfile.TemporaryDirectory() as tmp:
            gcode = Path(tmp) / "plate.gcode"
            run = subprocess.run(["prusa-slicer", "--export-gcode", str(plate[0]), "--output", str(gcode)],
                                 capture_output=True, text=True, timeout=1200)
            size = gcode.stat().st_size if gcode.exists() else 0
            layers = len(re.findall(r"^;LAYER_CHANGE", gcode.read_text(), re.M)) if size else 0
            ok = run.returncode == 0 and size > 0
            bad += not ok
            print(f"{'ok  ' if ok else 'FAIL'} sliced {plate[0].relative_to(directory)}: {size / 1e6:.1f} MB G-code, "
                  f"{layers} layers")
    print(f"{len(files)} files checked, {bad} failed")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "out/quarter-torus"))
