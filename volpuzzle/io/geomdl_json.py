"""geomdl (NURBS-Python 5.x) JSON as written by `geomdl.exchange.export_json` for volumes.

{"shape": {"type": "volume", "count": N, "data": [{"degree_u": .., "knotvector_u": [..], "size_u": .., (v, w),
 "control_points": {"points": [[x, y, z], ...], "weights": [...]}, "rational": bool, "dimension": 3}]}}

Points are Cartesian (geomdl exports `ctrlpts`, not the weighted `ctrlptsw`), ordered v fastest, then u, then w:
flat index = j + n_v * (i + n_u * k). A `"type": "surface"` file (u, v only; flat index j + n_v * i) is read by
read_surfaces, for `model.shell`.
"""

import numpy as np

from . import fail, make_surface, make_volume
from .vpjson import load_json

NAME = "geomdl-json"
EXTENSIONS = (".json",)
EXTENSION_FALLBACK = False


def detect(_path, head):
    return head.lstrip(b"\xef\xbb\xbf \t\r\n")[:1] == b"{" and b'"shape"' in head


def _int(path, label, key, d):
    field = f"{label}.{key}"
    v = d.get(key)
    if not isinstance(v, int) or isinstance(v, bool):
        raise fail(path, field, f"expected an integer, got {v!r}")
    return v


def _patch(path, d, label, axes="uvw"):
    if not isinstance(d, dict):
        raise fail(path, label, "expected an object")
    dim = d.get("dimension", 3)
    shape = "volume" if len(axes) == 3 else "surface"
    if dim != 3:
        kind = (f"a scalar (1-D) {('bivariate', 'trivariate')[len(axes) - 2]}" if dim == 1
                else f"{dim}-D control points")
        raise fail(path, f"{label}.dimension", f"{kind} is not a {shape} in space; expected dimension 3, got {dim!r}")
    degrees, knots, sizes = [], [], []
    for ax in axes:
        degrees.append(_int(path, label, f"degree_{ax}", d))
        kv = d.get(f"knotvector_{ax}")
        if not isinstance(kv, list):
            raise fail(path, f"{label}.knotvector_{ax}", "expected a list of numbers")
        try:
            knots.append(np.array(kv, dtype=float))
        except (TypeError, ValueError):
            raise fail(path, f"{label}.knotvector_{ax}", "expected a list of numbers") from None
        sizes.append(_int(path, label, f"size_{ax}", d))
    cp = d.get("control_points")
    if not isinstance(cp, dict) or "points" not in cp:
        raise fail(path, f"{label}.control_points", "expected an object with \"points\" (and optional \"weights\")")
    try:
        pts = np.array(cp["points"], dtype=float)
    except (TypeError, ValueError):
        raise fail(path, f"{label}.control_points.points", "expected a list of [x, y, z] numbers") from None
    count = int(np.prod(sizes))
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] != count:
        raise fail(path, f"{label}.control_points.points",
                   f"expected {' x '.join('size_' + a for a in axes)} = {' x '.join(map(str, sizes))} = {count} "
                   f"points of 3 coordinates, got shape {pts.shape}")
    # v fastest, then u, then w: stored order (w, u, v)
    stored = ((sizes[2],) if len(axes) == 3 else ()) + (sizes[0], sizes[1])
    order = (1, 2, 0) if len(axes) == 3 else (0, 1)
    pts = pts.reshape(stored + (3,)).transpose(order + (len(axes),))
    w = cp.get("weights")
    if w is not None:
        try:
            w = np.array(w, dtype=float)
        except (TypeError, ValueError):
            raise fail(path, f"{label}.control_points.weights", "expected a list of numbers") from None
        if w.shape != (count,):
            raise fail(path, f"{label}.control_points.weights", f"expected {count} numbers, got shape {w.shape}")
        w = w.reshape(stored).transpose(order)
    make = make_volume if len(axes) == 3 else make_surface
    return make(path, degrees, knots, pts, w, label=label)


def _shapes(path, kind):
    d = load_json(path)
    shape = d.get("shape") if isinstance(d, dict) else None
    if not isinstance(shape, dict):
        raise fail(path, "shape", "expected a geomdl \"shape\" object")
    if shape.get("type") != kind:
        raise fail(path, "shape.type", f"no {kind} in the file: expected \"{kind}\", got {shape.get('type')!r}")
    data = shape.get("data")
    if not isinstance(data, list):
        raise fail(path, "shape.data", f"expected a list of {kind}s")
    return data


def read(path):
    data = _shapes(path, "volume")
    return [_patch(path, p, f"shape.data[{i}]") for i, p in enumerate(data)], {"units": None}


def read_surfaces(path):
    data = _shapes(path, "surface")
    return [_patch(path, p, f"shape.data[{i}]", "uv") for i, p in enumerate(data)], {"units": None}
