"""The export stage: piece files, the assembled puzzle, report.json and report.md, written atomically.

Everything is written into a hidden temporary folder beside the target and renamed into place at the
end, so a failed build leaves nothing half-written, and an existing output is only replaced with force.
"""

from __future__ import annotations

import colorsys
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from json.encoder import encode_basestring_ascii
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import stop
from .errors import ExportError, VolpuzzleError
from .io.threemf import DEFAULT_ACCENT, write_3mf
from .workers import Remote

if TYPE_CHECKING:  # trimesh (~1.5 s to import) loads where a mesh is made: build() reads check_target from here
    import trimesh  # before it starts the workers, which are meant to start while this process loads

__all__ = ["write_build", "check_target", "piece_colors", "report_piece_entry", "clean_json", "render_report_md",
           "dumps_report", "FORMATS", "MARKER", "spec_inputs", "remove_stale_temporaries",
           "render_instructions_html", "assembly_sentences"]

FORMATS = ("stl", "3mf")
# Every folder volpuzzle writes holds this file; --force replaces only folders that do (a report.json alone proves
# nothing: anyone's folder may hold one). While a build runs, its temporary folder's marker names the process, so
# a later build can tell a temporary folder left by a killed build from one a running build still writes.
MARKER = ".volpuzzle"
_MARKER_KIND = "volpuzzle-output"
# Significant digits kept for floats in report.json: far below print resolution, free of 0.30000000000000004.
_DIGITS = 9


