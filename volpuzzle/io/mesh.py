"""Mesh input (STL, OBJ, PLY, OFF, 3MF, GLB) for the mesh-in-a-cage mode (paper section 5).

A mesh model must be ONE closed, consistently oriented solid with outward normals: it is intersected with the cage's
pieces, and a Boolean with an open or inside-out mesh gives garbage without failing. Anything else is refused with a
ModelError that names the file, what is wrong (counts of open edges, non-manifold edges, inconsistently oriented edges,
bodies) and where (a point near the first fault, in the file's coordinates), or repaired first when asked.

STL is read by our own reader rather than trimesh's: trimesh silently returns an empty mesh for a binary file whose
triangle count disagrees with its size, or for an ASCII file without `endsolid`, and raises a bare numpy error on a
facet with four vertices; users deserve the file, the line and the reason. STL facet normals are ignored (every
slicer recomputes them from the vertex order), so a missing, zero, wrong or NaN normal is not an error.
Other formats go through trimesh.load, with every exception turned into a ModelError.
"""

import os
import struct
from dataclasses import dataclass

import numpy as np
import trimesh

from ..errors import ModelError
from ..geometry import joined, unique_pairs
from . import regular_file_problem

EXTENSIONS = (".stl", ".obj", ".ply", ".off", ".3mf", ".glb")
_TRIMESH_TYPES = {".obj": "obj", ".ply": "ply", ".off": "off", ".3mf": "3mf", ".glb": "glb"}

__all__ = ["EXTENSIONS", "load_mesh", "load_mesh_scaled", "read_mesh", "mesh_from_bytes", "mesh_problems", "check_mesh",
           "repair_mesh", "simplify_dense", "DENSE_TRIANGLES"]


def _err(path, message):
    return ModelError(f"{path}: {message}")


# --- STL ------------------------------------------------------------------------------------------------------------
def _read_stl(path, data):
    """bytes of an STL file -> triangles (n, 3, 3) float64, or ModelError."""
    size = len(data)
    if size >= 84:
        (count,) = struct.unpack("<I", data[80:84])
        if 84 + 50 * count == size:
            return _read_stl_binary(data, count)
    if data.lstrip()[:5].lower() == b"solid":
        return _read_stl_ascii(path, data)
    if size < 84:
        raise _err(path, f"not an STL file: {size} bytes is too short for a binary STL header (84 bytes) "
                         "and the text does not start with 'solid'")
    (count,) = struct.unpack("<I", data[80:84])
    held = (size - 84) / 50
    raise _err(path, f"binary STL: the header says {count} triangles ({84 + 50 * count} bytes) but the file has "
                     f"{size} bytes ({held:g} triangles after the header): truncated, or a wrong triangle count")


def _read_stl_binary(data, count):
    rec = np.dtype([("normal", "<f4", (3,)), ("tri", "<f4", (3, 3)), ("attr", "<u2")])
    arr = np.frombuffer(data, dtype=rec, count=count, offset=84)
    return arr["tri"].astype(np.float64)


