"""The one place that converts between manifold3d and trimesh and checks the engine's status.

manifold3d reports failure through `status()` instead of raising, and an empty result can hide a failed
operation; every helper here checks both and raises GeometryError naming the piece (`what`).
"""

import ctypes
import sys
import weakref
from functools import lru_cache

import manifold3d
import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .errors import GeometryError
from .grid import frame_from_direction

# id(mesh) -> (weak reference, content hash, {what: result}). A build judges the same piece meshes several times
# (closed when they are made printable and again in the checks; as solids in the overlap check and again in the
# assembly replay; drawn in the preview and again in the step pictures), and a conversion or a closedness test costs
# milliseconds per piece.
_MEMO = {}


def memo(mesh, what, make):
    """make(), computed once per mesh object and kind of result while the mesh's content stays the same (a
    trimesh hashes its arrays and notices its own edits; other objects are not remembered)."""
    if not isinstance(mesh, trimesh.Trimesh):
        return make()
    h = hash(mesh)
    key = id(mesh)
    entry = _MEMO.get(key)
    if entry is None or entry[0]() is not mesh or entry[1] != h:
        entry = (weakref.ref(mesh, lambda _, key=key: _MEMO.pop(key, None)), h, {})
        _MEMO[key] = entry
    if what not in entry[2]:
        entry[2][what] = make()
    return entry[2][what]


def forget(meshes):
    """Let go of everything derived from these meshes: what memo holds for them (their engine solids, above all)
    and trimesh's own cache of derived arrays (triangles, centres, normals). For meshes a later stage has replaced
    or will only write: at 1024 pieces that is hundreds of MB the next stages would otherwise allocate on top of. A
    mesh used again afterwards is only measured again, never judged on stale results."""
    for mesh in meshes:
        _MEMO.pop(id(mesh), None)
        if isinstance(mesh, trimesh.Trimesh):
            mesh._cache.clear()  # trimesh has no public call for this; its own methods clear the cache this way
    _return_freed_memory()


