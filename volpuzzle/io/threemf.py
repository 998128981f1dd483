"""3MF writing and reading through lib3mf, the 3MF consortium's reference library.

trimesh's own 3MF writer drops colours and its files fail lib3mf's strict mode, so pieces, the assembled
puzzle and the plates go through lib3mf. Geometry crosses the ctypes boundary as numpy buffers
(zero-copy), not as lists of ctypes structures, which is what makes writing ~1 M triangles/s possible.

lib3mf stamps every object, build item and the build with a random UUID (production extension) on
creation; we overwrite them with UUIDs derived from the object's name and position, so the same input
gives byte-identical files. The zip entries already carry a fixed 1980 date.

lib3mf lets go of the GIL while it works (ctypes), so the export stage writes 3MF files on a worker thread beside
its other work; one lock keeps lib3mf itself to one thread at a time, since it does not promise more.
"""

from __future__ import annotations

import ctypes
import threading
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import ExportError, ModelError

__all__ = ["write_3mf", "read_3mf", "read_triangle_colors", "UNITS", "DEFAULT_ACCENT"]

UNITS = ("micron", "millimeter", "centimeter", "inch", "foot", "meter")
# A neutral dark grey for triangles marked as the second material (e.g. pins), when no colour is given.
DEFAULT_ACCENT = (64, 64, 64)
# Fixed namespace so UUIDs depend only on what is written.
_NAMESPACE = uuid.UUID("6c1f3f0e-3a51-4f53-9d3c-7a0c2b6e5a11")

_wrapper = None
_LOCK = threading.Lock()


def _lib():
    """(lib3mf module, its ctypes binding module, a Wrapper) — loaded once, on first use."""
    global _wrapper
    import lib3mf
    from lib3mf import Lib3MF as L

    if _wrapper is None:
        _wrapper = lib3mf.get_wrapper()
    return lib3mf, L, _wrapper


def _unit_enum(L, unit: str):
    table = {
        "micron": L.ModelUnit.MicroMeter,
        "millimeter": L.ModelUnit.MilliMeter,
        "centimeter": L.ModelUnit.CentiMeter,
        "inch": L.ModelUnit.Inch,
        "foot": L.ModelUnit.Foot,
        "meter": L.ModelUnit.Meter,
    }
    if unit not in table:
        raise ExportError(f"3MF unit: got {unit!r}, expected one of {', '.join(UNITS)}")
    return table[unit]


def _unit_name(L, value) -> str:
    names = {
        int(L.ModelUnit.MicroMeter): "micron",
        int(L.ModelUnit.MilliMeter): "millimeter",
        int(L.ModelUnit.CentiMeter): "centimeter",
        int(L.ModelUnit.Inch): "inch",
        int(L.ModelUnit.Foot): "foot",
        int(L.ModelUnit.Meter): "meter",
    }
    return names.get(int(value), "millimeter")


def _transform(L, t: np.ndarray | None):
    """(3, 4) [R | t] acting on column vectors -> lib3mf Transform (row-vector convention, 4 rows of 3)."""
    out = L.Transform()
    m = np.eye(3, 4) if t is None else np.asarray(t, dtype=np.float64)
    if m.shape != (3, 4) or not np.all(np.isfinite(m)):
        raise ExportError(f"3MF transform: got shape {m.shape} or non-finite values, expected a finite (3, 4) [R | t]")
    rows = np.vstack([m[:, :3].T, m[:, 3]])
    for i in range(4):
        for j in range(3):
            out.Fields[i][j] = float(rows[i, j])
    return out


def _from_transform(t) -> np.ndarray:
    """lib3mf Transform -> (3, 4) [R | t] for column vectors."""
    rows = np.array([[t.Fields[i][j] for j in range(3)] for i in range(4)], dtype=np.float64)
    return np.hstack([rows[:3].T, rows[3:].T])


def _set_geometry(L, w, mesh_obj, vertices: np.ndarray, faces: np.ndarray) -> None:
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.uint32)
    pv = (L.Position * len(v)).from_buffer(v) if len(v) else (L.Position * 0)()
    pf = (L.Triangle * len(f)).from_buffer(f) if len(f) else (L.Triangle * 0)()
    w.checkError(mesh_obj, w.lib.lib3mf_meshobject_setgeometry(
        mesh_obj._handle, ctypes.c_uint64(len(v)), pv, ctypes.c_uint64(len(f)), pf))


_TRI_PROPS = np.dtype([("rid", "<u4"), ("pids", "<u4", (3,))])


