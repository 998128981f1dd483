"""Model files: a small registry of readers keyed by format, plus the volpuzzle JSON writer.

Each format module exposes NAME, EXTENSIONS, `detect(path, head: bytes) -> bool` and `read(path) -> (list[Volume],
meta dict)`. Detection goes by content first (the first HEAD_BYTES of the file) and falls back to the extension, so
a renamed file still loads and a mislabelled one is not misread.

Surfaces (for `model.shell`) go through the same registry: a format module that can hold surfaces also exposes
`read_surfaces(path) -> (list[Surface], meta dict)`.

Every failure is a ModelError whose message starts with the file path and names the field at fault.
"""

import os
import stat

import numpy as np

from ..errors import ExportError, ModelError
from ..spline.knots import insert_knot
from ..spline.volume import Volume

HEAD_BYTES = 65536
# Largest coordinate or knot a model may have, in its own units: far beyond any printable object, and small enough
# that areas, volumes and Jacobians of it stay finite in double precision (1e308 made every figure inf or NaN).
MAX_COORDINATE = 1e9
UNITS = ("mm", "cm", "m", "in")


# --- helpers shared by the format modules ---------------------------------------------------------------------
def regular_file_problem(path):
    """None for a regular file (after symlinks), else what it is instead: 'no such file', 'a folder', 'a FIFO
    (named pipe)' ... Reading a FIFO or a device would block or never end, so such paths are refused by name."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "no such file"
    except (OSError, ValueError) as e:  # ValueError: a NUL byte in the path
        return f"cannot be opened ({getattr(e, 'strerror', None) or e})"
    if stat.S_ISREG(st.st_mode):
        return None
    if stat.S_ISDIR(st.st_mode):
        return "is a directory, not a file"
    kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode)
            else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "not a file")
    return f"is {kind}, not a regular file"


def fail(path, field, message):
    """A ModelError 'PATH: FIELD: MESSAGE' (field may be empty)."""
    return ModelError(f"{path}: {field}: {message}" if field else f"{path}: {message}")


def read_text(path):
    """The whole text file (undecodable bytes replaced, so that the parser names what is wrong); ModelError when it
    cannot be read."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.read()
    except OSError as e:
        raise fail(path, "", f"cannot be read ({e.strerror})") from None


def parse_floats(path, field, text):
    """Whitespace-separated numbers -> (n,) float array; a bad token names the field and the token."""
    tokens = text.split()
    try:
        return np.array([float(t) for t in tokens], dtype=float)
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise fail(path, field, f"expected numbers, got {bad!r}") from None


def _is_float(t):
    try:
        float(t)
        return True
    except ValueError:
        return False


def _clamp_left(p, U, P):
    a = U[p]
    s = int(np.sum(U == a))
    lead = int(np.sum(U < a))
    if s > p:
        return U[lead:], P[lead:]
    U, P = insert_knot(U, p, P, a, p - s)
    # With a of multiplicity p, the p+1 functions alive right of a match the clamped basis there (their last
    # polynomial piece does not depend on the knots left of a), so the knots left of a can become a.
    return np.concatenate([[a], U[lead:]]), P[lead - 1:]


def clamp_axis(degree, knots, hpoints, axis):
    """Turn a floating (unclamped) knot vector into the clamped one describing the same volume on its domain
    [knots[p], knots[n]]. hpoints (n_u, n_v, n_w, 4) homogeneous; returns (knots, hpoints)."""
    U = np.asarray(knots, float)
    P = np.moveaxis(np.asarray(hpoints, float), axis, 0)
    U, P = _clamp_left(degree, U, P)
    U, P = _clamp_left(degree, -U[::-1], P[::-1])  # the right end, mirrored
    return -U[::-1], np.moveaxis(P[::-1], 0, axis)


def make_volume(path, degrees, knots, points, weights=None, label=""):
    """Build a Volume from parsed data, clamping floating knot vectors; ModelErrors get the path (and patch label)
    as a prefix. points (n_u, n_v, n_w, 3) Cartesian, weights (n_u, n_v, n_w) or None."""
    where = f"{path}: {label}: " if label else f"{path}: "
    _check_magnitudes(where, knots, points, weights)
    try:
        vol = _volume_clamped(degrees, knots, points, weights)
    except ModelError as e:
        raise ModelError(where + str(e)) from None
    return vol