def _read_stl_ascii(path, data):
    text = data.decode("latin-1")
    tris, loop, facet_line, in_facet = [], None, 0, False
    nfacet = 0
    ended = False
    for lineno, line in enumerate(text.splitlines(), start=1):
        tok = line.split()
        if not tok:
            continue
        key = tok[0].lower()
        if key == "solid":  # a header; several solids in one file are all read
            if in_facet:
                raise _err(path, f"line {lineno}: 'solid' inside facet {nfacet} (line {facet_line})")
            ended = False
            continue
        if ended:
            raise _err(path, f"line {lineno}: text after 'endsolid' ({line.strip()[:40]!r})")
        if key == "facet":
            if in_facet:
                raise _err(path, f"line {lineno}: a new facet starts before 'endfacet' of facet {nfacet} "
                                 f"(line {facet_line})")
            in_facet, facet_line, loop = True, lineno, None
            nfacet += 1
        elif key == "outer":
            if not in_facet:
                raise _err(path, f"line {lineno}: 'outer loop' outside a facet")
            loop = []
        elif key == "vertex":
            if loop is None:
                raise _err(path, f"line {lineno}: 'vertex' outside 'outer loop'")
            try:
                xyz = [float(t) for t in tok[1:]]
            except ValueError:
                raise _err(path, f"line {lineno}: vertex coordinates are not numbers ({line.strip()[:60]!r})") from None
            if len(xyz) != 3:
                raise _err(path, f"line {lineno}: a vertex needs 3 coordinates, got {len(xyz)}")
            if not all(np.isfinite(xyz)):
                raise _err(path, f"line {lineno}: non-finite vertex coordinate ({line.strip()[:60]!r})")
            loop.append(xyz)
        elif key == "endloop":
            if loop is None:
                raise _err(path, f"line {lineno}: 'endloop' without 'outer loop'")
            if len(loop) != 3:
                raise _err(path, f"facet {nfacet} (line {facet_line}) has {len(loop)} vertices; STL facets are "
                                 "triangles with exactly 3")
        elif key == "endfacet":
            if not in_facet or loop is None:
                raise _err(path, f"line {lineno}: 'endfacet' without a facet and its 'outer loop'")
            if len(loop) != 3:
                raise _err(path, f"facet {nfacet} (line {facet_line}) has {len(loop)} vertices; STL facets are "
                                 "triangles with exactly 3")
            tris.append(loop)
            in_facet, loop = False, None
        elif key == "endsolid":
            if in_facet:
                raise _err(path, f"line {lineno}: 'endsolid' inside facet {nfacet} (line {facet_line})")
            ended = True  # the name after endsolid is not checked: many writers get it wrong
        else:
            raise _err(path, f"line {lineno}: unexpected {tok[0][:30]!r} in an ASCII STL (expected facet, outer loop, "
                             "vertex, endloop, endfacet or endsolid)")
    if in_facet:
        raise _err(path, f"truncated: the file ends inside facet {nfacet} (line {facet_line})")
    # a missing 'endsolid' after complete facets loses nothing: accepted
    return np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)


# --- reading ----------------------------------------------------------------------------------------------------------
def read_mesh(path):
    """Read a mesh file as it is (model units, no checks beyond readability) -> trimesh.Trimesh."""
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    problem = regular_file_problem(path)
    if problem == "no such file":
        raise _err(path, "no such file (expected a mesh: " + ", ".join(EXTENSIONS) + ")")
    if problem:
        raise _err(path, f"{problem}, expected a mesh file")
    if ext not in EXTENSIONS:
        raise _err(path, f"unsupported mesh extension {ext or '(none)'!r} (expected one of " + ", ".join(EXTENSIONS)
                   + ")")
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise _err(path, f"cannot be read ({e.strerror})") from None
    return mesh_from_bytes(path, data)


def mesh_from_bytes(path, data):
    """The bytes of a mesh file named path (its extension decides the format) -> trimesh.Trimesh; every failure
    a ModelError naming path, every vertex finite. A 3MF is read by lib3mf from path itself (it reads files by
    name), so for 3MF the bytes must be that file's."""
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in EXTENSIONS:
        raise _err(path, f"unsupported mesh extension {ext or '(none)'!r} (expected one of " + ", ".join(EXTENSIONS)
                   + ")")
    try:
        mesh = _mesh_from_bytes(path, ext, data)
    except MemoryError:
        raise _err(path, "too large to read into memory") from None
    v = np.asarray(mesh.vertices, dtype=float)
    if len(v) and not np.all(np.isfinite(v)):
        # a NaN vertex would be merged away or silently repaired into a different solid
        raise _err(path, f"{int(np.sum(~np.isfinite(v).all(axis=1)))} vertices have non-finite coordinates (NaN or "
                         "infinity)")
    return mesh


