"""A real slicer as a test: PrusaSlicer slices every plate of a build, without supports, as volpuzzle laid it out.

Usage: python scripts/slicer_check.py [--config slicer/prusaslicer.ini] OUT_DIR...
Each plate must slice with exit 0 and no warning or error from the slicer (an object with no extrusions in the first
layer, empty layers, objects off the bed, a non-manifold mesh). Prints per build the print time of each plate and what
report.json says of printability: pieces under 10 mm^2 on the bed, pins within 30 degrees of vertical, unlabelled
pieces. Exit 0 when every plate passes.
"""

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CONFIG = REPO / "slicer" / "prusaslicer.ini"
_WARNING = re.compile(r"warning|error|empty layer|no extrusions|outside|not manifold|failed", re.I)
_TIME = re.compile(r"^; estimated printing time \(normal mode\) = (.+)$", re.M)


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


def slice_plate(plate, config):
    """Slice one plate -> (ok, print time or None, complaints [lines])."""
    with tempfile.TemporaryDirectory() as tmp:
        gcode = Path(tmp) / "plate.gcode"
        run = subprocess.run(["prusa-slicer", "--export-gcode", "--load", str(config), "--dont-arrange",
                              "--output", str(gcode), str(plate)], capture_output=True, text=True, timeout=3600)
        lines = [ln.strip() for ln in (run.stdout + "\n" + run.stderr).splitlines() if ln.strip()]
        complaints = [ln for ln in lines if _WARNING.search(ln)]
        text = gcode.read_text(errors="replace") if gcode.exists() else ""
        found = _TIME.search(text)
        ok = run.returncode == 0 and bool(text) and not complaints
        if run.returncode != 0 and not complaints:
            complaints = lines[-3:] or [f"exit {run.returncode}"]
        return ok, found.group(1) if found else None, complaints


def summary(directory):
    """What report.json says of printability -> one line."""
    report = json.loads((directory / "report.json").read_text(encoding="utf-8"))
    pieces = report.get("pieces") or []
    prints = [p.get("print") or {} for p in pieces]
    low = [p["id"] for p, x in zip(pieces, prints, strict=True) if (x.get("bed_contact_mm2") or 0) < 10]
    pins, up = sum(x.get("pins") or 0 for x in prints), sum(x.get("pins_up") or 0 for x in prints)
    unlabelled = [p["id"] for p in pieces if not (p.get("label") or {}).get("text")]
    return (f"{len(pieces)} pieces; under 10 mm^2 on the bed: {len(low)}{' ' + ', '.join(low) if low else ''}; "
            f"pins within 30 deg of vertical: {up} of {pins}; unlabelled: {len(unlabelled)}"
            f"{' ' + ', '.join(unlabelled) if unlabelled else ''}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(CONFIG))
    ap.add_argument("directories", nargs="+")
    args = ap.parse_args(argv)
    if shutil.which("prusa-slicer") is None:
        print("prusa-slicer is not installed (make slicer-check installs it with apt-get)", file=sys.stderr)
        return 2
    bad = 0
    for d in map(Path, args.directories):
        plates = sorted((d / "plates").glob("*.3mf"))
        if not plates:
            print(f"FAIL {d}: no plates to slice", file=sys.stderr)
            bad += 1
            continue
        for plate in plates:
            # every object of the plate a closed manifold, as the slicer reads it
            for b in info(plate):
                if b.get("manifold") != "yes" or int(b.get("open_edges", "0") or 0):
                    bad += 1
                    print(f"FAIL {d.name}/{plate.relative_to(d)}: an object is not manifold ({b})")
            ok, when, complaints = slice_plate(plate, args.config)
            bad += not ok
            print(f"{'ok  ' if ok else 'FAIL'} {d.name}/{plate.relative_to(d)}: print time {when or '?'}"
                  + ("" if ok else " — " + " | ".join(complaints[:4])))
        print(f"     {d.name}: {summary(d)}")
    print(f"{bad} plate(s) failed" if bad else "every plate sliced without a warning")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
