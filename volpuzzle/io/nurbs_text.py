"""The `.nurbs` text format (GLScene's NURBS surfaces, e.g. the classic duck): one bivariate surface per file.

    uOrder 4            orders, degree + 1
    vOrder 4
    uDimension 13       control points along u and v
    vDimension 14
    uKnot [ k, k, ... ]
    vKnot [ ... ]
    controlPoint [ x y z, x y z, ... ]     Cartesian, u fastest: flat index = v * uDimension + u
    weight [ w, w, ... ]                   optional, one per control point, same order

Numbers inside brackets are separated by commas and/or white space. The file holds a surface, never a volume: as a
volume model it is refused with a pointer to `model.shell`.
"""

import re

import numpy as np

from . import fail, make_surface, read_text

NAME = "nurbs-text"
EXTENSIONS = (".nurbs",)
_KEYS = ("uOrder", "vOrder", "uDimension", "vDimension", "uKnot", "vKnot", "controlPoint", "weight")
_ENTRY = re.compile(r"([A-Za-z_]\w*)\s*(\[[^\]]*\]?|[^\s\[]+)")


def detect(_path, head):
    text = head[:4096].lstrip(b"\xef\xbb\xbf \t\r\n")
    return text.startswith((b"uOrder", b"vOrder", b"uDimension", b"vDimension")) and b"controlPoint" in head


def _numbers(path, key, body):
    if not body.endswith("]"):
        raise fail(path, key, "the list is never closed (missing ']')")
    tokens = [t for t in re.split(r"[\s,]+", body[1:-1]) if t]
    try:
        return np.array([float(t) for t in tokens], dtype=float)
    except ValueError:
        bad = next(t for t in tokens if not re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?", t))
        raise fail(path, key, f"expected numbers, got {bad!r}") from None


def _parse(path):
    entries = {}
    for m in _ENTRY.finditer(read_text(path)):
        key, body = m.group(1), m.group(2)
        if key not in _KEYS:
            raise fail(path, key, f"unknown entry (expected one of {', '.join(_KEYS)})")
        if key in entries:
            raise fail(path, key, "given twice (expected each entry once)")
        entries[key] = body
    return entries


def _int(path, entries, key):
    if key not in entries:
        raise fail(path, key, "missing (a .nurbs surface needs uOrder, vOrder, uDimension, vDimension, uKnot, vKnot "
                              "and controlPoint)")
    try:
        value = int(entries[key])
    except ValueError:
        raise fail(path, key, f"expected an integer, got {entries[key]!r}") from None
    if value < 1:
        raise fail(path, key, f"expected a positive integer, got {value}")
    return value


def read_surfaces(path):
    entries = _parse(path)
    orders = [_int(path, entries, k) for k in ("uOrder", "vOrder")]
    sizes = [_int(path, entries, k) for k in ("uDimension", "vDimension")]
    knots = []
    for key, n, k in zip(("uKnot", "vKnot"), sizes, orders, strict=True):
        if key not in entries:
            raise fail(path, key, "missing (expected a list of knots)")
        kv = _numbers(path, key, entries[key])
        if len(kv) != n + k:
            raise fail(path, key, f"{len(kv)} knots do not fit {n} control points of order {k} (expected {n + k})")
        knots.append(kv)
    if "controlPoint" not in entries:
        raise fail(path, "controlPoint", "missing (expected a list of x y z points)")
    count = sizes[0] * sizes[1]
    pts = _numbers(path, "controlPoint", entries["controlPoint"])
    if pts.size != 3 * count:
        raise fail(path, "controlPoint", f"expected uDimension x vDimension = {sizes[0]} x {sizes[1]} = {count} points "
                                         f"({3 * count} numbers), got {pts.size} numbers")
    pts = pts.reshape(sizes[1], sizes[0], 3).transpose(1, 0, 2)
    weights = None
    if "weight" in entries:
        weights = _numbers(path, "weight", entries["weight"])
        if weights.size != count:
            raise fail(path, "weight", f"expected {count} weights, one per control point, got {weights.size}")
        weights = weights.reshape(sizes[1], sizes[0]).T
    return [make_surface(path, [k - 1 for k in orders], knots, pts, weights)], {"units": None}


def read(path):
    raise fail(path, "", "a .nurbs file holds a surface, not a volume (expected a volume model; for a thick shell "
                         "from this surface write model: {shell: {surface: FILE, thickness: MM}})")