def piece_colors(n: int) -> np.ndarray:
    """(n, 3) uint8 distinct, pleasant colours, the same for the same n.

    Hues step by the golden angle so neighbours in id order differ strongly; lightness and saturation
    cycle through three levels so that large puzzles still tell pieces apart.
    """
    golden = (math.sqrt(5.0) - 1.0) / 2.0
    out = np.zeros((max(int(n), 0), 3), dtype=np.uint8)
    for k in range(len(out)):
        hue = (0.08 + k * golden) % 1.0
        light = (0.58, 0.48, 0.68)[k % 3]
        sat = (0.62, 0.72, 0.52)[(k // 3) % 3]
        out[k] = np.round(np.array(colorsys.hls_to_rgb(hue, light, sat)) * 255.0)
    return out


def _id_mesh(piece):
    """(id, trimesh) of a compose.Piece or an (id, mesh) pair."""
    if isinstance(piece, (tuple, list)):
        return str(piece[0]), piece[1]
    return str(piece.id), piece.mesh


def _cell(piece, pid):
    cell = getattr(piece, "cell", None)
    if cell is None and pid.startswith("p"):
        try:
            cell = tuple(int(x) for x in pid[1:].split("-"))
        except ValueError:
            cell = None
    return None if cell is None else [int(x) for x in cell]


def report_piece_entry(piece, file) -> dict:
    """A piece's line in report.json "pieces": id, cell, file, volume_mm3, bbox_mm, triangles, plate (None
    until the layout assigns one)."""
    pid, mesh = _id_mesh(piece)
    volume = getattr(piece, "volume", None)
    if volume is None:
        volume = abs(float(mesh.volume))
    triangles = getattr(piece, "triangles", None)
    if triangles is None:
        triangles = len(mesh.faces)
    return {
        "id": pid,
        "cell": _cell(piece, pid),
        "file": str(file),
        "volume_mm3": float(volume),
        "bbox_mm": np.asarray(mesh.bounds, dtype=float).tolist(),
        "triangles": int(triangles),
        "plate": None,
    }


def clean_json(x):
    """Plain JSON values: numpy -> Python, tuples -> lists, floats to 9 significant digits, nan/inf -> None."""
    # the plain types a report is mostly made of first, by exact type: a report has tens of thousands of values
    t = type(x)
    if t is float:
        return float(f"{x:.{_DIGITS}g}") if math.isfinite(x) else None
    if t is str or t is int or t is bool or x is None:
        return x
    if t is list:
        return [clean_json(v) for v in x]
    if t is dict:
        return {str(k): clean_json(v) for k, v in x.items()}
    if isinstance(x, Mapping):
        return {str(k): clean_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [clean_json(v) for v in x]
    if isinstance(x, np.ndarray):
        return clean_json(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        # float32 carries ~7 digits: its shortest repr, not the float64 expansion of it (0.100000001)
        x = float(str(x)) if isinstance(x, (np.float32, np.float16)) else float(x)
        if not math.isfinite(x):
            return None
        return float(f"{x:.{_DIGITS}g}")
    if isinstance(x, Path):
        return x.as_posix()
    if x is None or isinstance(x, str):
        return x
    return str(x)


def dumps_report(obj, indent: int = 2, _level: int = 0) -> str:
    """JSON with indent, but short lists of numbers (points, boxes, cells) kept on one line."""
    pad, inner = " " * (indent * _level), " " * (indent * (_level + 1))
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        body = [f"{inner}{_json_scalar(k)}: {dumps_report(v, indent, _level + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(body) + "\n" + pad + "}"
    if isinstance(obj, list):
        # a list holding a dict is never kept on one line: no need to write it out whole to measure it
        if not obj or all(not isinstance(v, dict) for v in obj):
            flat = json.dumps(obj, allow_nan=False)
            if len(flat) <= 80:
                return flat
        return "[\n" + ",\n".join(inner + dumps_report(v, indent, _level + 1) for v in obj) + "\n" + pad + "]"
    return _json_scalar(obj)


def _json_scalar(x) -> str:
    """json.dumps(x, allow_nan=False), the common plain types without its call: a 1024-piece report has ~200k values,
    and json.dumps per value was half the time of writing it (1.1 -> 0.5 s)."""
    t = type(x)
    if t is str:
        return encode_basestring_ascii(x)
    if t is int:
        return int.__repr__(x)
    if t is float and math.isfinite(x):
        return float.__repr__(x)
    return json.dumps(x, allow_nan=False)


def _fmt(x, nd=3):
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        return f"{x:,.{nd}f}" if abs(x) >= 1e-3 or x == 0 else f"{x:.3g}"
    return str(x)


def render_report_md(report: dict) -> str:
    """report.md: the report for people — summary, pieces, plates, checks, timings, preview."""
    spec = report.get("spec") or {}
    name = spec.get("name") or "puzzle"
    model = report.get("model") or {}
    pieces = report.get("pieces") or []
    joints = report.get("joints") or []
    checks = report.get("checks") or {}
    lines = [f"# {name}", ""]
    if report.get("volpuzzle_version"):
        lines += [f"Built with volpuzzle {report['volpuzzle_version']}.", ""]
    if report.get("preview"):
        lines += [f"![assembled and exploded views]({report['preview']})", ""]
    grid = spec.get("grid")
    lines += ["## Summary", "", "| | |", "|---|---|"]
    if grid:
        lines.append(f"| grid | {' × '.join(str(g) for g in grid)} |")
    lines.append(f"| pieces | {len(pieces)} |")
    lines.append(f"| joints | {len(joints)} |")
    if model.get("volume_mm3") is not None:
        lines.append(f"| model volume | {_fmt(model['volume_mm3'], 1)} mm³ |")
    if model.get("bbox_mm"):
        size = np.ptp(np.asarray(model["bbox_mm"], dtype=float), axis=0)
        lines.append(f"| model size | {' × '.join(f'{s:.1f}' for s in size)} mm |")
    if model.get("handedness"):
        lines.append(f"| handedness | {model['handedness']} |")
    rnd = report.get("randomize") or {}
    if rnd.get("amplitude"):
        lines.append(f"| randomized | seed {rnd.get('seed')}, amplitude {rnd.get('amplitude')} |")
    fit = report.get("fit") or {}
    if fit:
        from .check import fit_line

        lines += ["", "## Fit", "", fit_line(fit) + "."]
        lines += [f"- **Warning:** {w}" for w in fit.get("warnings") or []]
    lines += ["", "## Pieces", "", "| piece | label | cell | file | volume (mm³) | size (mm) | triangles | plate | "
              "on the bed (mm²) | base cut (mm) | pins up |",
              "|---|---|---|---|---:|---|---:|---:|---:|---:|---:|"]
    for p in pieces:
        bbox = p.get("bbox_mm")
        size = " × ".join(f"{s:.1f}" for s in np.ptp(np.asarray(bbox, dtype=float), axis=0)) if bbox else "–"
        cell = "-".join(str(c) for c in p["cell"]) if p.get("cell") is not None else "–"
        pr = p.get("print") or {}
        up = f"{pr['pins_up']} of {pr['pins']}" if pr.get("pins") else "–"
        lines.append(f"| {p.get('id')} | {_label_text(p)} | {cell} | [{p.get('file')}]({p.get('file')}) | "
                     f"{_fmt(p.get('volume_mm3'), 1)} | {size} | {p.get('triangles', '–')} | "
                     f"{_fmt(p.get('plate'))} | {_fmt(pr.get('bed_contact_mm2'), 1)} | "
                     f"{_fmt(pr.get('base_cut_mm'), 1) if pr.get('base_cut_mm') else '–'} | {up} |")
    lines += _printing_md(pieces, spec)
    dowels = report.get("dowels") or []
    if dowels:
        lines += ["", f"Loose dowels: {len(dowels)} (folder `dowels/`)."]
    plates = report.get("plates") or []
    if plates:
        lines += ["", "## Plates", "", "| plate | pieces |", "|---|---|"]
        for pl in plates:
            lines.append(f"| [{pl.get('file')}]({pl.get('file')}) | {', '.join(pl.get('pieces', []))} |")
    mesh = report.get("mesh") or {}
    if mesh:
        lines += ["", "## Mesh in a cage", "",
                  f"Contacts between pieces: {mesh.get('contacts_touching', 0)}; with room for a pin: "
                  f"{mesh.get('contacts_with_room', 0)}; pinned: {mesh.get('contacts_pinned', 0)}. "
                  f"Fragments merged into a neighbour: {len(mesh.get('merged', []))}. "
                  f"Cells that miss the mesh: {len(mesh.get('cells_without_piece', []))}."]
    assembly = report.get("assembly") or {}
    if assembly.get("steps"):
        lines += ["", "## Assembly", "", "Each picture shows the pieces in place in grey and the block to add in "
                  "colour, with an arrow along which it slides in. A printable page of the same steps: "
                  "[instructions.html](instructions.html).", ""]
        pictures = assembly.get("pictures") or []
        for n, text in enumerate(assembly_sentences(report), start=1):
            pic = pictures[n - 1] if n - 1 < len(pictures) else None
            lines += [f"{n}. {text}" + (f"<br>![step {n}]({pic})" if pic else "")]
    elif assembly.get("words"):
        lines += ["", "## Assembly", ""] + list(assembly["words"])
    if checks:
        verdict = "passed" if checks.get("passed") else "FAILED"
        lines += ["", f"## Checks: {verdict}", "", "| check | value |", "|---|---|"]
        lines.append(f"| all pieces closed | {_fmt(checks.get('all_closed'))} |")
        if checks.get("closed_failures"):
            lines.append(f"| not closed | {', '.join(checks['closed_failures'])} |")
        if checks.get("volume_sum_mm3") is not None:
            lines.append(f"| volume sum | {_fmt(checks['volume_sum_mm3'], 1)} mm³ |")
        if checks.get("expected_volume_mm3") is not None:
            lines.append(f"| expected volume | {_fmt(checks['expected_volume_mm3'], 1)} mm³ |")
        if checks.get("volume_error") is not None:
            lines.append(f"| volume error | {checks['volume_error']:+.4%} |")
        if checks.get("max_overlap_mm3") is not None:
            pair = checks.get("max_overlap_pair") or []
            where = f" ({' / '.join(pair)})" if pair else ""
            lines.append(f"| largest overlap | {_fmt(checks['max_overlap_mm3'], 4)} mm³{where} |")
        if checks.get("overlap_limit_mm3") is not None:
            lines.append(f"| overlap limit | {_fmt(checks['overlap_limit_mm3'], 4)} mm³ |")
        if checks.get("face_clearance_mm") is not None:
            lines.append(f"| face clearance | {_fmt(float(checks['face_clearance_mm']), 2)} mm, taking "
                         f"{_fmt(checks.get('face_clearance_mm3'), 1)} mm³ |")
        if checks.get("base_cuts_mm3"):
            lines.append(f"| base cuts | {_fmt(checks['base_cuts_mm3'], 1)} mm³ |")
        for f in checks.get("failures") or []:
            lines.append(f"| failure | {f} |")
    timings = report.get("timings_s") or {}
    if timings:
        lines += ["", "## Timings", "", "| stage | seconds |", "|---|---:|"]
        for k, v in timings.items():
            lines.append(f"| {k} | {_fmt(v, 2)} |")
    return "\n".join(lines) + "\n"


def _label_text(entry) -> str:
    label = entry.get("label") or {}
    return f"`{label['text']}`" if label.get("text") else "none"


def _printing_md(pieces, spec) -> list:
    """report.md's printing section: bed contact, pins up, labels, with what could not be done and why."""
    if not pieces or not any(p.get("print") for p in pieces):
        return []
    from .check import BED_MIN_MM2

    prints = [p.get("print") or {} for p in pieces]
    contact = [x.get("bed_contact_mm2") for x in prints if x.get("bed_contact_mm2") is not None]
    low = [p["id"] for p, x in zip(pieces, prints, strict=True) if (x.get("bed_contact_mm2") or 0) < BED_MIN_MM2]
    cuts = [p["id"] for p, x in zip(pieces, prints, strict=True) if x.get("base_cut_mm")]
    pins = sum(x.get("pins") or 0 for x in prints)
    up = sum(x.get("pins_up") or 0 for x in prints)
    out = ["", "## Printing", "",
           f"Every piece lies on the plate as `plates/` shows, to be printed without supports. Bed contact: "
           f"{min(contact):.1f} mm² at least, median {float(np.median(contact)):.1f} mm²; pieces under "
           f"{BED_MIN_MM2:g} mm²: {', '.join(low) if low else 'none'}. Pieces given a flat base cut: "
           f"{len(cuts)}. Pins within 30° of vertical: {up} of {pins}."]
    labels_on = ((spec or {}).get("output") or {}).get("labels", True)
    if labels_on:
        missing = [(p["id"], (p.get("label") or {}).get("skipped") or "no site") for p in pieces
                   if not (p.get("label") or {}).get("text")]
        renamed = [(p["id"], p["label"]["text"]) for p in pieces
                   if (p.get("label") or {}).get("text") and p["label"]["text"] != p["id"]]
        if missing:
            out += ["", "Pieces that could not be labelled:"] + [f"- {pid}: {why}" for pid, why in missing]
        else:
            out += ["", f"Every piece carries a label ({len(pieces)} of {len(pieces)})."]
        mirrored = [p["id"] for p in pieces if (p.get("label") or {}).get("face") == "bed"]
        if mirrored:
            out += ["", "Labels engraved mirrored on the bed side (no inner face held them; they read from below): "
                    + ", ".join(mirrored) + "."]
        if renamed:
            out += ["", "Labels shortened to the piece's number: "
                    + ", ".join(f"`{t}` = {pid}" for pid, t in renamed) + "."]
    return out


def assembly_sentences(report: dict) -> list:
    """One sentence per assembly step for people holding the pieces: which piece (by its label), onto what, which
    pins go where; the picture gives the direction."""
    pieces = report.get("pieces") or []
    text = {p.get("id"): (p.get("label") or {}).get("text") for p in pieces}

    def name(pid):
        t = text.get(pid)
        return f"**{pid}**" if not t or t == pid else f"**{pid}** (labelled `{t}`)"

    def names(ids):
        ids = list(ids)
        if len(ids) > 4:
            return f"the block of {len(ids)} pieces with {name(ids[0])}"
        return " and ".join(name(i) for i in ids) if ids else "the rest"

    out, started = [], False
    for s in (report.get("assembly") or {}).get("steps") or []:
        if s.get("kind") == "place":
            out.append(f"Place {name(s.get('piece'))} on the table" + (" to start a new block." if started else "."))
            started = True
            continue
        what = name(s["piece"]) if s.get("piece") else names(s.get("pieces") or [])
        line = f"Slide {what} onto {names(s.get('onto') or [])} along the arrow"
        pins = [f"the pin of {name(pin)} enters {name(hole)}" for pin, hole in s.get("joints") or []]
        out.append(line + (", so that " + "; ".join(pins) if pins else "") + ".")
    return out


def render_instructions_html(report: dict) -> str:
    """instructions.html: one printable page of assembly steps, a picture and a sentence each, with the fit."""
    import html

    spec = report.get("spec") or {}
    title = html.escape(str(spec.get("name") or "puzzle"))
    pieces = report.get("pieces") or []
    pictures = (report.get("assembly") or {}).get("pictures") or []
    fit = report.get("fit") or {}
    parts = ["<!DOCTYPE html>", "<html lang=\"en\"><head><meta charset=\"utf-8\">",
             f"<title>{title}: assembly</title>",
             "<style>body{font-family:sans-serif;margin:1.5em;color:#111}"
             "ol{display:flex;flex-wrap:wrap;gap:10px;padding:0;list-style:none;counter-reset:s}"
             "li{width:240px;border:1px solid #bbb;padding:6px;break-inside:avoid;page-break-inside:avoid}"
             "li img{width:100%}p.s{font-size:11px;margin:4px 0 0}"
             "@media print{body{margin:0}li{width:30%}}</style></head><body>",
             f"<h1>{title}: assembly</h1>",
             f"<p>{len(pieces)} pieces. Grey: in place; colour: the block to add, along the arrow.</p>"]
    if fit:
        from .check import fit_line

        parts.append(f"<p>Fit: {html.escape(fit_line(fit))}.</p>")
    parts.append("<ol>")
    for n, sentence in enumerate(assembly_sentences(report), start=1):
        sentence = html.escape(sentence).replace("**", "")
        sentence = sentence.replace("`", "")
        img = f"<img src=\"{html.escape(pictures[n - 1])}\" alt=\"step {n}\">" if n - 1 < len(pictures) else ""
        parts.append(f"<li>{img}<p class=\"s\"><b>{n}.</b> {sentence}</p></li>")
    parts += ["</ol>", "</body></html>"]
    return "\n".join(parts) + "\n"


def _write_piece(path: Path, name: str, mesh: trimesh.Trimesh, fmt: str, rgb, pins=None, tex=None) -> None:
    if fmt == "stl":
        import trimesh

        # trimesh's binary STL has an all-zero header (no timestamp): same mesh -> same bytes. Written from a
        # throw-away mesh of the same arrays, so that the triangles and normals the STL needs are not left cached
        # on every piece at once (0.1 KB a triangle: 220 MB at 1024 pieces)
        path.write_bytes(trimesh.exchange.stl.export_stl(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)))
    else:
        write_3mf(path, [(name, mesh.vertices, mesh.faces, rgb, None)], materials=[pins],
                  colors=None if tex is None else [tex])


def _marker_text(pid=None) -> str:
    import socket

    return json.dumps({"kind": _MARKER_KIND, "pid": pid, "host": socket.gethostname() if pid else None}) + "\n"


def _read_marker(folder: Path):
    """The marker dict of a folder volpuzzle wrote, or None (absent, a symlink, unreadable, someone else's)."""
    path = folder / MARKER
    try:
        if path.is_symlink() or not path.is_file() or path.stat().st_size > 4096:
            return None
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("kind") == _MARKER_KIND else None


def spec_inputs(spec) -> list:
    """The files a build reads (the spec, the model, a NURBS cage): a folder holding one is never replaced."""
    m = spec.model
    cage = getattr(m, "cage", None)
    return [p for p in (spec.source, m.nurbs, m.mesh, getattr(cage, "nurbs", None)) if p is not None]


def _inside(path: Path, folder: Path) -> bool:
    try:
        Path(os.path.realpath(path)).relative_to(os.path.realpath(folder))
        return True
    except ValueError:
        return False


def check_target(target, force: bool = False, protect=()) -> Path:
    """Raise ExportError unless write_build may write target: absent, or with force an empty folder or one that
    volpuzzle wrote (it holds the MARKER file) and that holds none of the `protect` paths (the spec and the model
    being built). Cheap: call it before the work starts, too."""
    target = Path(target)
    try:
        present = target.exists() or target.is_symlink()
    except (OSError, ValueError) as e:
        raise ExportError(f"output.directory: cannot use {str(target)!r} ({getattr(e, 'strerror', None) or e})") \
            from None
    if present:
        if not force:
            raise ExportError(f"{target} exists; use --force to replace it")
        if not target.is_dir() or target.is_symlink():
            raise ExportError(f"{target} exists and is not a folder; refusing to replace it")
        mine = [p for p in protect if _inside(p, target)]
        if mine:
            raise ExportError(f"{target} holds {mine[0]}, which this build reads; refusing to replace it, even with "
                              f"--force (expected an output folder apart from the spec and the model)")
        try:
            empty = not any(target.iterdir())
        except OSError as e:
            raise ExportError(f"{target}: cannot list the folder ({e.strerror})") from None
        if not empty and _read_marker(target) is None and not _legacy_output(target):
            raise ExportError(f"{target} is not a volpuzzle output folder (no {MARKER} marker that volpuzzle "
                              f"writes) and not empty; refusing to replace it, even with --force (remove it "
                              f"yourself or choose another -o)")
    # the folder is written beside the target and renamed into place: where that cannot be, say so before the work
    # rather than after it (a read-only disk, a folder of someone else's)
    place = target.parent
    while not place.exists() and place != place.parent:
        place = place.parent
    if place.is_dir() and not os.access(place, os.W_OK | os.X_OK):
        raise ExportError(f"{target}: cannot create the output folder: {place} is not writable (expected a folder "
                          f"you may write in; choose another -o)")
    return target


def _alive(pid) -> bool:
    if pid is None:
        return False  # a finished folder not yet renamed: its build is over
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError, TypeError):
        return True  # someone's process, or no pid: not ours to judge
    return True


def remove_stale_temporaries(target: Path) -> list:
    """Remove `.NAME.tmp-*` and `.NAME.old-*` folders beside target that a killed build left: only folders
    with our marker whose process is gone (on this host). -> the names removed."""
    import socket

    target = Path(target)
    removed = []
    try:
        siblings = list(target.parent.iterdir())
    except OSError:
        return removed
    host = socket.gethostname()
    for p in siblings:
        if not (p.name.startswith(f".{target.name}.tmp-") or p.name.startswith(f".{target.name}.old-")):
            continue
        if p.is_symlink() or not p.is_dir():
            continue
        marker = _read_marker(p)
        if marker is None:
            if not _legacy_temporary(p):
                continue
            marker = {"pid": None, "host": None}
        if p.name.startswith(f".{target.name}.tmp-") and (marker.get("host") not in (host, None)
                                                           or _alive(marker.get("pid"))):
            continue  # a running build's, or another machine's: leave it
        if p.name.startswith(f".{target.name}.old-") and not target.is_dir():
            continue  # killed between the two renames: this is the only copy of the previous output
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p.name)
    return removed


_OUTPUT_NAMES = {"pieces", "dowels", "plates", "steps", "puzzle.3mf", "preview.png", "report.json", "report.md",
                 "instructions.html"}


def _legacy_temporary(folder: Path, age_s: float = 3600.0) -> bool:
    """A temporary folder of a volpuzzle from before the marker: mkdtemp's 8-character suffix, nothing in it but
    what the export stage writes, and untouched for an hour (no build takes that long to export)."""
    suffix = folder.name.rsplit(".tmp-", 1)[-1]
    if ".tmp-" not in folder.name or len(suffix) != 8:
        return False
    try:
        names = {p.name for p in folder.iterdir()}
        return names <= _OUTPUT_NAMES and time.time() - folder.stat().st_mtime > age_s
    except OSError:
        return False


def _legacy_output(folder: Path) -> bool:
    """An output folder of a volpuzzle from before the marker: nothing in it but what the export stage writes, and
    a report.json that volpuzzle wrote (it names its version). A folder with any other file is not one."""
    try:
        names = {p.name for p in folder.iterdir()}
        report = folder / "report.json"
        if not names <= _OUTPUT_NAMES or report.is_symlink() or not report.is_file():
            return False
        if report.stat().st_size > (64 << 20):
            return False
        data = json.loads(report.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and isinstance(data.get("volpuzzle_version"), str) and "pieces" in data


def _failure(target: Path, e: BaseException, tmp: Path | None = None) -> str:
    """One line for a failed write: the file (as it would be named in the target), the reason, and that nothing
    was left."""
    if isinstance(e, OSError):
        name = os.fspath(e.filename) if isinstance(e.filename, (str, Path)) else None
        if name and tmp is not None and name.startswith(os.fspath(tmp)):
            name = os.fspath(target) + name[len(os.fspath(tmp)):]
        where = f" while writing {name}" if name else ""
        reason = e.strerror or str(e)
        return f"{target}: writing the output failed{where}: {reason}; nothing was written"
    return f"{target}: writing the output failed: {e}; nothing was written"


def _free_space_problem(parent: Path, items) -> str | None:
    """A message when the disk beside the target plainly cannot hold the output, else None. The output takes
    about 50 bytes a triangle for the pieces, and as much again for the assembled puzzle and the plates."""
    need = 3 * 50 * sum(len(m.faces) for _, m in items) + (1 << 20)
    try:
        free = shutil.disk_usage(parent).free
    except OSError:
        return None
    if free < need:
        return (f"{parent}: not enough free disk space for the output (needs about {need / 1e6:.3g} MB, "
                f"{free / 1e6:.3g} MB free)")
    return None


def write_build(target, pieces: Sequence, report: dict, fmt: str = "stl", force: bool = False,
                dowels: Sequence = (), colors: np.ndarray | None = None,
                extras: Mapping[str, Callable[[Path], None]] | None = None,
                pin_triangles: Mapping[str, np.ndarray] | None = None,
                triangle_colors: Mapping[str, np.ndarray] | None = None, workers=None) -> Path:
    """Write the output folder (SPEC section 5) atomically -> the target path.

    pieces: compose.Piece objects or (id, trimesh) pairs, in mm. dowels: (name, trimesh) pairs.
    colors: (n, 3) uint8 per piece, default piece_colors(n). extras: {relative path: writer(path)} for
    files produced elsewhere (plates, preview), called inside the temporary folder. pin_triangles: {piece id:
    (m,) 0/1 per triangle}, 1 on a pin: 3MF files give those triangles the second (pin) material. triangle_colors:
    {piece id: (m, 3) per-triangle colours, -1 rows where the piece colour stays} (a texture), for 3MF files.
    workers: a volpuzzle.workers.Workers that draws the extras given as workers.Remote (the pictures) meanwhile.
    Raises ExportError when the target exists without force, or on any failed write.
    """
    t0 = time.perf_counter()
    target = Path(target)
    if fmt not in FORMATS:
        raise ExportError(f"output.format: got {fmt!r}, expected one of {', '.join(FORMATS)}")
    items = [_id_mesh(p) for p in pieces]
    if not items:
        raise ExportError(f"{target}: no pieces to write")
    ids = [pid for pid, _ in items]
    if len(set(ids)) != len(ids):
        raise ExportError(f"{target}: piece ids repeat ({', '.join(sorted({i for i in ids if ids.count(i) > 1}))})")
    colors = piece_colors(len(items)) if colors is None else np.asarray(colors, dtype=np.uint8)
    if colors.shape != (len(items), 3):
        raise ExportError(f"colors: got shape {colors.shape}, expected ({len(items)}, 3)")
    check_target(target, force)
    parent = target.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ExportError(f"{target}: cannot create the output folder: {e.strerror or e}") from None
    remove_stale_temporaries(target)
    low = _free_space_problem(parent, items)
    if low:
        raise ExportError(low)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=parent))
    except OSError as e:
        raise ExportError(f"{target}: cannot create the output folder: {e.strerror or e}") from None
    try:
        tmp.chmod(0o777 & ~_umask())  # mkdtemp makes it private; the output folder should not be
        (tmp / MARKER).write_text(_marker_text(os.getpid()), encoding="utf-8")
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise ExportError(_failure(target, e)) from None
    # lib3mf lets go of the GIL while it compresses, so 3MF files (and extras named *.3mf) are written on one worker
    # thread while this one writes the rest and paints the preview.
    worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="volpuzzle-3mf")
    pending = []
    ahead = []  # (path in tmp, workers.Prefetch) of the extras begun in the workers

    def named(path, job, *args):
        try:
            job(*args)
        except OSError as e:
            if e.filename is None:  # a failed write() names no file: say which one it was
                raise OSError(e.errno, e.strerror or str(e), os.fspath(path)) from e
            raise

    def write(path, job, *args):
        if path.suffix == ".3mf":
            pending.append(worker.submit(named, path, job, *args))
        else:
            named(path, job, *args)

    try:
        report = dict(report)
        (tmp / "pieces").mkdir()
        # the extras a worker may write (workers.Remote): this process draws the first picture itself once the
        # pieces are written (the preview; the steps drawn here instead cost it more, 1.3 against 1.0 CPU s at 32
        # pieces), the rest (other pictures, then the plates) are begun in the workers meanwhile, and one no worker
        # has begun by then is done here too (workers.Prefetch) rather than waited for: a plate on the 3MF thread,
        # from the last while the workers go from the first. A build begins the steps' pictures before this, once
        # the assembly is known (layout.step_pictures_ahead)
        remote = sorted((rel for rel, w in (extras or {}).items() if workers is not None and isinstance(w, Remote)),
                        key=lambda rel: (rel.endswith(".3mf"), rel))
        for rel in remote[1:]:
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            ahead.append((tmp / rel, workers.prefetch(extras[rel], tmp / rel)))
        extras = {rel: w for rel, w in (extras or {}).items() if rel not in remote[1:]}
        # the largest file first, so that the worker is busy from the start
        write(tmp / "puzzle.3mf", write_3mf, tmp / "puzzle.3mf",
              [(pid, mesh.vertices, mesh.faces, rgb, None) for (pid, mesh), rgb in zip(items, colors, strict=True)],
              "millimeter",
              [(pin_triangles or {}).get(pid) for pid, _ in items], DEFAULT_ACCENT,
              None if triangle_colors is None else [triangle_colors.get(pid) for pid, _ in items])
        for dest, job in reversed(ahead):
            if dest.suffix == ".3mf":
                write(dest, job.result)
        entries = {e.get("id"): dict(e) for e in report.get("pieces") or []}
        piece_entries = []
        for (pid, mesh), piece, rgb in zip(items, pieces, colors, strict=True):
            rel = f"pieces/{pid}.{fmt}"
            write(tmp / rel, _write_piece, tmp / rel, pid, mesh, fmt, rgb, (pin_triangles or {}).get(pid),
                  (triangle_colors or {}).get(pid))
            entry = entries.get(pid) or report_piece_entry(piece, rel)
            entry["file"] = rel
            piece_entries.append(entry)
        report["pieces"] = piece_entries
        if dowels:
            (tmp / "dowels").mkdir()
            dowel_entries = []
            for name, mesh in dowels:
                rel = f"dowels/{name}.{fmt}"
                write(tmp / rel, _write_piece, tmp / rel, str(name), mesh, fmt, (200, 200, 200))
                dowel_entries.append({"name": str(name), "file": rel, "volume_mm3": abs(float(mesh.volume))})
            report["dowels"] = dowel_entries
        for rel, writer in sorted((extras or {}).items(), key=lambda kv: not kv[0].endswith(".3mf")):
            dest = tmp / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            write(dest, writer, dest)
        # the last first: the workers take them in order, so those not begun are at the back
        for dest, picture in reversed(ahead):
            if dest.suffix != ".3mf":
                named(dest, picture.result)
        for job in pending:
            job.result()
        if report.get("preview") and not (tmp / report["preview"]).is_file():
            report.pop("preview")  # never link a picture that is not there
        if not report.get("preview") and (tmp / "preview.png").is_file():
            report["preview"] = "preview.png"
        timings = dict(report.get("timings_s") or {})
        timings.setdefault("export", time.perf_counter() - t0)
        report["timings_s"] = {k: (round(float(v), 3) if isinstance(v, (int, float)) else v)
                               for k, v in timings.items()}
        report = clean_json(report)
        for name, text in (("report.json", dumps_report(report) + "\n"), ("report.md", render_report_md(report)),
                           ("instructions.html", render_instructions_html(report)),
                           (MARKER, _marker_text())):  # the marker last: finished, no process owns it any more
            named(tmp / name, (tmp / name).write_text, text, "utf-8")
        stop.check()  # a stop that a library swallowed on the way must not leave a finished folder behind
        _move_into_place(tmp, target)
    except BaseException as e:
        # nothing may still write into tmp once it is removed: neither the 3MF thread nor a worker process
        worker.shutdown(wait=True, cancel_futures=True)
        for _dest, job in ahead:
            job.settle()
        shutil.rmtree(tmp, ignore_errors=True)
        if not isinstance(e, Exception):
            raise
        cause = e.__cause__ if isinstance(e, ExportError) and isinstance(e.__cause__, OSError) else e
        if isinstance(e, VolpuzzleError) and cause is e:
            raise
        raise ExportError(_failure(target, cause, tmp)) from e
    finally:
        worker.shutdown(wait=True)
    return target


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _move_into_place(tmp: Path, target: Path) -> None:
    """Rename tmp to target; an existing target is set aside first and only removed once tmp is in place."""
    if not (target.exists() or target.is_symlink()):
        os.replace(tmp, target)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
    old.rmdir()
    os.replace(target, old)
    try:
        os.replace(tmp, target)
    except BaseException:
        os.replace(old, target)
        raise
    shutil.rmtree(old, ignore_errors=True)


