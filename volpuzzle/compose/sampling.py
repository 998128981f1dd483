"""The global tessellation of every cell face (Sampling): the grid edges bisected until F's chord error meets the
tolerance, then each grid face triangulated between its four edges' samples (triangulate.py), each vertex evaluated
once and held in one global table."""

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..errors import GeometryError
from ..grid import AXES, other_axes
from .lattice import Lattice, periodic_seams
from .triangulate import (
    ROUNDS,
    FaceWork,
    boundary_polygon,
    ccw,
    chain_positions,
    face_chains,
    face_edges,
    ladder,
    merge_sorted,
    refine_faces,
    seed_points,
)

# Measured points (edge midpoints and quarter points, triangle centroids) are held to this fraction of the
# tolerance: for a smooth surface the linear interpolant's error inside a triangle can exceed its value there.
SAFETY = 0.8
_MAX_EDGE_SAMPLES = 20000  # per grid edge; beyond this the tolerance is far below what a printer can show
WELD_MM = 1e-6  # points closer than this are one point (collapsed axes map whole faces onto lines or points)


@dataclass(frozen=True, eq=False)
class FaceMesh:
    """One canonical grid face: ids (k,) global vertex ids; st (k, 2) their coordinates in the face's rectangle
    ([0, 1]^2 along its axes b < c); tris (m, 3) rows of ids' positions, oriented along +e_axis in parameter space."""

    ids: np.ndarray
    st: np.ndarray
    tris: np.ndarray


@dataclass(frozen=True, eq=False)
class Sampling:
    """The global tessellation of every cell face. breaks: the tiling's three break arrays; seams: PeriodicSeam
    tuple; domain (2, 3); uvw (n, 3) parameters and xyz (n, 3) mm of every vertex (each evaluated once); faces:
    {canonical face GridKey: FaceMesh}; max_error_mm: the largest deviation measured between F and its tessellation;
    tolerance: the goal in mm."""

    breaks: tuple
    seams: tuple
    domain: np.ndarray
    uvw: np.ndarray
    xyz: np.ndarray
    faces: dict
    max_error_mm: float
    tolerance: float

    @property
    def lattice(self):
        return Lattice([len(b) - 1 for b in self.breaks], self.seams)

    @property
    def counts(self):
        """(vertices, triangles) of the whole tessellation, each shared face counted once."""
        return len(self.xyz), int(sum(len(f.tris) for f in self.faces.values()))


class _FaceSize(NamedTuple):
    """A grid face's mean lengths in mm along its s and t axes, and whether F squeezes it to nothing along each."""

    length_s: float
    length_t: float
    squeezed_s: bool
    squeezed_t: bool


class _FaceTriangles(NamedTuple):
    """A face's triangulation before it gets its global ids: st (k, 2) its points, the first len(boundary_ids) on
    its boundary (counter-clockwise); boundary_ids (b,) their global ids; tris (m, 3) rows of st."""

    st: np.ndarray
    boundary_ids: np.ndarray
    tris: np.ndarray


def _ro(a):
    """A read-only copy of a."""
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _knot_values(fmap, a, lo, hi):
    """The distinct knots of F's volumes along axis a strictly inside (lo, hi)."""
    vals = []
    for vol in (fmap.warp, fmap.model):
        if vol is not None:
            k = np.unique(np.asarray(vol.knots[a], dtype=float))
            vals.append(k[(k > lo) & (k < hi)])
    return np.unique(np.concatenate(vals)) if vals else np.empty(0)


def _edge_params(key, breaks, t):
    """Fractions t (k,) along grid edge `key` -> uvw (k, 3)."""
    a, g = key.axis, key.corner
    uvw = np.empty((len(t), 3))
    for k in range(3):
        uvw[:, k] = breaks[k][g[k]]
    uvw[:, a] = breaks[a][g[a]] + t * (breaks[a][g[a] + 1] - breaks[a][g[a]])
    return uvw


def _face_params(key, breaks, st):
    """Face coordinates st (k, 2) on grid face `key` -> uvw (k, 3)."""
    a, g = key.axis, key.corner
    b, c = other_axes(a)
    uvw = np.empty((len(st), 3))
    uvw[:, a] = breaks[a][g[a]]
    uvw[:, b] = breaks[b][g[b]] + st[:, 0] * (breaks[b][g[b] + 1] - breaks[b][g[b]])
    uvw[:, c] = breaks[c][g[c]] + st[:, 1] * (breaks[c][g[c] + 1] - breaks[c][g[c]])
    return uvw