def _mesh_from_bytes(path, ext, data):
    if not data.strip():
        raise _err(path, "the file is empty, expected a closed triangle mesh")
    if ext == ".stl":
        tris = _read_stl(path, data)
        if len(tris) == 0:
            raise _err(path, "the STL holds no triangles")
        if not np.all(np.isfinite(tris)):
            bad = int(np.argwhere(~np.isfinite(tris).all(axis=(1, 2)))[0, 0])
            raise _err(path, f"triangle {bad} has a non-finite vertex coordinate (NaN or infinity)")
        # process=True merges equal vertices, which is what turns a triangle soup into a connected mesh
        return trimesh.Trimesh(**trimesh.triangles.to_kwargs(tris), process=True)
    if ext == ".3mf":
        return _read_3mf(path)
    if ext == ".off":
        return _read_off(path, data)
    try:
        import io

        # unprocessed, then processed once below: with process=True the loader, its scene's dump and the
        # concatenation each merged the vertices again (3 merges and 2 copies, 0.4 of 1.4 CPU s at 1.2M faces)
        loaded = trimesh.load(io.BytesIO(data), file_type=_TRIMESH_TYPES[ext], force="mesh", process=False)
    except Exception as e:  # trimesh raises anything from ValueError to IndexError on a bad file
        raise _err(path, f"cannot read as {ext[1:].upper()}: {type(e).__name__}: {str(e)[:200]}") from None
    if isinstance(loaded, trimesh.Scene):  # force='mesh' gives an empty Scene when nothing is in it
        loaded = loaded.dump(concatenate=True) if len(loaded.geometry) else trimesh.Trimesh()
    if not isinstance(loaded, trimesh.Trimesh):
        raise _err(path, f"holds no triangle mesh (got {type(loaded).__name__})")
    return trimesh.Trimesh(loaded.vertices, loaded.faces, process=True)


def _read_off(path, data):
    """OFF (header, counts, vertices, faces with a leading vertex count; '#' comments; polygons fanned into
    triangles). Ours because trimesh's takes seconds on a 75k-face bunny and fails with bare numpy errors."""
    text = data.decode("latin-1")
    if "#" in text:
        text = "\n".join(line.split("#", 1)[0] for line in text.splitlines())
    lines = [line for line in (raw.strip() for raw in text.splitlines()) if line]
    if not lines or not lines[0].upper().endswith("OFF") or lines[0].upper() not in ("OFF", "COFF", "NOFF", "CNOFF"):
        head = lines[0][:20] if lines else ""
        raise _err(path, f"not an OFF file: the first line is {head!r}, expected 'OFF'")
    tokens = lines[1].split() if len(lines) > 1 else []
    try:
        nv, nf = int(tokens[0]), int(tokens[1])
    except (IndexError, ValueError):
        raise _err(path, "OFF: expected the counts line 'vertices faces edges' after the header") from None
    rows = lines[2:] if len(lines[1].split()) <= 3 else None
    if rows is None or len(rows) < nv + nf:
        raise _err(path, f"OFF: truncated: the header promises {nv} vertices and {nf} faces, the file has "
                         f"{0 if rows is None else len(rows)} data lines")
    try:
        v = np.array(" ".join(" ".join(r.split()[:3]) for r in rows[:nv]).split(), dtype=float).reshape(nv, 3)
    except ValueError:
        raise _err(path, "OFF: a vertex line does not hold three numbers") from None
    if not np.all(np.isfinite(v)):
        raise _err(path, "OFF: non-finite vertex coordinates (NaN or infinity)")
    tris = []
    try:  # the common all-triangles case in one numpy call
        flat = np.array(" ".join(rows[nv:nv + nf]).split(), dtype=np.int64)
    except ValueError:
        flat = None
    if flat is not None and flat.size == 4 * nf and np.all(flat[::4] == 3):
        tris = flat.reshape(nf, 4)[:, 1:]
    else:
        for k, r in enumerate(rows[nv:nv + nf]):
            t = r.split()
            try:
                n = int(t[0])
                idx = [int(x) for x in t[1:1 + n]]
            except ValueError:
                raise _err(path, f"OFF: face {k} is not a list of integers ({r[:40]!r})") from None
            if n < 3 or len(idx) != n:
                raise _err(path, f"OFF: face {k} has {len(idx)} of its {n} vertex indices (need at least 3)")
            tris.extend([idx[0], idx[i], idx[i + 1]] for i in range(1, n - 1))
    f = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    if len(f) and (f.min() < 0 or f.max() >= nv):
        raise _err(path, f"OFF: a face refers to vertex {int(f.max() if f.max() >= nv else f.min())}, "
                         f"outside 0..{nv - 1}")
    return trimesh.Trimesh(v, f, process=True)