def printable(pieces, workers=None):
    """Pieces exactly as STL and 3MF store them: float32 vertices. Rounding can merge the ends of micro-edges that
    booleans and tessellation leave; those edges are collapsed (exact duplicates merged, triangles that repeat a
    vertex dropped) so the checks judge the very mesh that is written. workers: a volpuzzle.workers.Workers that
    rounds some of them (the same meshes)."""
    import dataclasses

    from .check import remember_closed
    from .errors import GeometryError
    from .geometry import remember_hull_points
    from .workers import MeshRef, map_pieces

    items = [MeshRef(p.mesh) for p in pieces]
    done = map_pieces(workers, _printable_one, items, what="check")
    out = []
    for p, (ref, problem, volume, hull) in zip(pieces, done, strict=True):
        if problem:  # in piece order, whichever process found it
            raise GeometryError(_printable_problem(p, problem))
        remember_closed(ref.mesh, problem)  # the checks ask again of this very mesh
        # and the plates' layout asks for its hull: at 1024 pieces ~0.7 s of this process alone, there
        remember_hull_points(ref.mesh, hull)
        out.append(dataclasses.replace(p, mesh=ref.mesh, volume=volume, triangles=int(len(ref.mesh.faces))))
    return out


def _printable_one(_shared, ref):
    """One piece of printable, wherever it runs: MeshRef -> (MeshRef of the float32 mesh, its closed_problem, its
    signed volume mm^3, its hull_points_of (k, 3); None for both when it is not closed)."""
    import trimesh

    from .check import closed_problem, signed_volume
    from .geometry import hull_points_of, weld
    from .workers import MeshRef

    mesh = ref.mesh
    # + 0 turns -0.0 into 0.0, so that equal coordinates have equal bytes; a byte-wise unique is ~3x faster
    # than np.unique(axis=0)
    v32 = np.ascontiguousarray(np.asarray(mesh.vertices, dtype=np.float32) + np.float32(0.0))
    _, first, inverse = np.unique(v32.view(np.dtype((np.void, 12))).ravel(), return_index=True,
                                  return_inverse=True)
    v, f = weld(v32[first].astype(np.float64), inverse.reshape(-1)[mesh.faces], 0.0)
    out = trimesh.Trimesh(v, f, process=False)
    problem = closed_problem(out)
    if problem:
        return MeshRef(out), problem, None, None
    return MeshRef(out), problem, signed_volume(v, f), hull_points_of(out)