def _off_chord(d, chord):
    """Distance (m, k) of points from their chord, given their offsets d (m, k, 3) from points on it and the chords
    (m, 3): only the part across the chord counts (sliding along it is a change of parameter, not of shape)."""
    n = np.linalg.norm(chord, axis=1, keepdims=True)
    u = np.divide(chord, n, out=np.zeros_like(chord), where=n > 0)
    along = np.einsum("mkd,md->mk", d, u)
    return np.sqrt(np.maximum(np.einsum("mkd,mkd->mk", d, d) - along ** 2, 0.0))


def _sample_edges(keys, breaks, fmap, target, tolerance):
    """Bisect every edge's intervals (all edges in one batch per round) until F's chord error at the quarter
    points and the midpoint is at most target. -> ({edge GridKey: sorted fractions (k,)}, {GridKey: xyz (k, 3), the
    last NaN: the end is a grid vertex}, the largest error measured on the final intervals)."""
    t_list, e_list = [], []
    for e, key in enumerate(keys):
        a, g = key.axis, key.corner
        lo, hi = breaks[a][g[a]], breaks[a][g[a] + 1]
        kn = (_knot_values(fmap, a, lo, hi) - lo) / (hi - lo)
        t, _ = merge_sorted(np.array([0.0, 0.5, 1.0]), kn, 1e-7)  # a knot a hair off a break or the midpoint is that
        t_list.append(t)
        e_list.append(np.full(len(t), e))
    uvw = (np.concatenate([_edge_params(k, breaks, t) for k, t in zip(keys, t_list, strict=True)])
           if keys else np.empty((0, 3)))
    x = fmap.evaluate(uvw) if len(uvw) else np.empty((0, 3))
    # the intervals under bisection: their edge (index into keys), ends t0, t1 along it and F there, x0, x1
    ends = np.cumsum([len(t) for t in t_list])
    first = ends - np.array([len(t) for t in t_list], dtype=int)
    sel0 = np.concatenate([np.arange(f, e - 1) for f, e in zip(first, ends, strict=True)]) if keys else np.empty(0, int)
    T = np.concatenate(t_list) if keys else np.empty(0)
    E = np.concatenate(e_list) if keys else np.empty(0, int)
    edge, t0, t1, x0, x1 = E[sel0], T[sel0], T[sel0 + 1], x[sel0], x[sel0 + 1]
    done_edge, done_t, done_x = [], [], []  # the intervals that met the target, by their start
    worst = 0.0
    counts = np.array([len(t) for t in t_list])
    quarters = np.array([0.25, 0.5, 0.75])
    for _ in range(ROUNDS):
        if len(edge) == 0:
            break
        q = t0[:, None] + (t1 - t0)[:, None] * quarters[None, :]  # (m, 3)
        key_of = [keys[i] for i in edge]
        uvw = np.concatenate([_edge_params(k, breaks, q[i]) for i, k in enumerate(key_of)])
        xq = fmap.evaluate(uvw).reshape(len(edge), 3, 3)
        lin = x0[:, None, :] + quarters[None, :, None] * (x1 - x0)[:, None, :]
        err = _off_chord(xq - lin, x1 - x0).max(axis=1)
        bad = err > target
        good = ~bad
        if np.any(good):
            worst = max(worst, float(err[good].max()))
            done_edge.append(edge[good])
            done_t.append(t0[good])
            done_x.append(x0[good])
        if not np.any(bad):
            edge = edge[:0]
            break
        np.add.at(counts, edge[bad], 1)
        if counts.max() > _MAX_EDGE_SAMPLES:
            k = keys[int(np.argmax(counts))]
            raise GeometryError(
                f"output.tolerance: {tolerance:g} mm needs more than {_MAX_EDGE_SAMPLES} samples along "
                f"{AXES[k.axis]} on one cell edge (got tolerance {tolerance:g}, expected a coarser one, "
                f"e.g. {tolerance * 4:g})")
        b_edge, b_t0, b_t1, b_x0, b_x1 = edge[bad], t0[bad], t1[bad], x0[bad], x1[bad]
        tm, xm = 0.5 * (b_t0 + b_t1), xq[bad, 1]
        edge = np.concatenate([b_edge, b_edge])
        t0, t1 = np.concatenate([b_t0, tm]), np.concatenate([tm, b_t1])
        x0, x1 = np.concatenate([b_x0, xm]), np.concatenate([xm, b_x1])
    if len(edge):
        raise GeometryError(f"output.tolerance: the cell edges did not reach {tolerance:g} mm in {ROUNDS} rounds")
    de = np.concatenate(done_edge) if done_edge else np.empty(0, int)
    dt = np.concatenate(done_t) if done_t else np.empty(0)
    dx = np.concatenate(done_x) if done_x else np.empty((0, 3))
    order = np.lexsort((dt, de))
    de, dt, dx = de[order], dt[order], dx[order]
    split = np.searchsorted(de, np.arange(len(keys) + 1))
    ts, xs = {}, {}
    for e, key in enumerate(keys):
        s, f = split[e], split[e + 1]
        ts[key] = np.append(dt[s:f], 1.0)
        xs[key] = np.concatenate([dx[s:f], [[np.nan] * 3]])  # the end is a grid vertex
    return ts, xs, worst


