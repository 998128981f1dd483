"""G+Smo XML: <xml> root holding <Geometry> elements; TensorBSpline3 and TensorNurbs3 are read as volumes,
TensorBSpline2 and TensorNurbs2 as surfaces (for `model.shell`).

<Geometry type="TensorBSpline3" id="..">
  <Basis type="TensorBSplineBasis3"> three <Basis type="BSplineBasis" index="0|1|2"><KnotVector degree="p">..
  <coefs geoDim="3"> x y z ... </coefs>
TensorNurbs3 wraps that basis in <Basis type="TensorNurbsBasis3"> together with <weights>.

Coefficients run u fastest: flat index = i + n_u * (j + n_v * k) (checked against the IRIT and geomdl versions of the
same volumes). Numbers are ASCII or base64 (format="B64Float64" etc., little-endian). A <MultiPatch> that lists
geometry ids gives the patch order; geometries it does not list follow in file order.

No entity expansion: the XML goes through defusedxml, which refuses DOCTYPE and ENTITY declarations in any
encoding (a text search for "<!ENTITY" misses them in UTF-16).
"""

import base64
import binascii
import re
import xml.etree.ElementTree as ET

import defusedxml
import defusedxml.ElementTree as SafeET
import numpy as np

from . import fail, make_surface, make_volume, parse_floats

NAME = "gismo-xml"
EXTENSIONS = (".xml",)
SUPPORTED = ("TensorBSpline3", "TensorNurbs3")
SURFACES = ("TensorBSpline2", "TensorNurbs2")
_B64 = {"b64float64": "<f8", "b64float32": "<f4", "b64int32": "<i4", "b64int64": "<i8",
        "b64uint32": "<u4", "b64uint64": "<u8"}
_DECL = re.compile(rb"<\?xml[^>]*\?>")


def detect(_path, head):
    body = _DECL.sub(b"", head.lstrip(b"\xef\xbb\xbf"))
    body = re.sub(rb"<!--.*?-->", b"", body, flags=re.S).lstrip()
    return body.startswith(b"<xml") and body[4:5] in (b">", b" ", b"\t", b"\n", b"\r", b"/")


def _parse(path):
    with open(path, "rb") as f:
        raw = f.read()
    # A comment before '<?xml ...?>' is common in G+Smo files and makes the declaration illegal for a strict
    # parser. The declaration names the encoding, so it is moved to the front rather than dropped.
    if not raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        decl = _DECL.search(raw)
        if decl is not None and decl.start() > 0:
            raw = decl.group() + raw[:decl.start()] + raw[decl.end():]
    try:
        return SafeET.fromstring(raw, forbid_dtd=True)
    except defusedxml.DefusedXmlException:
        raise fail(path, "", "XML with DOCTYPE or ENTITY declarations is not accepted (no entity expansion)") from None
    except ET.ParseError as e:
        line, col = e.position
        raise fail(path, "", f"invalid or truncated XML at line {line} column {col + 1}: "
                             f"{str(e).split(':')[0]}") from None


def _numbers(path, field, el):
    text = el.text or ""
    fmt = (el.get("format") or "ascii").lower()
    if fmt == "ascii":
        return parse_floats(path, field, text)
    if fmt not in _B64:
        raise fail(path, field, f"unknown number format {el.get('format')!r}; expected ascii or one of "
                                f"B64Float64, B64Float32, B64Int32, B64Int64, B64UInt32, B64UInt64")
    try:
        data = base64.b64decode("".join(text.split()), validate=True)
    except (binascii.Error, ValueError):
        raise fail(path, field, f"invalid base64 data (format {el.get('format')})") from None
    dt = np.dtype(_B64[fmt])
    if len(data) % dt.itemsize:
        raise fail(path, field, f"base64 data of {len(data)} bytes is not a whole number of {dt.itemsize}-byte "
                                f"values (format {el.get('format')})")
    return np.frombuffer(data, dtype=dt).astype(float)