def _set_triangle_materials(L, w, mesh_obj, resource_id, pids: np.ndarray) -> None:
    """resource_id: one resource for all triangles, or (m,) one per triangle."""
    props = np.zeros(len(pids), dtype=_TRI_PROPS)
    props["rid"] = resource_id
    props["pids"] = pids if pids.ndim == 2 else pids[:, None]
    buf = (L.TriangleProperties * len(props)).from_buffer(props)
    w.checkError(mesh_obj, w.lib.lib3mf_meshobject_setalltriangleproperties(
        mesh_obj._handle, ctypes.c_uint64(len(props)), buf))


def _check_object(path, k, obj):
    if len(obj) != 5:
        raise ExportError(f"{path}: object {k}: expected (name, vertices, faces, rgb, transform), got {len(obj)} items")
    name, vertices, faces, rgb, transform = obj
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
        raise ExportError(f"{path}: object {name!r}: vertices must be finite (n, 3), got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ExportError(f"{path}: object {name!r}: faces must be a non-empty (m, 3) index array, got shape {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ExportError(f"{path}: object {name!r}: face indices must lie in [0, {len(v) - 1}], "
                          f"got [{f.min()}, {f.max()}]")
    if rgb is not None:
        c = np.asarray(rgb)
        if c.shape != (3,) or c.min() < 0 or c.max() > 255:
            raise ExportError(f"{path}: object {name!r}: colour must be 3 values in 0..255, got {rgb!r}")
    return str(name), v, f, rgb, transform


def write_3mf(path, objects: Sequence, unit: str = "millimeter", materials: Sequence | None = None,
              accent_rgb=DEFAULT_ACCENT, accent_name: str = "pins", colors: Sequence | None = None) -> Path:
    """Write one mesh object per entry, each placed by its own build item, each with one colour.

    objects: sequence of (name, vertices (n, 3) float, faces (m, 3) int, rgb (3,) uint8 | None,
    transform (3, 4) [R | t] | None). materials: None, or per object None | (m,) int array marking each
    triangle 0 = the object's colour, 1 = the second material (accent_rgb, named accent_name: what it marks).
    Materials are named for what they are: "piece <name>" for an object's own colour.
    colors: None, or per object None | (m, 3) int array of per-triangle colours or (m, 3 corners, 3) colours at the
    corners (a texture), -1 where the triangle keeps its material. Those go into one colour group (3MF materials
    extension, m:colorgroup) that the triangles reference; the object keeps its base material for slicers that only
    read that.
    Raises ExportError naming the file on bad input or a failed write. Same input -> same bytes.
    """
    path = Path(path)
    objects = [_check_object(path, k, o) for k, o in enumerate(objects)]
    if not objects:
        raise ExportError(f"{path}: nothing to write (got 0 objects, expected at least 1)")
    if materials is not None and len(materials) != len(objects):
        raise ExportError(f"{path}: materials: got {len(materials)} entries, expected one per object ({len(objects)})")
    if colors is not None and len(colors) != len(objects):
        raise ExportError(f"{path}: colors: got {len(colors)} entries, expected one per object ({len(objects)})")
    with _LOCK:
        _write_model(path, objects, unit, materials, accent_rgb, accent_name, colors)
    return path


def _color_ids(w, cache, rgb):
    """Colour-group property ids for (k, 3) colours, adding each distinct colour once to the file's group."""
    group, ids = cache["group"], cache["ids"]
    keys = (rgb[:, 0].astype(np.int64) << 16) | (rgb[:, 1].astype(np.int64) << 8) | rgb[:, 2].astype(np.int64)
    uniq, inverse = np.unique(keys, return_inverse=True)
    pid = np.empty(len(uniq), dtype=np.uint32)
    for i, key in enumerate(uniq.tolist()):
        if key not in ids:
            ids[key] = group.AddColor(w.RGBAToColor((key >> 16) & 255, (key >> 8) & 255, key & 255, 255))
        pid[i] = ids[key]
    return group.GetResourceID(), pid[inverse.reshape(-1)]


def _write_model(path, objects, unit, materials, accent_rgb, accent_name="pins", colors=None) -> None:
    _, L, w = _lib()
    try:
        model = w.CreateModel()
        model.SetUnit(_unit_enum(L, unit))
        model.SetBuildUUID(str(uuid.uuid5(_NAMESPACE, f"build/{len(objects)}")))
        group = None
        accent_pid = None
        color_cache = {}
        if any(o[3] is not None for o in objects) or materials is not None:
            group = model.AddBaseMaterialGroup()
        if colors is not None and any(c is not None for c in colors):
            # before the objects: a resource must come before the objects that reference it
            color_cache.update(group=model.AddColorGroup(), ids={})
        for k, (name, v, f, rgb, transform) in enumerate(objects):
            mesh_obj = model.AddMeshObject()
            mesh_obj.SetName(name)
            mesh_obj.SetUUID(str(uuid.uuid5(_NAMESPACE, f"object/{k}/{name}")))
            _set_geometry(L, w, mesh_obj, v, f)
            own_pid = None
            if rgb is not None:
                r, g, b = (int(x) for x in rgb)
                own_pid = group.AddMaterial(f"piece {name}", w.RGBAToColor(r, g, b, 255))
                mesh_obj.SetObjectLevelProperty(group.GetResourceID(), own_pid)
            mat = None if materials is None else materials[k]
            if mat is not None:
                mat = np.asarray(mat)
                if mat.shape != (len(f),) or not np.isin(mat, (0, 1)).all():
                    raise ExportError(f"{path}: object {name!r}: materials must be {len(f)} values of 0 or 1, "
                                      f"got shape {mat.shape}")
                if own_pid is None:
                    raise ExportError(f"{path}: object {name!r}: a second material needs the object's own colour too")
                if accent_pid is None:
                    r, g, b = (int(x) for x in accent_rgb)
                    accent_pid = group.AddMaterial(str(accent_name), w.RGBAToColor(r, g, b, 255))
            tex = None if colors is None else colors[k]
            if mat is not None or tex is not None:
                if own_pid is None:
                    raise ExportError(f"{path}: object {name!r}: per-triangle colours need the object's own colour too")
                pids = np.full((len(f), 3), own_pid, dtype=np.uint32)
                if mat is not None:
                    pids[:] = np.where(mat == 1, accent_pid, own_pid).astype(np.uint32)[:, None]
                rids = np.full(len(f), group.GetResourceID(), dtype=np.uint32)
                if tex is not None:
                    tex = np.asarray(tex)
                    if tex.shape == (len(f), 3):
                        tex = np.repeat(tex[:, None, :], 3, axis=1)
                    if tex.shape != (len(f), 3, 3) or tex.max(initial=0) > 255:
                        raise ExportError(f"{path}: object {name!r}: colors must be ({len(f)}, 3) or ({len(f)}, 3, 3) "
                                          f"values in 0..255 or -1, got shape {tex.shape}")
                    on = tex[:, 0, 0] >= 0
                    if np.any(on):
                        rid, cpid = _color_ids(w, color_cache, tex[on].reshape(-1, 3))
                        rids[on], pids[on] = rid, cpid.reshape(-1, 3)
                _set_triangle_materials(L, w, mesh_obj, rids, pids)
            item = model.AddBuildItem(mesh_obj, _transform(L, transform))
            item.SetUUID(str(uuid.uuid5(_NAMESPACE, f"item/{k}/{name}")))
        writer = model.QueryWriter("3mf")
        path.parent.mkdir(parents=True, exist_ok=True)
        _write_through_python(L, w, writer, path)
    except ExportError:
        raise
    except Exception as e:  # lib3mf raises ELib3MFException; OSError from mkdir
        raise ExportError(f"{path}: could not write 3MF: {e}") from e


def _write_through_python(L, w, writer, path: Path) -> None:
    """The 3MF stream written by a Python file object. lib3mf's own file writer, on a full disk, leaves a C++
    exception that escapes later from a destructor ("terminate called", SIGABRT); through callbacks lib3mf never
    sees the failure: the first OSError is kept, later chunks are dropped, and the error is raised here."""
    failed = []
    with open(path, "wb") as f:
        def write(data, size, _user):
            if not failed:
                try:
                    f.write(ctypes.string_at(data, size))
                except OSError as e:
                    failed.append(e)

        def seek(position, _user):
            if not failed:
                try:
                    f.seek(position)
                except OSError as e:
                    failed.append(e)

        write_cb, seek_cb = L.WriteCallback(write), L.SeekCallback(seek)  # kept alive until the call returns
        w.checkError(writer, w.lib.lib3mf_writer_writetocallback(writer._handle, write_cb, seek_cb, None))
    if failed:
        try:
            path.unlink()  # a partial 3MF is a corrupt one
        except OSError:
            pass
        e = failed[0]
        raise OSError(e.errno, e.strerror or str(e), str(path)) from e


def _get_geometry(L, w, mesh_obj):
    nv = mesh_obj.GetVertexCount()
    nt = mesh_obj.GetTriangleCount()
    v = np.zeros((nv, 3), dtype=np.float32)
    f = np.zeros((nt, 3), dtype=np.uint32)
    needed = ctypes.c_uint64(0)
    if nv:
        w.checkError(mesh_obj, w.lib.lib3mf_meshobject_getvertices(
            mesh_obj._handle, ctypes.c_uint64(nv), needed, (L.Position * nv).from_buffer(v)))
    if nt:
        w.checkError(mesh_obj, w.lib.lib3mf_meshobject_gettriangleindices(
            mesh_obj._handle, ctypes.c_uint64(nt), needed, (L.Triangle * nt).from_buffer(f)))
    return v.astype(np.float64), f.astype(np.int64)


def _object_rgb(model, mesh_obj):
    """The object's own colour from its object-level base material or colour group, or None."""
    rid, pid, has = mesh_obj.GetObjectLevelProperty()
    if not has:
        return None
    try:
        group = model.GetBaseMaterialGroupByID(rid)
        c = group.GetDisplayColor(pid)
    except Exception:
        try:
            c = model.GetColorGroupByID(rid).GetColor(pid)
        except Exception:
            return None
    return np.array([c.Red, c.Green, c.Blue], dtype=np.uint8)


def read_3mf(path, strict: bool = True, with_units: bool = False):
    """Read every build item of a 3MF file -> list of (name, vertices (n, 3) float64, faces (m, 3) int64,
    rgb (3,) uint8 | None), vertices in the file's units with the build item's transform applied.

    strict: lib3mf's strict mode, and any reader warning is an error. Raises ModelError naming the file.
    with_units: also return the unit name, as (objects, unit).
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: no such 3MF file")
    with _LOCK:
        return _read_model(path, strict, with_units)


def _open_model(w, path, strict):
    """lib3mf's model of the file -> model; ModelError when unreadable. strict: lib3mf's strict mode, which raises
    on what it would otherwise only warn about."""
    try:
        model = w.CreateModel()
        reader = model.QueryReader("3mf")
        reader.SetStrictModeActive(bool(strict))
        reader.ReadFromFile(str(path))
    except Exception as e:
        raise ModelError(f"{path}: not a readable 3MF file: {e}") from e
    return model


def _read_model(path, strict, with_units):
    _, L, w = _lib()
    model = _open_model(w, path, strict)
    out = []
    items = model.GetBuildItems()
    k = 0
    while items.MoveNext():
        item = items.GetCurrent()
        res = item.GetObjectResource()
        try:
            mesh_obj = model.GetMeshObjectByID(res.GetResourceID())
        except Exception as e:
            raise ModelError(f"{path}: build item {k} is not a mesh object (components are not supported): {e}") from e
        v, f = _get_geometry(L, w, mesh_obj)
        if item.HasObjectTransform():
            t = _from_transform(item.GetObjectTransform())
            v = v @ t[:, :3].T + t[:, 3]
        name = mesh_obj.GetName() or f"object-{k}"
        out.append((name, v, f, _object_rgb(model, mesh_obj)))
        k += 1
    if with_units:
        return out, _unit_name(L, model.GetUnit())
    return out


def read_triangle_colors(path, strict: bool = True):
    """The display colour at the corners of every triangle of every build item -> {object name: (m, 3, 3) uint8}: from
    its colour-group or base-material property, else the object's own colour (grey when it has none)."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: no such 3MF file")
    with _LOCK:
        _, L, w = _lib()
        model = _open_model(w, path, strict)
        out = {}
        items = model.GetBuildItems()
        while items.MoveNext():
            res = items.GetCurrent().GetObjectResource()
            mesh_obj = model.GetMeshObjectByID(res.GetResourceID())
            n = mesh_obj.GetTriangleCount()
            props = np.zeros(n, dtype=_TRI_PROPS)
            needed = ctypes.c_uint64(0)
            w.checkError(mesh_obj, w.lib.lib3mf_meshobject_getalltriangleproperties(
                mesh_obj._handle, ctypes.c_uint64(n), needed, (L.TriangleProperties * n).from_buffer(props)))
            own = _object_rgb(model, mesh_obj)
            rgb = np.tile(np.array((128, 128, 128) if own is None else own, np.uint8), (n, 3, 1))
            rid_corner = np.repeat(props["rid"][:, None], 3, axis=1)
            lookup = {}
            for rid, pid in set(zip(rid_corner.ravel().tolist(), props["pids"].ravel().tolist(), strict=True)):
                if rid == 0:
                    continue
                try:
                    c = model.GetColorGroupByID(rid).GetColor(pid)
                except Exception:
                    try:
                        c = model.GetBaseMaterialGroupByID(rid).GetDisplayColor(pid)
                    except Exception:
                        continue
                lookup[(rid, pid)] = (c.Red, c.Green, c.Blue)
            for key, c in lookup.items():
                rgb[(rid_corner == key[0]) & (props["pids"] == key[1])] = c
            out[mesh_obj.GetName()] = rgb
        return out
