"""volpuzzle JSON (SPEC section 2): the format the tool writes.

{"format": "volpuzzle-nurbs", "version": 1, "degrees": [..3], "knots": [[..], [..], [..]],
 "control_points": (n_u, n_v, n_w, 3) nested, Cartesian, "weights": optional (n_u, n_v, n_w), "units": "mm"}

Extension: instead of one volume at top level, "patches": [{degrees, knots, control_points, weights}, ...].
"""

import json

import numpy as np

from . import UNITS, fail, make_volume

NAME = "volpuzzle-json"
EXTENSIONS = (".json",)
EXTENSION_FALLBACK = False  # a .json without the marker may be geomdl; the registry explains both
FORMAT = "volpuzzle-nurbs"
VERSION = 1


def detect(_path, head):
    return head.lstrip(b"\xef\xbb\xbf \t\r\n")[:1] == b"{" and FORMAT.encode() in head


def load_json(path):
    """Parse a JSON file, turning syntax errors and truncation into a ModelError with line and column."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise fail(path, "", f"not UTF-8 text (byte {e.start}); expected a JSON file") from None
    try:
        return json.loads(text, parse_int=_small_int)  # NaN and Infinity reach the Volume, which names the index
    except json.JSONDecodeError as e:
        ends_early = e.pos >= len(text.rstrip()) or e.msg.startswith("Unterminated string")
        what = "truncated" if ends_early else "invalid"
        raise fail(path, "", f"{what} JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    except RecursionError:
        raise fail(path, "", "invalid JSON: nested too deeply") from None
    except ValueError as e:  # from the number hooks
        raise fail(path, "", f"invalid JSON: {e}") from None


def _small_int(text):
    """An integer of at most 30 digits: longer ones are no count or index of a model (and Python refuses to
    convert more than 4300 digits with a bare ValueError)."""
    digits = len(text.lstrip("-"))
    if digits > 30:
        raise ValueError(f"an integer of {digits} digits ({text[:12]}...), expected at most 30")
    return int(text)


def _array(path, field, value, ndim, last=None):
    """Nested lists -> float array with `ndim` dimensions (and last axis `last`), or a ModelError."""
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise fail(path, field, f"expected a rectangular nested list of numbers with {ndim} levels "
                                f"(ragged lists or non-numbers found)") from None
    if a.ndim != ndim or (last is not None and a.shape[-1] != last):
        want = "(n_u, n_v, n_w, 3)" if ndim == 4 else "(n_u, n_v, n_w)"
        raise fail(path, field, f"expected an array of shape {want}, got shape {a.shape}")
    return a


def _patch(path, d, label):
    pre = f"{label}." if label else ""
    if not isinstance(d, dict):
        raise fail(path, label or "", f"expected an object, got {type(d).__name__}")
    for key in ("degrees", "knots", "control_points"):
        if key not in d:
            raise fail(path, pre + key, "missing (required: degrees, knots, control_points)")
    deg = d["degrees"]
    if (not isinstance(deg, list) or len(deg) != 3
            or not all(isinstance(x, int) and not isinstance(x, bool) for x in deg)):
        raise fail(path, pre + "degrees", f"expected three integers, got {deg!r}")
    knots = d["knots"]
    if not isinstance(knots, list) or len(knots) != 3:
        raise fail(path, pre + "knots", "expected three lists of numbers (u, v, w)")
    ks = []
    for a, k in enumerate(knots):
        if not isinstance(k, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in k):
            raise fail(path, f"{pre}knots[{a}]", "expected a list of numbers")
        ks.append(np.array(k, dtype=float))
    cps = _array(path, pre + "control_points", d["control_points"], 4, 3)
    w = d.get("weights")
    if w is not None:
        w = _array(path, pre + "weights", w, 3)
    return make_volume(path, deg, ks, cps, w, label=label)


def read(path):
    d = load_json(path)
    if not isinstance(d, dict):
        raise fail(path, "", f"expected a JSON object at the top level, got {type(d).__name__}")
    if d.get("format") != FORMAT:
        raise fail(path, "format", f"expected \"{FORMAT}\", got {d.get('format')!r}")
    if d.get("version") != VERSION or isinstance(d.get("version"), bool):
        raise fail(path, "version", f"expected {VERSION}, got {d.get('version')!r}")
    units = d.get("units")
    if units is not None and units not in UNITS:
        raise fail(path, "units", f"expected one of {', '.join(UNITS)}, got {units!r}")
    if "patches" in d:
        if not isinstance(d["patches"], list):
            raise fail(path, "patches", "expected a list of volume objects")
        vols = [_patch(path, p, f"patches[{i}]") for i, p in enumerate(d["patches"])]
    else:
        vols = [_patch(path, d, "")]
    return vols, {"units": units}


# --- writing --------------------------------------------------------------------------------------------------
def _num(x):
    # repr of a Python float is the shortest string that reads back to the same double: exact round trip.
    x = float(x)
    return repr(x + 0.0) if x == 0 else repr(x)


def _nested(a, indent):
    """Nested JSON lists, the innermost level on one line."""
    if a.ndim == 1:
        return "[" + ", ".join(_num(x) for x in a) + "]"
    pad = " " * (indent + 2)
    inner = (",\n" + pad).join(_nested(x, indent + 2) for x in a)
    return "[\n" + pad + inner + "\n" + " " * indent + "]"


def dumps(vol, units="mm"):
    """The volpuzzle JSON text of a Volume: deterministic, full precision."""
    lines = [
        "{",
        f'  "format": "{FORMAT}",',
        f'  "version": {VERSION},',
        f'  "units": "{units}",',
        '  "degrees": [' + ", ".join(str(int(p)) for p in vol.degrees) + "],",
        '  "knots": [\n    ' + ",\n    ".join(_nested(np.asarray(k), 4) for k in vol.knots) + "\n  ],",
        '  "control_points": ' + _nested(np.asarray(vol.control_points), 2)
        + ("," if vol.weights is not None else ""),
    ]
    if vol.weights is not None:
        lines.append('  "weights": ' + _nested(np.asarray(vol.weights), 2))
    lines.append("}")
    return "\n".join(lines) + "\n"