def _bspline_basis(path, basis, label, dims=3):
    """TensorBSplineBasis3 (or 2, dims) element -> (degrees, knots)."""
    kids = [b for b in basis.findall("Basis")]
    if len(kids) != dims:
        raise fail(path, f"{label}.Basis", f"expected {('two', 'three')[dims - 2]} BSplineBasis children, "
                                           f"got {len(kids)}")
    try:
        keys = [int(b.get("index", a)) for a, b in enumerate(kids)]
    except ValueError:
        raise fail(path, f"{label}.Basis", f"index: expected {' or '.join(map(str, range(dims)))}") from None
    kids = [b for _, b in sorted(zip(keys, kids, strict=True), key=lambda kb: kb[0])]
    degrees, knots = [], []
    for a, b in enumerate(kids):
        field = f"{label}.Basis[{a}]"
        if b.get("type") != "BSplineBasis":
            raise fail(path, field, f"type {b.get('type')!r} is not supported; expected BSplineBasis")
        kv = b.find("KnotVector")
        if kv is None:
            raise fail(path, field, "missing <KnotVector>")
        try:
            p = int(kv.get("degree"))
        except (TypeError, ValueError):
            raise fail(path, f"{field}.KnotVector.degree", f"expected an integer, got {kv.get('degree')!r}") from None
        degrees.append(p)
        knots.append(_numbers(path, f"{field}.KnotVector", kv))
    return degrees, knots


