"""A real slicer as a test: PrusaSlicer slices every plate of a build, without supports, as volpuzzle laid it out.

Usage: python scripts/slicer_check.py [--config slicer/prusaslicer.ini] [--support-share] OUT_DIR...
Each plate must slice with exit 0 and no warning or error from the slicer (an object with no extrusions in the first
layer, empty layers, objects off the bed, a non-manifold mesh). Prints per build the print time of each plate and what
report.json says of printability: pieces under 10 mm^2 on the bed, pins within 30 degrees of vertical, unlabelled
pieces. Exit 0 when every plate passes.

--support-share slices every plate a second time with automatic supports on and measures, from that G-code, the share
of the extruded filament that goes into support (`;TYPE:Support material` and `;TYPE:Support material interface`),
then prints one Markdown table: per build the print time without supports, the support share with them, pieces under
10 mm^2 on the bed, pins within 30 degrees of vertical and unlabelled pieces.
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
_SUPPORT_TYPES = ("Support material", "Support material interface")
_SUPPORTS_ON = ["--support-material", "--support-material-auto"]
_E = re.compile(r"\bE(-?[0-9.]+)")
_XY = re.compile(r"\b[XY]-?[0-9.]")


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


def _run_slicer(plate, config, extra=()):
    """Slice one plate -> (exit code, G-code text or "", the slicer's output lines)."""
    with tempfile.TemporaryDirectory() as tmp:
        gcode = Path(tmp) / "plate.gcode"
        run = subprocess.run(["prusa-slicer", "--export-gcode", "--load", str(config), *extra, "--dont-arrange",
                              "--output", str(gcode), str(plate)], capture_output=True, text=True, timeout=3600)
        lines = [ln.strip() for ln in (run.stdout + "\n" + run.stderr).splitlines() if ln.strip()]
        return run.returncode, gcode.read_text(errors="replace") if gcode.exists() else "", lines


def slice_plate(plate, config):
    """Slice one plate -> (ok, print time or None, complaints [lines])."""
    code, text, lines = _run_slicer(plate, config)
    complaints = [ln for ln in lines if _WARNING.search(ln)]
    found = _TIME.search(text)
    ok = code == 0 and bool(text) and not complaints
    if code != 0 and not complaints:
        complaints = lines[-3:] or [f"exit {code}"]
    return ok, found.group(1) if found else None, complaints


def extrusion_by_type(gcode):
    """mm of filament pushed per `;TYPE:` of a G-code text -> {type: mm}. Only moves that travel in X or Y while
    extruding count (a retraction and its undo add nothing); absolute E (reset by G92) or relative (M83)."""
    used, kind, e, relative = {}, None, 0.0, False
    for line in gcode.splitlines():
        if line.startswith(";TYPE:"):
            kind = line[6:].strip()
            continue
        code = line.split(";", 1)[0].strip()
        if not code:
            continue
        if code.startswith("M83"):
            relative = True
        elif code.startswith("M82"):
            relative = False
        elif code.startswith("G92"):
            m = _E.search(code)
            if m:
                e = float(m.group(1))
        elif code.startswith(("G1 ", "G0 ", "G1\t", "G2 ", "G3 ")):
            m = _E.search(code)
            if not m:
                continue
            value = float(m.group(1))
            delta = value if relative else value - e
            if not relative:
                e = value
            if delta > 0 and _XY.search(code) and kind is not None:
                used[kind] = used.get(kind, 0.0) + delta
    return used


def support_share(plate, config):
    """The plate sliced with automatic supports on -> (share of the extruded filament in support (0..1) or None when
    the slicer failed, mm of support filament, mm of all filament)."""
    code, text, _ = _run_slicer(plate, config, _SUPPORTS_ON)
    if code != 0 or not text:
        return None, 0.0, 0.0
    used = extrusion_by_type(text)
    total = sum(used.values())
    support = sum(used.get(k, 0.0) for k in _SUPPORT_TYPES)
    return (support / total if total > 0 else 0.0), support, total


def seconds(when):
    """PrusaSlicer's '1d 2h 3m 4s' -> seconds (None stays None)."""
    if not when:
        return None
    units = {"d": 86400, "h": 3600, "m": 60, "s": 1}
    return sum(int(n) * units[u] for n, u in re.findall(r"(\d+)\s*([dhms])", when))


def hours(total):
    """seconds -> '4 h 36 m'."""
    if total is None:
        return "?"
    h, m = divmod(int(round(total / 60.0)), 60)
    return f"{h} h {m:02d} m" if h else f"{m} m"


def figures(directory):
    """What report.json says of printability -> dict: pieces, low (ids under 10 mm^2 on the bed), pins, pins_up,
    unlabelled (ids)."""
    report = json.loads((directory / "report.json").read_text(encoding="utf-8"))
    pieces = report.get("pieces") or []
    prints = [p.get("print") or {} for p in pieces]
    return {"pieces": len(pieces),
            "low": [p["id"] for p, x in zip(pieces, prints, strict=True) if (x.get("bed_contact_mm2") or 0) < 10],
            "pins": sum(x.get("pins") or 0 for x in prints), "pins_up": sum(x.get("pins_up") or 0 for x in prints),
            "unlabelled": [p["id"] for p in pieces if not (p.get("label") or {}).get("text")]}


def summary(directory):
    """What report.json says of printability -> one line."""
    f = figures(directory)
    low, unlabelled = f["low"], f["unlabelled"]
    return (f"{f['pieces']} pieces; under 10 mm^2 on the bed: {len(low)}{' ' + ', '.join(low) if low else ''}; "
            f"pins within 30 deg of vertical: {f['pins_up']} of {f['pins']}; unlabelled: {len(unlabelled)}"
            f"{' ' + ', '.join(unlabelled) if unlabelled else ''}")


def table(rows):
    """Markdown table of the per-build figures: rows of (name, print seconds or None, support share or None,
    figures dict)."""
    out = ["| spec | print time without supports | support share when on | pieces < 10 mm² on the bed | "
           "pins within 30° of vertical | unlabelled |", "|---|---|---|---|---|---|"]
    for name, total, share, f in rows:
        out.append(f"| {name} | {hours(total)} | {'?' if share is None else f'{100 * share:.1f} %'} | "
                   f"{len(f['low'])} | {f['pins_up']} / {f['pins']} | {len(f['unlabelled'])} / {f['pieces']} |")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(CONFIG))
    ap.add_argument("--support-share", action="store_true",
                    help="slice each plate again with supports on and print the table of figures")
    ap.add_argument("directories", nargs="+")
    args = ap.parse_args(argv)
    if shutil.which("prusa-slicer") is None:
        print("prusa-slicer is not installed (make slicer-check installs it with apt-get)", file=sys.stderr)
        return 2
    bad, rows = 0, []
    for d in map(Path, args.directories):
        plates = sorted((d / "plates").glob("*.3mf"))
        if not plates:
            print(f"FAIL {d}: no plates to slice", file=sys.stderr)
            bad += 1
            continue
        total, support, extruded = 0, 0.0, 0.0
        for plate in plates:
            # every object of the plate a closed manifold, as the slicer reads it
            for b in info(plate):
                if b.get("manifold") != "yes" or int(b.get("open_edges", "0") or 0):
                    bad += 1
                    print(f"FAIL {d.name}/{plate.relative_to(d)}: an object is not manifold ({b})")
            ok, when, complaints = slice_plate(plate, args.config)
            bad += not ok
            total = None if total is None or seconds(when) is None else total + seconds(when)
            line = (f"{'ok  ' if ok else 'FAIL'} {d.name}/{plate.relative_to(d)}: print time {when or '?'}"
                    + ("" if ok else " — " + " | ".join(complaints[:4])))
            if args.support_share:
                share, mm, all_mm = support_share(plate, args.config)
                if share is None:
                    support = None
                    line += "; with supports: the slicer failed"
                else:
                    line += f"; support share with supports on {100 * share:.1f} %"
                    if support is not None:
                        support, extruded = support + mm, extruded + all_mm
            print(line)
        print(f"     {d.name}: {summary(d)}")
        if args.support_share:
            # the share of the whole build: support filament over all filament, summed over its plates
            share = None if support is None else (support / extruded if extruded > 0 else 0.0)
            rows.append((d.name, total, share, figures(d)))
    print(f"{bad} plate(s) failed" if bad else "every plate sliced without a warning")
    if rows:
        print()
        print(table(rows))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
