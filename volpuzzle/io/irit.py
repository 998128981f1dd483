"""IRIT text data (.itd): trivariates `[TRIVAR BSPLINE lu lv lw ou ov ow PT [KV ..] [KV ..] [KV ..] [pt] ...]` and
`[TRIVAR BEZIER lu lv lw PT [pt] ...]`; every other object in the file is skipped. Surfaces (`[SURFACE BSPLINE lu lv
ou ov PT [KV ..] [KV ..] [pt] ...]`, `[SURFACE BEZIER lu lv PT ...]`) are read the same way by read_surfaces.

IRIT gives orders (degree + 1). PT is E3 (points [x y z]) or P3 (rational: [w  w*x  w*y  w*z], weight first and
premultiplied). Points run u fastest: flat index = i + lu * (j + lv * k).

A periodic knot vector (KVP) of order k over lu points has lu + 2k - 1 knots, and the first k - 1 control slabs
repeat at the end (IRIT's periodic end conditions). We unroll that wrap and convert the floating knot vector to a
clamped one by knot insertion at the domain ends: the same volume, exactly, on the same domain. (A KVP of lu + k
knots is read as an already unrolled floating vector.)
"""

import math
import re

import numpy as np

from . import fail, make_surface, make_volume, read_text

NAME = "irit-itd"
EXTENSIONS = (".itd", ".dat")
_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*"|\[|\]|#[^\n]*|[^\s\[\]"#]+')
_PT = re.compile(r"^([EP])(\d+)$", re.I)
_MAX_DEPTH = 64  # IRIT objects nest a few levels; deeper is not a model (and would exhaust the recursion)
_MAX_DEGREE = 7  # as spline.Volume


def detect(_path, head):
    text = re.sub(rb"(?m)^\s*#.*$", b"", head[:8192]).lstrip().upper()
    return text.startswith(b"[") and (b"[OBJECT" in text or b"TRIVAR" in text or b"CURVE" in text
                                      or b"SURFACE" in text)


def _tree(path, text):
    """Bracketed tokens -> nested Python lists (strings at the leaves)."""
    stack = [[]]
    line = 1
    pos = 0
    for m in _TOKEN.finditer(text):
        line += text.count("\n", pos, m.start())
        pos = m.start()
        t = m.group()
        if t.startswith("#"):
            continue
        if t == "[":
            if len(stack) > _MAX_DEPTH:
                raise fail(path, "", f"invalid IRIT data: brackets nested deeper than {_MAX_DEPTH} levels at line "
                                     f"{line} (expected objects a few levels deep)")
            stack.append([])
            stack[-1].append(line)  # remember where the list starts, for messages
        elif t == "]":
            if len(stack) == 1:
                raise fail(path, "", f"invalid IRIT data: unbalanced ']' at line {line}")
            node = stack.pop()
            stack[-1].append(node)
        else:
            stack[-1].append(t)
    if len(stack) != 1:
        raise fail(path, "", f"truncated IRIT data: the list opened at line {stack[-1][0]} is never closed "
                             f"(missing ']')")
    return stack[0]


def _walk(node, name=None, kind="TRIVAR"):
    """Yield (node, object name) for every `kind` (TRIVAR or SURFACE) list anywhere in the tree."""
    items = node[1:] if node and isinstance(node[0], int) else node
    head = items[0].upper() if items and isinstance(items[0], str) else None
    if head == kind:
        yield node, name
        return
    if head == "OBJECT" and len(items) > 1 and isinstance(items[1], str):
        name = items[1]
    for x in items:
        if isinstance(x, list):
            yield from _walk(x, name, kind)


def _ints(path, field, tokens):
    try:
        return [int(t) for t in tokens]
    except (ValueError, TypeError):
        raise fail(path, field, f"expected integers, got {' '.join(map(str, tokens))!r}") from None


def _floats(path, field, tokens):
    try:
        return np.array([float(t) for t in tokens], dtype=float)
    except (ValueError, TypeError):
        raise fail(path, field, f"expected numbers, got {' '.join(map(str, tokens))!r}") from None


_KINDS = {3: ("TRIVAR", "lu lv lw", "ou ov ow", "three", "trivariate", "volume"),
          2: ("SURFACE", "lu lv", "ou ov", "two", "bivariate", "surface")}