_MM_PER_3MF_UNIT = {"micron": 1e-3, "millimeter": 1.0, "centimeter": 10.0, "inch": 25.4, "foot": 304.8,
                    "meter": 1000.0}


def _read_3mf(path):
    """3MF through lib3mf (trimesh's reader needs lxml): every build item, concatenated, converted to mm from the
    unit the file declares -- so model.units does not apply to a 3MF (its unit is in the file)."""
    from .threemf import read_3mf

    objects, unit = read_3mf(path, strict=False, with_units=True)
    if not objects:
        raise _err(path, "the 3MF holds no mesh objects")
    mm = _MM_PER_3MF_UNIT.get(unit, 1.0)
    verts, faces, n = [], [], 0
    for _, v, f, _ in objects:
        verts.append(np.asarray(v, float) * mm)
        faces.append(np.asarray(f, np.int64) + n)
        n += len(v)
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=True)
    mesh.metadata["units_in_file"] = True
    return mesh


# --- checking ---------------------------------------------------------------------------------------------------------
def _near(mesh, edges):
    p = mesh.vertices[edges[0]].mean(axis=0)
    return "(" + ", ".join(f"{x:.4g}" for x in p) + ")"


def _directed_edges(faces):
    """faces (m, 3) -> (3m, 2) int64: each triangle's edges 01, 12, 20, all first edges first (column copies: a
    gather by column lists cost 2-4x as much at 1.2M faces)."""
    f = np.asarray(faces, dtype=np.int64)
    m = len(f)
    out = np.empty((3 * m, 2), np.int64)
    for k in range(3):
        out[k * m:(k + 1) * m, 0] = f[:, k]
        out[k * m:(k + 1) * m, 1] = f[:, (k + 1) % 3]
    return out


def _signed_volume(v, faces):
    """The volume (units^3) enclosed by triangles faces (m, 3) over vertices v (n, 3), positive for outward ones:
    the sum of a . (b x c) / 6, on coordinate columns (np.cross and einsum on gathered rows cost 6x as much)."""
    x, y, z = (np.ascontiguousarray(v[:, k]) for k in range(3))
    total = 0.0
    for s in range(0, len(faces), _CHUNK):  # chunks small enough that their temporaries reuse freed memory
        a, b, c = faces[s:s + _CHUNK, 0], faces[s:s + _CHUNK, 1], faces[s:s + _CHUNK, 2]
        ax, ay, az, bx, by, bz, cx, cy, cz = x[a], y[a], z[a], x[b], y[b], z[b], x[c], y[c], z[c]
        total += float((ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)).sum())
    return total / 6.0


_CHUNK = 1 << 16