def _printable_problem(piece, problem):
    """The message for a piece whose float32 mesh is not one closed solid: rounding broke it, or the engine's own
    float64 solid already meets itself (two coincident vertices the engine keeps apart, which every reader of the
    file merges: a zero-thickness sheet or a pinch), which no finer tolerance mends."""
    from .check import closed_problem

    own = closed_problem(piece.mesh)
    if not own:
        return (f"{piece.id}: the piece is no longer one closed solid at the float32 precision of STL and 3MF files "
                f"({problem}); try a smaller output.tolerance")
    import trimesh

    merged = trimesh.Trimesh(piece.mesh.vertices, piece.mesh.faces, process=True, validate=False)
    from .geometry import unique_pairs

    edges, counts = unique_pairs(merged.edges_sorted)
    odd = edges[counts != 2]
    where = (" at (" + ", ".join(f"{c:.2f}" for c in merged.vertices[odd[0]].mean(axis=0)) + ") mm"
             if len(odd) else "")
    return (f"{piece.id}: the piece's surface meets itself{where} (got {own} once coincident vertices are merged, "
            f"as a slicer reads the file; expected one closed solid); try other cuts: another grid, splits or "
            f"model.cage.padding")


def pin_triangles(pieces, joints):
    """{piece id: (m,) uint8, 1 for triangles on one of its pins}: those outside the piece's face, within the pin's
    outer radius (a snap pin swells) and length. For the second (pin) material of 3MF files."""
    from .joint import cell_joints, outer_radius

    out = {}
    touching = cell_joints(joints)  # a piece looks at its own cell's joints, not every joint (0.2 s at 1024 pieces)
    for p in pieces:
        cell = tuple(p.cell)
        mine = [j for j in touching.get(cell, ()) if j.style == "pin" and tuple(j.pin_cell) == cell]
        if not mine:
            continue
        # not mesh.triangles_center: that would keep (m, 3, 3) triangles cached on every piece to the end
        c = np.asarray(p.mesh.vertices).view(np.ndarray)[p.mesh.faces].mean(axis=1)
        flag = np.zeros(len(c), np.uint8)
        for j in mine:
            d = np.asarray(j.direction, float)
            rel = c - np.asarray(j.center, float)
            t = rel @ d
            radial = np.linalg.norm(rel - t[:, None] * d, axis=1)
            reach = outer_radius(j.radius, j.shape) + 1e-3
            flag |= ((t > 1e-3) & (t <= j.length + 1e-3) & (radial <= reach)).astype(np.uint8)
        out[p.id] = flag
    return out