def _edge_end(key):
    """The grid vertex where edge `key` ends: its corner + e_axis."""
    return tuple(key.corner[k] + (k == key.axis) for k in range(3))


def _face_lengths(x5):
    """F on a (5, 5) grid of a face (i along s, j along t) -> _FaceSize."""
    ds = np.linalg.norm(np.diff(x5, axis=0), axis=2)  # (4, 5)
    dt = np.linalg.norm(np.diff(x5, axis=1), axis=2)  # (5, 4)
    spread_s = np.linalg.norm(x5 - x5[:1], axis=2).max()
    spread_t = np.linalg.norm(x5 - x5[:, :1], axis=2).max()
    return _FaceSize(ds.sum(axis=0).mean(), dt.sum(axis=1).mean(), spread_s <= WELD_MM, spread_t <= WELD_MM)


def sample_parameters(tiling, fmap, tolerance):
    """The adaptive tessellation of every cell face: edges bisected, faces refined, until the tessellation deviates
    from F by at most `tolerance` mm at the measured points. -> Sampling."""
    tolerance = float(tolerance)
    if not tolerance > 0:
        raise GeometryError(f"output.tolerance: must be > 0 mm (got {tolerance:g})")
    target = SAFETY * tolerance
    seams = periodic_seams(tiling)
    breaks = tuple(np.asarray(b, dtype=float) for b in tiling.breaks)
    lat = Lattice([len(b) - 1 for b in breaks], seams)

    # canonical faces, edges, vertices
    faces = sorted({lat.face(a, g)[0] for index in sorted(tiling.cells) for a, g in
                    ((a, tuple(index[k] + (side if k == a else 0) for k in range(3)))
                     for a in range(3) for side in (0, 1))})
    edges = sorted({lat.edge(axis, start)[0] for key in faces for axis, start in face_edges(key)})
    verts = sorted({lat.vertex(g) for key in edges for g in (key.corner, _edge_end(key))})
    vid = {g: i for i, g in enumerate(verts)}
    v_uvw = np.array([[breaks[k][g[k]] for k in range(3)] for g in verts], dtype=float)

    # how long each face is in mm, and whether F squeezes it onto a line or a point (collapsed axes)
    grid5 = np.linspace(0.0, 1.0, 5)
    st5 = np.stack(np.meshgrid(grid5, grid5, indexing="ij"), -1).reshape(-1, 2)
    x5 = fmap.evaluate(np.concatenate([_face_params(k, breaks, st5) for k in faces]) if faces else np.empty((0, 3)))
    x5 = x5.reshape(len(faces), 5, 5, 3)
    size = {k: _face_lengths(x5[i]) for i, k in enumerate(faces)}

    ts, xs, worst_edge = _sample_edges(edges, breaks, fmap, target, tolerance)
    # a face squeezed across one direction is laddered between its two rails, which must then carry the same levels
    ladders = [k for k in faces if size[k].squeezed_s != size[k].squeezed_t]
    changed_keys = set()
    for _ in range(64):
        changed = False
        for key in ladders:
            bottom, right, top, left = face_edges(key)
            rails = (left, right) if size[key].squeezed_s else (bottom, top)
            refs = [lat.edge(axis, start) for axis, start in rails]
            local = [1.0 - ts[k][::-1] if rev else ts[k] for k, rev in refs]
            for (k, rev), mine, other in ((refs[0], local[0], local[1]), (refs[1], local[1], local[0])):
                merged, grew = merge_sorted(mine, other, 1e-12)
                if grew:
                    ts[k] = 1.0 - merged[::-1] if rev else merged
                    changed_keys.add(k)
                    changed = True
        if not changed:
            break
    else:
        raise GeometryError("compose: the samples of squeezed faces did not settle (internal error)")
    if changed_keys:
        resampled = sorted(changed_keys)
        x = fmap.evaluate(np.concatenate([_edge_params(k, breaks, ts[k]) for k in resampled]))
        pos = 0
        for k in resampled:
            xs[k] = x[pos:pos + len(ts[k])]
            pos += len(ts[k])

    # global ids: grid vertices, then edge interiors, then face interiors
    uvw_parts, xyz_parts = [v_uvw], [fmap.evaluate(v_uvw)]
    n_ids = len(verts)
    e_ids = {}
    for key in edges:
        t = ts[key]
        inner = np.arange(n_ids, n_ids + len(t) - 2)
        n_ids += len(inner)
        e_ids[key] = np.concatenate([[vid[lat.vertex(key.corner)]], inner,
                                     [vid[lat.vertex(_edge_end(key))]]]).astype(np.int64)
        uvw_parts.append(_edge_params(key, breaks, t[1:-1]))
        xyz_parts.append(xs[key][1:-1])
    xyz_so_far = np.concatenate(xyz_parts)

    triangulated, works = {}, {}
    for key in faces:
        chains = face_chains(lat, key, ts, e_ids)
        st_b, ids_b = boundary_polygon(chains)
        face_size = size[key]
        if face_size.squeezed_s and face_size.squeezed_t:
            # a whole face on one point: a fan about its centre, which welding removes
            c = len(st_b)
            tris = np.array([(c, i, (i + 1) % c) for i in range(c)], dtype=np.int64)
            triangulated[key] = _FaceTriangles(np.concatenate([st_b, [[0.5, 0.5]]]), ids_b, tris)
        elif face_size.squeezed_s or face_size.squeezed_t:
            bottom, right, top, left = chain_positions(chains)
            rails = (left, right, bottom, top) if face_size.squeezed_s else (bottom, top, left, right)
            triangulated[key] = _FaceTriangles(st_b, ids_b, np.array(ladder(*rails), dtype=np.int64))
        else:
            g = key.corner
            knots = []
            for ax in other_axes(key.axis):
                lo, hi = breaks[ax][g[ax]], breaks[ax][g[ax] + 1]
                knots.append((_knot_values(fmap, ax, lo, hi) - lo) / (hi - lo))
            ls, lt = face_size.length_s, face_size.length_t
            scale = np.maximum([ls, lt], 1e-9 * max(ls, lt, 1e-3))
            works[key] = FaceWork(key, st_b, ids_b, xyz_so_far[ids_b], scale, seed_points(scale, *knots))

    worst_face = refine_faces(list(works.values()), breaks, fmap, target, tolerance)
    for w in works.values():
        triangulated[w.key] = _FaceTriangles(w.st, w.boundary_ids, w.tris)

    face_meshes = {}
    for key in faces:
        st, ids_b, tris = triangulated[key]
        n_in = len(st) - len(ids_b)
        ids = np.concatenate([ids_b, np.arange(n_ids, n_ids + n_in)]).astype(np.int64)
        n_ids += n_in
        if n_in:
            uvw_in = _face_params(key, breaks, st[len(ids_b):])
            uvw_parts.append(uvw_in)
            w = works.get(key)
            xyz_parts.append(w.xyz[len(ids_b):] if w is not None else fmap.evaluate(uvw_in))
        tris, _ = ccw(st, np.asarray(tris, dtype=np.int64))
        if key.axis == 1:  # e_u x e_w = -e_v: counter-clockwise in (s, t) faces -v
            tris = tris[:, [0, 2, 1]]
        face_meshes[key] = FaceMesh(_ro(ids), _ro(st), _ro(tris))
    uvw = np.concatenate(uvw_parts)
    xyz = np.concatenate(xyz_parts)
    if not np.all(np.isfinite(xyz)):
        raise GeometryError("compose: F gave non-finite points on the cell faces")
    return Sampling(breaks, seams, _ro(np.asarray(tiling.domain, dtype=float)), _ro(uvw), _ro(xyz), face_meshes,
                    float(max(worst_edge, worst_face)), tolerance)