def mesh_problems(mesh):
    """What keeps `mesh` from being one closed, oriented solid -> list of messages (empty when it is one)."""
    faces = np.asarray(mesh.faces)
    if len(faces) == 0:
        return ["zero faces: the file holds no triangles"]
    out = []
    directed = _directed_edges(faces)
    # in place where it can be: at 1.2M faces each temporary is 29 MB of fresh pages, whose faults cost as much as
    # the arithmetic
    keys = np.minimum(directed[:, 0], directed[:, 1])
    hi = np.maximum(directed[:, 0], directed[:, 1])
    base = int(hi.max()) + 1
    keys *= base
    keys += hi
    del hi
    shift = len(keys).bit_length()
    if 2 * base.bit_length() + shift <= 62:
        # each key with its index in the low bits: a plain sort of int64 is ~5x faster than an argsort
        packed = keys
        packed <<= shift
        packed |= np.arange(len(keys), dtype=np.int64)
        packed.sort()
        order = packed & ((1 << shift) - 1)
        sk = packed
        sk >>= shift
    else:
        order = np.argsort(keys)  # the order within a run of equal keys does not matter below
        sk = keys[order]
    starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
    counts = np.diff(np.r_[starts, len(sk)])
    # the edges of the runs other than two (rare: a closed mesh has none) as vertex pairs
    open_k, nonman_k = sk[starts[counts == 1]], sk[starts[counts > 2]]
    open_e = np.stack([open_k // base, open_k % base], axis=1)
    nonman = np.stack([nonman_k // base, nonman_k % base], axis=1)
    if len(open_e):
        out.append(f"{len(open_e)} open (boundary) edges: the surface has holes, near {_near(mesh, open_e)}")
    if len(nonman):
        out.append(f"{len(nonman)} non-manifold edges shared by more than two triangles, near {_near(mesh, nonman)}")
    # two triangles that agree in orientation run along their shared edge the same way: a directed edge used twice.
    # Read from the runs above (a pair of an edge's two uses starting at the same vertex) rather than a second sort;
    # the rare runs of more than two uses are counted on their own
    two = starts[counts == 2]
    first, second = order[two], order[two + 1]
    same = two[directed[first, 0] == directed[second, 0]]
    incons = directed[order[same]]
    many = np.flatnonzero(counts > 2)
    if len(many):
        rows = order[np.concatenate([np.arange(starts[i], starts[i] + counts[i]) for i in many])]
        duniq, dcount = unique_pairs(directed[rows])
        incons = np.concatenate([incons, duniq[dcount > 1]])
    if len(incons):
        incons = incons[np.argsort(incons[:, 0] * base + incons[:, 1])]  # the message names the least edge
        out.append(f"{len(incons)} edges where neighbouring triangles are inconsistently oriented (flipped faces), "
                   f"near {_near(mesh, incons)}")
    # bodies: faces joined across the edges that exactly two triangles share (as trimesh's face_adjacency), from the
    # sort above rather than trimesh's own (3 s at 1.2M faces)
    nb, labels = joined(np.stack([first, second], axis=1) % len(faces), len(faces))
    if nb > 1:
        sizes = np.sort(np.bincount(labels))[::-1]
        shown = ", ".join(str(s) for s in sizes[:5]) + (", ..." if nb > 5 else "")
        out.append(f"{nb} separate bodies (triangles per body: {shown}); expected one solid")
    if not out:
        # the signed volume alone (the divergence theorem over the triangles), not trimesh's whole mass properties:
        # at 1.2M faces those cost 2.6 s, for a mesh that may be simplified before anything needs its inertia
        with np.errstate(all="ignore"):
            vol = _signed_volume(np.asarray(mesh.vertices, float), faces)
        if abs(vol) <= 1e-12 * float(np.max(mesh.extents)) ** 3:
            out.append("encloses no volume (a flat or two-sided surface)")
        elif not vol > 0:
            out.append(f"encloses volume {vol:.4g} (units^3): the triangles face inward (expected outward normals, "
                       "positive volume)")
    return out


def check_mesh(mesh, path):
    problems = mesh_problems(mesh)
    if problems:
        hint = "" if problems[0].startswith("zero faces") else "; model.repair: true may fix holes and orientation"
        raise _err(path, "not one closed, consistently oriented solid: " + "; ".join(problems) + hint)
    return mesh


def _simple_loops(loop):
    """Split a closed vertex loop that passes a vertex twice into loops that do not (else a fan over it would
    give that vertex's spoke four triangles)."""
    out, stack, where = [], [], {}
    for v in loop + [loop[0]]:
        if v in where:
            i = where[v]
            sub = stack[i:]
            for u in sub[1:]:
                where.pop(u, None)
            del stack[i + 1:]
            if len(sub) >= 3:
                out.append(sub)
        else:
            where[v] = len(stack)
            stack.append(v)
    return out


def _fill_boundary_loops(mesh):
    """Close each hole by a fan of triangles from its loop's centroid, oriented with the surrounding surface."""
    faces = np.asarray(mesh.faces)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    und = np.sort(directed, axis=1).astype(np.int64)
    _, inv, counts = np.unique(und[:, 0] * (int(und.max()) + 1) + und[:, 1], return_inverse=True, return_counts=True)
    bnd = directed[counts[inv.ravel()] == 1]
    if len(bnd) == 0:
        return mesh
    nxt = {}
    for a, b in bnd:
        nxt.setdefault(int(b), []).append(int(a))  # the fill runs against the surface: b -> a
    verts = [np.asarray(mesh.vertices)]
    new_faces = [faces]
    n = len(mesh.vertices)
    # Each boundary vertex has as many edges in as out, so walking unused edges always comes back to the start;
    # a vertex where two holes touch is just passed twice.
    for start in list(nxt):
        while nxt.get(start):
            loop, cur = [start], nxt[start].pop()
            while cur != start and nxt.get(cur):
                loop.append(cur)
                cur = nxt[cur].pop()
            if cur != start:
                continue  # a dangling boundary: left for the check to report
            for simple in _simple_loops(loop):
                c = mesh.vertices[simple].mean(axis=0)
                verts.append(c[None])
                new_faces.append(np.array([[simple[i], simple[(i + 1) % len(simple)], n]
                                           for i in range(len(simple))]))
                n += 1
    return trimesh.Trimesh(np.concatenate(verts), np.concatenate(new_faces), process=True)


def repair_mesh(mesh):
    """trimesh's repairs plus hole filling: merge vertices, drop degenerate and duplicate faces, fill holes,
    fix winding and turn normals outward -> a new Trimesh (check it again)."""
    with np.errstate(all="ignore"):  # a flat input has zero volume, and trimesh divides by it
        return _repair(mesh)


def _repair(mesh):
    m = mesh.copy()
    m.merge_vertices()
    m.update_faces(m.nondegenerate_faces())
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    trimesh.repair.fix_winding(m)
    trimesh.repair.fill_holes(m)
    if not m.is_watertight:
        m = _fill_boundary_loops(m)
        trimesh.repair.fix_winding(m)
    trimesh.repair.fix_inversion(m, multibody=True)
    return m


def load_mesh_scaled(path, unit_scale=1.0, size=None, repair=False):
    """Read, check (or repair then check) and scale a mesh -> (trimesh.Trimesh in mm, scale mm per file unit).

    The scale is about the origin, like a NURBS model's, so a NURBS cage in the same units needs the same factor.
    """
    mesh = read_mesh(path)
    if repair:
        problems = mesh_problems(mesh)
        if problems:
            mesh = repair_mesh(mesh)
            left = mesh_problems(mesh)
            if left:
                raise _err(path, "not one closed, consistently oriented solid, even after repair (model.repair): "
                           + "; ".join(left) + " (before repair: " + "; ".join(problems) + ")")
    else:
        check_mesh(mesh, path)
    scale = 1.0 if mesh.metadata.get("units_in_file") else float(unit_scale)
    if size is not None:
        extent = float(np.max(mesh.extents)) * scale
        if not extent > 0:
            raise _err(path, "the mesh has zero extent; cannot scale it to model.size")
        scale *= float(size) / extent
    if scale != 1.0:
        mesh.apply_scale(scale)
    return mesh, scale


def load_mesh(path, unit_scale=1.0, size=None, repair=False):
    """A closed, outward-oriented solid in mm -> trimesh.Trimesh: units first, then `size` = largest bounding-box
    side in mm. ModelError naming the file for anything unreadable or not one closed solid."""
    return load_mesh_scaled(path, unit_scale, size, repair)[0]


# --- dense meshes ----------------------------------------------------------------------------------------------------
DENSE_TRIANGLES = 400_000  # above this a mesh is simplified within the output tolerance (simplify_dense)


@dataclass(frozen=True, eq=False)
class _Surface:
    """A mesh's triangles as the distance kernels read them: vertices (n, 3) float64, faces (m, 3) int64, a kd-tree
    of the triangles' centres and the largest distance from a centre to its triangle's corners (mm)."""

    v: np.ndarray
    f: np.ndarray
    tree: object
    reach: float


def _surface(vertices, faces):
    """vertices (n, 3), faces (m, 3) -> _Surface (arrays, not a Trimesh, so that a thread may build it: trimesh's
    caches are not thread-safe)."""
    from scipy.spatial import cKDTree

    from ._mesh_distance import centres_and_reach

    # the kernels read the triangles through their vertex indices: mesh.triangles would be a 90 MB copy at 1.2M faces
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    centre, reach = centres_and_reach(v, f)
    # unbalanced, it builds in 60% of the time (0.53 -> 0.33 s at 1.2M) and queries as fast
    return _Surface(v, f, cKDTree(centre, balanced_tree=False), float(reach))


def _farthest_from(points, mesh, enough, k=4, chunk=200_000):
    """The largest distance from points (n, 3) to the surface of mesh (a Trimesh or its _surface), exact where it
    matters: each point's distance to the nearest of the k triangles whose centres lie nearest it bounds it from
    above; the few points whose bound exceeds `enough` are measured against every triangle whose centre lies within
    that bound plus the largest triangle's reach from its centre (any nearer triangle must be one of them)."""
    from ._mesh_distance import nearest_distances, nearest_of

    surf = mesh if isinstance(mesh, _Surface) else _surface(mesh.vertices, mesh.faces)
    v, f, tree, reach = surf.v, surf.f, surf.tree, surf.reach
    worst = 0.0
    for s in range(0, len(points), chunk):
        p = np.ascontiguousarray(points[s:s + chunk], dtype=np.float64)
        best = np.full(len(p), np.inf)
        todo = np.arange(len(p))
        for kk in (k, 8 * k):  # the few points over large triangles look further before the exact search
            _, near = tree.query(p[todo], k=min(kk, len(f)))
            best[todo] = nearest_distances(p[todo], v, f, near.reshape(len(todo), -1), best[todo])
            todo = todo[best[todo] > enough]
            if not len(todo):
                break
        if len(todo):
            balls = tree.query_ball_point(p[todo], best[todo] + reach)
            ptr = np.zeros(len(todo) + 1, np.int64)
            ptr[1:] = np.cumsum([len(b) for b in balls])
            cand = np.fromiter((j for b in balls for j in b), np.int64, count=int(ptr[-1]))
            best[todo] = nearest_of(p[todo], v, f, ptr, cand, best[todo].copy())
        worst = max(worst, float(best.max()))
    return worst


def simplify_dense(mesh, max_error, above=None):
    """A closed mesh (mm) of more than `above` triangles -> (mesh, info or None): simplified (quadric edge
    collapses, fast_simplification) to about above / 2 triangles, or to `above` when that strays too far, and kept
    only when it is still one closed oriented solid lying within max_error mm of the original both ways (measured
    from every vertex of each to the other's surface). Every later stage costs in proportion to the triangles, and a
    mesh far finer than the print tolerance (a scan, a subdivision) gains nothing from them. info: {"triangles_in",
    "triangles", "max_deviation_mm"}; None when the mesh is kept as it is. above: DENSE_TRIANGLES unless given."""
    above = DENSE_TRIANGLES if above is None else int(above)
    faces = np.asarray(mesh.faces)
    if len(faces) <= above or not max_error > 0:
        return mesh, None
    from concurrent.futures import ThreadPoolExecutor

    import fast_simplification

    v0 = np.asarray(mesh.vertices, float)
    # Wall time on the second core, the same results: fast_simplification, cKDTree and the distance kernels release
    # the GIL, so a thread indexes the original's surface while the simplification runs, and measures the simplified
    # mesh's vertices against it while this thread measures the other way (at 1.2M faces ~0.5 s and ~1 s of the
    # ~7 s). The back measure is wasted only when the forward one already fails.
    with ThreadPoolExecutor(1) as pool:
        original = pool.submit(_surface, v0, faces)
        for target in (above // 2, above):
            try:
                v, f = fast_simplification.simplify(v0, faces.astype(np.int64),
                                                    target_reduction=1.0 - target / len(faces))
            except Exception:  # noqa: BLE001 - the mesh as it is stays a correct (if slow) input
                return mesh, None
            out = trimesh.Trimesh(np.asarray(v, float), np.asarray(f, np.int64), process=False)
            if len(out.faces) == 0 or mesh_problems(out):
                continue
            back = pool.submit(lambda vs: _farthest_from(vs, original.result(), max_error), np.asarray(out.vertices))
            dev = _farthest_from(v0, out, max_error)
            if dev <= max_error:
                dev = max(dev, back.result())
            if dev <= max_error:
                return out, {"triangles_in": int(len(faces)), "triangles": int(len(out.faces)),
                             "max_deviation_mm": round(dev, 6)}
            back.result()  # not left running into the next try
    return mesh, None