def _return_freed_memory():
    """Hand memory that is free again back to the system, where the C library can (glibc's malloc_trim).

    The engine's solids are built on its worker threads, in their own malloc arenas; once they are freed that memory
    is not reused by numpy on the main thread, and without a trim the export allocates on top of it (1024 pieces:
    peak 2.07 GB without, 1.72 GB with)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's malloc_trim, or None. Looked up among the symbols the process already has (no find_library, which may
    start a subprocess: unsafe once the engine's threads run)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # musl and other C libraries have no malloc_trim
        return None


_OPS = {"union": lambda a, b: a + b, "difference": lambda a, b: a - b, "intersection": lambda a, b: a ^ b}


def is_ok(m):
    """True when the engine reports no error for Manifold m (its status; emptiness is the caller's question)."""
    return m.status() == manifold3d.Error.NoError


def check_status(m, what, step):
    """m, or GeometryError naming `what` and the `step` at which the engine failed (with its status)."""
    status = m.status()
    if status != manifold3d.Error.NoError:
        raise GeometryError(f"{what}: the geometry engine failed at {step} (status {status.name})")
    return m


def manifold_from_mesh(vertices, faces, what, keep_faces=True):
    """vertices (n, 3), faces (m, 3) -> Manifold, or GeometryError naming `what` and the engine's status.

    keep_faces gives every triangle its own face id, so the engine never merges coplanar triangles:
    a parameter-space box must keep its grid, since its vertices are later mapped through F.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.uint64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise GeometryError(f"{what}: expected vertices (n, 3) and faces (m, 3), got {v.shape} and {f.shape}")
    if not np.all(np.isfinite(v)):
        raise GeometryError(f"{what}: the mesh has non-finite vertex coordinates")
    face_id = np.arange(len(f), dtype=np.uint64) if keep_faces else None
    m = manifold3d.Manifold(manifold3d.Mesh64(vert_properties=v, tri_verts=f, face_id=face_id))
    check_status(m, what, "building a solid from its mesh")
    if m.is_empty():
        raise GeometryError(f"{what}: the mesh encloses no volume (empty solid from {len(f)} triangles)")
    return m


def to_trimesh(m):
    """Manifold -> trimesh.Trimesh (float64, no processing: the engine's vertices and triangles as they are)."""
    mesh = m.to_mesh64()
    v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    f = np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3)
    return trimesh.Trimesh(vertices=v.copy(), faces=f.copy(), process=False)


def from_trimesh(mesh, what):
    """trimesh.Trimesh -> Manifold, with status checks."""
    return manifold_from_mesh(mesh.vertices, mesh.faces, what)


def cylinder(center, direction, radius, start, stop, what, segments=48):
    """A Manifold cylinder of `radius` along `direction` (3,), from center + start * d to center + stop * d (d the
    unit direction), its local frame that of grid.frame_from_direction; status checked, naming `what`."""
    d = np.asarray(direction, dtype=float)
    e1, e2, n = frame_from_direction(d / np.linalg.norm(d))
    frame = np.zeros((3, 4))
    frame[:, 0], frame[:, 1], frame[:, 2], frame[:, 3] = e1, e2, n, center
    cyl = manifold3d.Manifold.cylinder(stop - start, radius, -1.0, segments).translate([0.0, 0.0, start])
    return check_status(cyl.transform(frame), what, f"a cylinder of radius {radius:g} mm")


def solid_of(mesh, what):
    """from_trimesh(mesh, what), made once per mesh object while its content stays the same (memo): stages that
    read the same piece share its Manifold, which no operation changes in place."""
    return memo(mesh, "solid_keep_faces", lambda: from_trimesh(mesh, what))


def boolean(a, b, op, what):
    """a op b for op in 'union' | 'difference' | 'intersection'; checks the status of the result."""
    if op not in _OPS:
        raise GeometryError(f"{what}: unknown boolean operation {op!r} (expected one of {sorted(_OPS)})")
    check_status(a, what, f"{op} (first operand)")
    check_status(b, what, f"{op} (second operand)")
    return check_status(_OPS[op](a, b), what, op)


def boolean_all(first, others, op, what):
    """first op every solid of others, in one batch Boolean of the engine, for op in 'union' | 'difference' (others
    not meeting each other; one batch is ~30% cheaper than one Boolean each); checks every operand and the result."""
    kinds = {"union": manifold3d.OpType.Add, "difference": manifold3d.OpType.Subtract}
    if op not in kinds:
        raise GeometryError(f"{what}: unknown batch boolean operation {op!r} (expected one of {sorted(kinds)})")
    others = list(others)
    if not others:
        return check_status(first, what, f"{op} (first operand)")
    for k, m in enumerate([first, *others]):
        check_status(m, what, f"{op} (operand {k + 1})")
    return check_status(manifold3d.Manifold.batch_boolean([first, *others], kinds[op]), what, op)


def kernel_arrays(mesh):
    """A trimesh's vertices (n, 3) float64 and faces (m, 3) int64, C-ordered: the types the compiled kernels are
    declared for (precompile.KERNELS)."""
    return (np.ascontiguousarray(mesh.vertices, dtype=np.float64),
            np.ascontiguousarray(mesh.faces, dtype=np.int64))


def boxes_nested(a, b):
    """Whether one box (2, 3) of a and b holds the other: surfaces that do not meet then prove nothing, as one solid
    may lie inside the other (check.pairs_apart, assembly._Scene._unmet)."""
    (alo, ahi), (blo, bhi) = a, b
    return bool((np.all(alo >= blo) and np.all(ahi <= bhi)) or (np.all(blo >= alo) and np.all(bhi <= ahi)))


def weld(vertices, faces, tol):
    """Merge vertices closer than tol and drop triangles that then repeat a vertex, e.g. where a face of the
    parameter box collapses to a line or a point (a cone's axis, a sphere's pole).

    Each cluster keeps its lowest-index vertex, so the result depends only on the input order.
    Also cancels pairs of triangles with the same vertices and opposite orientation: two faces of one cell
    that coincide in space (a single cell closing on itself across a seam) enclose nothing.
    Returns (vertices (k, 3), faces (j, 3)).
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(v) == 0:
        return v.reshape(0, 3), f
    if tol > 0:
        pairs = cKDTree(v).query_pairs(tol, output_type="ndarray")
        if len(pairs):
            # clusters are the connected components of the close pairs; each maps to its smallest index
            _, comp = joined(pairs, len(v))
            low = np.full(comp.max() + 1, len(v), dtype=np.int64)
            np.minimum.at(low, comp, np.arange(len(v)))
            f = low[comp][f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    if len(f):
        # rotate each triangle to start at its smallest vertex: equal triangles then have equal rows, and a
        # reversed one is the row with its last two entries swapped
        rot = np.argmin(f, axis=1)
        rows = np.arange(len(f))
        canon = np.stack([f[rows, (rot + k) % 3] for k in range(3)], axis=1)
        key, rkey = _row_keys(canon, canon[:, [0, 2, 1]])
        # a triangle and its reverse cancel; keep each oriented triangle once
        keep = ~np.isin(rkey, key)
        _, first = np.unique(key, return_index=True)
        once = np.zeros(len(f), dtype=bool)
        once[first] = True
        f = f[keep & once]
    used, f = np.unique(f, return_inverse=True)
    return v[used], f.reshape(-1, 3)


def joined(pairs, n):
    """The parts n items fall into when each pair (k, 2) of their indices joins two: -> (count, (n,) part of each
    item, numbered from 0; an item in no pair is a part of its own)."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, part = connected_components(graph, directed=False)
    return int(count), part


def unique_pairs(e):
    """The distinct rows of non-negative index pairs e (k, 2), in np.unique(e, axis=0)'s order, and their counts:
    one integer key per pair sorts ~20x faster than unique's rows as records. -> ((j, 2) int64, (j,) counts)"""
    e = np.asarray(e, dtype=np.int64).reshape(-1, 2)
    base = int(e.max()) + 1 if len(e) else 1
    keys, counts = np.unique(e[:, 0] * base + e[:, 1], return_counts=True)
    return np.stack([keys // base, keys % base], axis=1), counts


def _row_keys(a, b):
    """One int64 per row of the index arrays a and b (k, 3), equal exactly when the rows are equal."""
    n = int(max(a.max(), b.max())) + 1
    if n < 2 ** 21:
        return [(x[:, 0] * n + x[:, 1]) * n + x[:, 2] for x in (a, b)]
    _, inv = np.unique(np.concatenate([a, b]), axis=0, return_inverse=True)
    inv = inv.ravel()
    return inv[:len(a)], inv[len(a):]


def kept_bodies(solid, count, volume, share):
    """The solid with as many bodies as `count`, slivers dropped: where a cut grazes a piece, a speck thinner than
    the cut's depth parts from it; specks of at most `share` of the piece's `volume` (0.2 mm^3 at least, less than a
    nozzle lays in a millimetre) are dropped. -> Manifold, or None when what parts is more than a sliver."""
    if solid.is_empty():
        return None
    parts = sorted(solid.decompose(), key=lambda b: -b.volume())
    if len(parts) <= count:
        return solid if len(parts) == count else None
    if sum(float(b.volume()) for b in parts[count:]) > max(0.2, share * volume):
        return None
    kept = parts[0]
    for b in parts[1:count]:
        kept = kept + b
    return kept


def trim(m, normal, offset, what):
    """The part of Manifold m on the side `normal` points to of the plane normal . x = offset, status checked."""
    operand = check_status(m, what, "trimming by a plane (operand)")
    return check_status(operand.trim_by_plane(tuple(float(x) for x in normal), float(offset)), what,
                        "trimming by a plane")


def section_area(vertices, faces, height):
    """mm^2 of the section of a closed, outward-wound triangle mesh (vertices (n, 3), faces (m, 3)) by the plane
    z = height. Green's theorem over the segments where triangles cross the plane: in a triangle's own vertex order,
    the segment runs from the edge that goes down through the plane to the edge that comes back up, which leaves the
    solid's section on its left, so the segments need no tracing into loops and holes subtract themselves. A vertex
    on the plane counts as below it, so that the section is the one just above the plane, as the engine's slice
    measures it: a face lying in the plane belongs to the part under it (a box cut at its bottom face has its whole
    section, at its top none). An edge's crossing is computed from its lower end, the same point for both of its
    triangles."""
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    above = (v[:, 2] > height)[f]
    crossing_plane = above.any(axis=1) & ~above.all(axis=1)
    f, above = f[crossing_plane], above[crossing_plane]
    if not len(f):
        return 0.0
    start, stop = f, np.roll(f, -1, axis=1)  # edge k runs from corner k to corner k + 1
    a_start, a_stop = above, np.roll(above, -1, axis=1)
    rows = np.arange(len(f))

    def crossing(k):
        lo = np.where(a_start[rows, k], stop[rows, k], start[rows, k])  # the edge's end below the plane (or on it)
        hi = np.where(a_start[rows, k], start[rows, k], stop[rows, k])
        t = (height - v[lo, 2]) / (v[hi, 2] - v[lo, 2])
        return v[lo, :2] + t[:, None] * (v[hi, :2] - v[lo, :2])

    down = crossing(np.argmax(a_start & ~a_stop, axis=1))
    up = crossing(np.argmax(~a_start & a_stop, axis=1))
    return float(0.5 * np.sum(down[:, 0] * up[:, 1] - up[:, 0] * down[:, 1]))


def hull_points_of(mesh):
    """The vertices (k, 3) of trimesh's convex_hull of the mesh, in its order (qhull's, same options, by index),
    without building the hull's mesh, which costs a third more than qhull itself and is not needed where only the
    extreme points are (plates are packed, and cages fitted, on them). A point set qhull refuses goes to trimesh's
    own retry, and one that also refuses (flat, tiny) gives all its vertices. Made once per mesh (memo): the pieces'
    are made where their printable meshes are, by the workers too (export.printable), for the plates' layout."""
    return memo(mesh, "hull_points", lambda: _hull_points(mesh))


def remember_hull_points(mesh, points):
    """hull_points_of(mesh) as already found (in a worker, for a copy of the same arrays): points (k, 3)."""
    memo(mesh, "hull_points", lambda: points)


def _hull_points(mesh):
    from scipy.spatial import ConvexHull, QhullError

    points = mesh.vertices.view(np.ndarray)
    try:
        return points[np.sort(ConvexHull(points, qhull_options="QbB Pp Qt").vertices)]
    except QhullError:
        try:
            return mesh.convex_hull.vertices.view(np.ndarray)
        except Exception:  # noqa: BLE001 - trimesh raises several kinds here; all the vertices bound the mesh too
            return points