def _trivar(path, node, label, dims=3):
    """A TRIVAR (dims 3) or SURFACE (dims 2) node -> (Volume or Surface, periodic flag per axis)."""
    head, ls, os_, count_word, what, shape_word = _KINDS[dims]
    line, items = node[0], node[1:]
    label = f"{label} (line {line})"
    if len(items) < 2 or not isinstance(items[1], str):
        raise fail(path, label, f"expected {head} BSPLINE or {head} BEZIER")
    kind = items[1].upper()
    scalars = [x for x in items[2:] if isinstance(x, str)]
    lists = [x for x in items[2:] if isinstance(x, list)]
    if kind == "BSPLINE":
        if len(scalars) != 2 * dims + 1:
            raise fail(path, label, f"expected '{head} BSPLINE {ls} {os_} PT' ({count_word} lengths, {count_word} "
                                    f"orders, a point type), got {' '.join(scalars)!r}")
        lengths = _ints(path, f"{label}: lengths", scalars[:dims])
        orders = _ints(path, f"{label}: orders", scalars[dims:2 * dims])
    elif kind == "BEZIER":
        if len(scalars) != dims + 1:
            raise fail(path, label, f"expected '{head} BEZIER {ls} PT', got {' '.join(scalars)!r}")
        lengths = _ints(path, f"{label}: lengths", scalars[:dims])
        orders = list(lengths)
    else:
        raise fail(path, label, f"{head} {items[1]} is not supported; expected BSPLINE or BEZIER")
    pt = _PT.match(scalars[-1])
    if not pt:
        raise fail(path, f"{label}: point type", f"expected E3 or P3, got {scalars[-1]!r}")
    rational, dim = pt.group(1).upper() == "P", int(pt.group(2))
    if dim == 1:
        raise fail(path, f"{label}: point type", f"{scalars[-1]} is a scalar {what} (a field, not a {shape_word} "
                                                 f"in space); expected E3 or P3")
    if dim != 3:
        raise fail(path, f"{label}: point type", f"expected E3 or P3 (points in space), got {scalars[-1]}")
    for a, (n, k) in enumerate(zip(lengths, orders, strict=True)):
        if n < 1 or k < 2 or k > n:
            raise fail(path, f"{label}: {'uvw'[a]}", f"expected order >= 2 and length >= order, got length {n}, "
                                                    f"order {k}")
        if k > _MAX_DEGREE + 1:
            raise fail(path, f"{label}: {'uvw'[a]}", f"order {k} (degree {k - 1}) is not supported "
                                                    f"(expected order 2 to {_MAX_DEGREE + 1})")

    kvs, pts = [], []
    count = math.prod(lengths)  # Python integers: no overflow, and nothing allocated by it
    points = sum(1 for x in lists if len(x) > 1 and isinstance(x[1], str) and re.match(r"^[-+.\d]", x[1]))
    if points != count:
        raise fail(path, f"{label}: control points", f"expected {' x '.join(map(str, lengths))} = "
                                                     f"{count} points, got {points}")
    for x in lists:
        body = x[1:]
        if body and isinstance(body[0], str) and body[0].upper() in ("KV", "KVP"):
            kvs.append((body[0].upper(), _floats(path, f"{label}: {body[0]} (line {x[0]})", body[1:])))
        elif body and isinstance(body[0], str) and re.match(r"^[-+.\d]", body[0]):
            pts.append((x[0], body))
        # anything else is an attribute such as [color 4]: skipped
    periodic = [False] * dims
    if kind == "BSPLINE":
        if len(kvs) != dims:
            raise fail(path, f"{label}: knot vectors",
                       f"expected {count_word} [KV ...] lists ({', '.join('uvw'[:dims])}), got {len(kvs)}")
        knots = []
        for a, ((tag, kv), n, k) in enumerate(zip(kvs, lengths, orders, strict=True)):
            field = f"{label}: {tag} {'uvw'[a]}"
            if tag == "KVP":
                if len(kv) not in (n + 2 * k - 1, n + k):
                    raise fail(path, field, f"a periodic knot vector of order {k} over {n} points needs "
                                            f"{n + 2 * k - 1} knots, got {len(kv)}")
                periodic[a] = len(kv) == n + 2 * k - 1
            elif len(kv) != n + k:
                raise fail(path, field, f"length {len(kv)} does not fit {n} points of order {k} "
                                        f"(expected {n + k} knots)")
            knots.append(kv)
    else:
        knots = [np.r_[np.zeros(n), np.ones(n)] for n in lengths]

    width = 4 if rational else 3
    flat = np.empty((count, width))
    for i, (ln, body) in enumerate(pts):
        if len(body) != width:
            raise fail(path, f"{label}: point at line {ln}", f"expected {width} numbers for {scalars[-1]}"
                                                            f"{' ([w w*x w*y w*z])' if rational else ''}, "
                                                            f"got {len(body)}")
        flat[i] = _floats(path, f"{label}: point at line {ln}", body)
    order = tuple(range(dims))[::-1]  # u fastest
    net = flat.reshape(tuple(lengths[::-1]) + (width,)).transpose(order + (dims,))
    if rational:
        w = net[..., 0]
        bad = np.argwhere(~(np.isfinite(w) & (w > 0)))
        if bad.size:
            i = tuple(bad[0])
            raise fail(path, f"{label}: weights", f"every weight must be > 0, got {w[i]:g} at index {list(i)}")
        cps, weights = net[..., 1:] / w[..., None], w
    else:
        cps, weights = net, None
    for a in range(dims):
        if periodic[a]:
            k = orders[a]
            idx = np.r_[np.arange(lengths[a]), np.arange(k - 1)]
            cps = np.take(cps, idx, axis=a)
            weights = None if weights is None else np.take(weights, idx, axis=a)
    make = make_volume if dims == 3 else make_surface
    return make(path, [k - 1 for k in orders], knots, cps, weights, label=label), periodic


def _read_objects(path, kind, dims, noun):
    """Every `kind` (TRIVAR | SURFACE) object of the file -> (list of Volume | Surface, meta); ModelError when none."""
    tree = _tree(path, read_text(path))
    objects, periodic = [], []
    for i, (node, name) in enumerate(_walk(tree, kind=kind)):
        obj, per = _trivar(path, node, f"{kind}[{i}]" + (f" (object {name})" if name else ""), dims=dims)
        objects.append(obj)
        periodic.append([ax for ax, p in zip("uvw"[:dims], per, strict=True) if p])
    if not objects:
        raise fail(path, kind, f"no {noun} in the file: expected a [{kind} BSPLINE ...] or [{kind} BEZIER ...] object")
    return objects, {"units": None, "periodic_knots": periodic}


def read(path):
    """Every TRIVAR BSPLINE / BEZIER object in the file -> (list[Volume], meta)."""
    return _read_objects(path, "TRIVAR", 3, "volume")


def read_surfaces(path):
    """Every SURFACE BSPLINE / BEZIER object in the file -> (list[Surface], meta)."""
    return _read_objects(path, "SURFACE", 2, "surface")