def _geometry(path, g, label, dims=3):
    gtype = g.get("type")
    supported = SUPPORTED if dims == 3 else SURFACES
    if gtype not in supported:
        what = "trivariate" if dims == 3 else "bivariate"
        raise fail(path, label, f"Geometry type {gtype!r} is not supported; supported: {', '.join(supported)} "
                                f"({what} tensor-product B-splines and NURBS)")
    basis = g.find("Basis")
    if basis is None:
        raise fail(path, label, "missing <Basis>")
    weights = None
    if gtype == f"TensorNurbs{dims}":
        if basis.get("type") != f"TensorNurbsBasis{dims}":
            raise fail(path, f"{label}.Basis", f"expected type TensorNurbsBasis{dims}, got {basis.get('type')!r}")
        wel = basis.find("weights")
        if wel is None:
            raise fail(path, f"{label}.Basis.weights", f"missing: a TensorNurbsBasis{dims} needs <weights>")
        weights = _numbers(path, f"{label}.Basis.weights", wel)
        basis = basis.find("Basis")
        if basis is None:
            raise fail(path, f"{label}.Basis", f"missing the inner TensorBSplineBasis{dims}")
    if basis.get("type") != f"TensorBSplineBasis{dims}":
        raise fail(path, f"{label}.Basis", f"expected type TensorBSplineBasis{dims}, got {basis.get('type')!r}")
    degrees, knots = _bspline_basis(path, basis, label, dims)
    sizes = [len(k) - p - 1 for k, p in zip(knots, degrees, strict=True)]
    for a, n in enumerate(sizes):
        if n < 1:
            raise fail(path, f"{label}.Basis[{a}].KnotVector",
                       f"{len(knots[a])} knots are too few for degree {degrees[a]} "
                       f"(need at least {2 * degrees[a] + 2})")
    count = int(np.prod(sizes))
    cel = g.find("coefs")
    if cel is None:
        raise fail(path, f"{label}.coefs", "missing <coefs>")
    coefs = _numbers(path, f"{label}.coefs", cel)
    gd = cel.get("geoDim")
    try:
        geo_dim = int(gd) if gd is not None else (coefs.size // count if count else 0)
    except ValueError:
        raise fail(path, f"{label}.coefs.geoDim", f"expected an integer, got {gd!r}") from None
    if geo_dim == 1:
        what = ("trivariate", "volume") if dims == 3 else ("bivariate", "surface")
        raise fail(path, f"{label}.coefs.geoDim", f"a scalar (geoDim 1) {what[0]} is a field, not a {what[1]} in "
                                                  "space; expected geoDim 3")
    if geo_dim != 3:
        raise fail(path, f"{label}.coefs.geoDim", f"expected 3 coordinates per coefficient, got {geo_dim}")
    if coefs.size != 3 * count:
        raise fail(path, f"{label}.coefs", f"expected {' x '.join(map(str, sizes))} = {count} control points "
                                           f"({3 * count} numbers) to fit the knot vectors, got {coefs.size} numbers")
    # u fastest: reverse the axes of the flat array
    order = tuple(range(dims))[::-1]
    pts = coefs.reshape(tuple(sizes[::-1]) + (3,)).transpose(order + (dims,))
    if weights is not None:
        if weights.size != count:
            raise fail(path, f"{label}.Basis.weights", f"expected {count} weights, got {weights.size}")
        weights = weights.reshape(tuple(sizes[::-1])).transpose(order)
    make = make_volume if dims == 3 else make_surface
    return make(path, degrees, knots, pts, weights, label=label)


def _ordered(path, root, geoms):
    """Geometry elements in patch order: MultiPatch references first, then the rest in file order."""
    by_id = {g.get("id"): g for g in geoms if g.get("id") is not None}
    order = []
    for mp in root.iter("MultiPatch"):
        pel = mp.find("patches")
        if pel is None:
            continue
        kind = pel.get("type", "id_range")
        nested = pel.findall("Geometry")
        if nested:
            order.extend(nested)
            continue
        try:
            ids = [int(t) for t in (pel.text or "").split()]
        except ValueError:
            raise fail(path, "MultiPatch.patches", "expected geometry ids (integers)") from None
        if kind == "id_range":
            if len(ids) != 2:
                raise fail(path, "MultiPatch.patches", f"id_range: expected two ids, got {len(ids)}")
            ids = list(range(ids[0], ids[1] + 1))
        for i in ids:
            g = by_id.get(str(i))
            if g is None:
                raise fail(path, "MultiPatch.patches", f"references geometry id {i}, which is not in the file")
            order.append(g)
    seen = set()
    out = []
    for g in order + geoms:
        if id(g) not in seen:
            seen.add(id(g))
            out.append(g)
    return out


def _patches(path, dims):
    """Every geometry of `dims` parameters (3: volumes, 2: surfaces) in the file, in patch order -> (list, meta)."""
    root = _parse(path)
    if root.tag != "xml":
        raise fail(path, "", f"expected a G+Smo file with an <xml> root element, got <{root.tag}>")
    geoms = list(root.iter("Geometry"))
    # Curves and surfaces (boundaries, say) may sit beside the volumes: only the types of `dims` are patches here.
    kept = [g for g in _ordered(path, root, geoms) if (g.get("type") or "").endswith(str(dims))]
    if not kept:
        found = sorted({g.get("type") or "?" for g in geoms})
        have = f" (found: {', '.join(found)})" if found else ""
        what, types = ("volume", SUPPORTED) if dims == 3 else ("surface", SURFACES)
        raise fail(path, "Geometry", f"no {what} in the file{have}; expected a Geometry of type {' or '.join(types)}")
    out = []
    for i, g in enumerate(kept):
        gid = g.get("id")
        out.append(_geometry(path, g, f"Geometry[{i}]" + (f" (id {gid})" if gid is not None else ""), dims=dims))
    return out, {"units": None}


def read(path):
    """Every TensorBSpline3 / TensorNurbs3 geometry in the file, in patch order -> (list[Volume], meta)."""
    return _patches(path, 3)


def read_surfaces(path):
    """Every TensorBSpline2 / TensorNurbs2 geometry in the file, in patch order -> (list[Surface], meta)."""
    return _patches(path, 2)