def _check_magnitudes(where, knots, points, weights):
    for field, values in (("control points", points), *((f"knots[{a}]", k) for a, k in enumerate(knots))):
        try:
            a = np.asarray(values, dtype=float)
        except (TypeError, ValueError):
            continue  # the Volume reports the shape
        with np.errstate(invalid="ignore"):
            big = np.abs(a[np.isfinite(a)]) > MAX_COORDINATE
        if big.any():
            worst = float(np.max(np.abs(a[np.isfinite(a)])))
            raise ModelError(f"{where}{field}: a value of magnitude {worst:.3g} is too large to compute with (got "
                             f"{worst:.3g}, expected at most {MAX_COORDINATE:g} in the model's units)")
    if weights is not None:
        w = np.asarray(weights, dtype=float)
        ok = w[np.isfinite(w) & (w > 0)]
        if ok.size and float(ok.max()) > MAX_COORDINATE * float(ok.min()):
            raise ModelError(f"{where}weights: range {float(ok.min()):.3g} to {float(ok.max()):.3g} is too wide to "
                             f"compute with (expected a ratio of at most {MAX_COORDINATE:g})")


def _volume_clamped(degrees, knots, points, weights):
    try:
        return Volume(degrees, knots, points, weights)
    except ModelError as e:
        if "only clamped" not in str(e):
            raise
    # The rest of the validation passed; only the end knots are unclamped: convert (exact on the domain).
    degrees = tuple(int(d) for d in degrees)
    cps = np.asarray(points, float)
    w = np.ones(cps.shape[:3]) if weights is None else np.asarray(weights, float)
    hp = np.concatenate([cps * w[..., None], w[..., None]], axis=-1)
    knots = [np.asarray(k, float) for k in knots]
    for a in range(3):
        p, k = degrees[a], knots[a]
        if not (np.all(k[:p + 1] == k[0]) and np.all(k[-p - 1:] == k[-1])):
            knots[a], hp = clamp_axis(p, k, hp, a)
    vol = Volume.from_homogeneous(degrees, knots, hp)
    if weights is not None and vol.weights is None:
        vol = Volume(vol.degrees, vol.knots, vol.control_points, np.ones(vol.shape))
    return vol


_SLAB_KNOTS = np.array([0.0, 0.0, 1.0, 1.0])


def make_surface(path, degrees, knots, points, weights=None, label=""):
    """Build a Surface from parsed data, as make_volume does (floating knot vectors clamped, errors prefixed).
    points (n_u, n_v, 3) Cartesian, weights (n_u, n_v) or None."""
    from ..spline.surface import Surface

    pts = np.asarray(points, dtype=float)
    if pts.ndim != 3 or pts.shape[2] != 3:
        where = f"{label}: " if label else ""
        raise fail(path, "", f"{where}control points: expected shape (n_u, n_v, 3), got {pts.shape}")
    w = None if weights is None else np.stack([np.asarray(weights, float)] * 2, axis=2)
    # the surface as the w = 0 slab of a volume of degree 1 along w: one home for validation and clamping
    vol = make_volume(path, list(degrees) + [1], list(knots) + [_SLAB_KNOTS], np.stack([pts, pts], axis=2), w, label)
    return Surface.from_volume_slab(vol)


# --- registry ---------------------------------------------------------------------------------------------------
def _formats():
    from . import geomdl_json, gismo, irit, nurbs_text, vpjson

    return [vpjson, geomdl_json, gismo, irit, nurbs_text]


def _surface_formats():
    from . import geomdl_json, gismo, irit, nurbs_text

    return [nurbs_text, geomdl_json, gismo, irit]


def format_names():
    return [f.NAME for f in _formats()]


def _check_file(path):
    path = os.fspath(path)
    problem = regular_file_problem(path)
    if problem == "no such file":
        raise ModelError(f"{path}: no such file (expected a model file: .json, .xml or .itd)")
    if problem:
        raise ModelError(f"{path}: {problem}, expected a model file")
    try:
        with open(path, "rb") as f:
            head = f.read(HEAD_BYTES)
    except OSError as e:
        raise ModelError(f"{path}: cannot be read ({e.strerror})") from None
    if not head.strip():
        raise ModelError(f"{path}: the file is empty, expected a volume model")
    return path, head


def detect_format(path, head=None):
    """The format module for a file: by content first, then by extension; ModelError if neither fits."""
    if head is None:
        path, head = _check_file(path)
    fmts = _formats()
    for f in fmts:
        if f.detect(path, head):
            return f
    ext = os.path.splitext(path)[1].lower()
    for f in fmts:
        if ext in f.EXTENSIONS and getattr(f, "EXTENSION_FALLBACK", True):
            return f
    if ext == ".json":
        raise ModelError(
            f"{path}: not a volume model: expected a volpuzzle JSON (\"format\": \"volpuzzle-nurbs\") or a geomdl "
            f"JSON (a \"shape\" object of \"type\": \"volume\")")
    supported = ", ".join(f"{f.NAME} ({'/'.join(f.EXTENSIONS)})" for f in fmts)
    from ..spec import MESH_SUFFIXES

    if ext in MESH_SUFFIXES:  # `info` of a mesh: it is a model here too, only not a volume one
        raise ModelError(
            f"{path}: a {ext} file is a triangle mesh, not a volume model (expected {supported}; for a puzzle "
            f"of this mesh write model: {{mesh: FILE, cage: box}} in a spec)")
    raise ModelError(f"{path}: unrecognised model format; supported: {supported}")


def _read(path):
    path, head = _check_file(path)
    fmt = detect_format(path, head)
    vols, meta = fmt.read(path)
    if not vols:
        raise ModelError(f"{path}: no volume in the file (expected a trivariate B-spline or NURBS)")
    meta = dict(meta)
    meta.setdefault("units", None)
    meta["format"] = fmt.NAME
    meta["patches"] = len(vols)
    meta["path"] = path
    return vols, meta


def _pick(path, vols, patch):
    n = len(vols)
    if isinstance(patch, bool) or not isinstance(patch, (int, np.integer)):
        raise ModelError(f"{path}: patch: expected an integer from 0 to {n - 1}, got {patch!r}")
    if not 0 <= patch < n:
        raise ModelError(f"{path}: patch: {int(patch)} is out of range; the file has {n} patch{'es' if n != 1 else ''} "
                         f"(expected 0 to {n - 1})")
    return vols[int(patch)]


def read_patches(path):
    """Every volume patch in the file -> list[Volume] (at least one)."""
    return _read(path)[0]


def load_model_with_meta(path, patch=0):
    """-> (Volume, {'format', 'patches', 'units' (str or None), 'path'})."""
    vols, meta = _read(path)
    return _pick(meta["path"], vols, patch), meta


def load_model(path, patch=0):
    """Read one patch of a model file in any supported format (SPEC section 2) -> Volume."""
    return load_model_with_meta(path, patch)[0]


def load_surface_with_meta(path, patch=0):
    """One surface patch of a surface file (.nurbs text, G+Smo TensorBSpline2/TensorNurbs2, IRIT SURFACE, geomdl
    surface JSON) -> (Surface, {'format', 'patches', 'units', 'path'})."""
    path, head = _check_file(path)
    fmt = detect_format(path, head)
    if not hasattr(fmt, "read_surfaces"):
        names = ", ".join(f.NAME for f in _surface_formats())
        raise ModelError(f"{path}: a {fmt.NAME} file holds volumes, not surfaces (expected a surface file: {names})")
    surfs, meta = fmt.read_surfaces(path)
    meta = dict(meta)
    meta.setdefault("units", None)
    meta.update(format=fmt.NAME, patches=len(surfs), path=path)
    return _pick(path, surfs, patch), meta


def load_surface(path, patch=0):
    """Read one surface of a surface file -> Surface."""
    return load_surface_with_meta(path, patch)[0]


def save_model(vol, path, units="mm"):
    """Write vol as volpuzzle JSON (deterministic bytes, full float precision)."""
    from .vpjson import dumps

    if units not in UNITS:
        raise ExportError(f"{path}: units: expected one of {', '.join(UNITS)}, got {units!r}")
    text = dumps(vol, units)
    path = os.fspath(path)
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
        os.replace(tmp, path)
    except OSError as e:
        try:
            os.remove(tmp)
        except OSError:
            pass
        raise ExportError(f"{path}: cannot write the model ({e.strerror})") from None
    return path


__all__ = ["load_model", "load_model_with_meta", "read_patches", "load_surface", "load_surface_with_meta",
           "save_model", "detect_format", "format_names"]
