"""compose: turn every cell of the tiling into a closed solid in mm, through the map F = M o R, with its joints.

The cell boxes' boundaries are tessellated once for the whole tiling, adaptively per face, in one global vertex table:
  1. grid vertices (the cells' corners);
  2. on every grid edge, 1D samples bisected until F's chord error meets the tolerance;
  3. on every grid face, a 2D triangulation of its parameter rectangle whose boundary is exactly its four edges'
     samples: one Delaunay triangulation of the boundary and a coarse seed (on the face's parameters scaled to mm),
     then longest-edge bisection of every triangle that misses F, until every triangle meets the tolerance.
The tolerance bounds the distance across the surface (from F at a triangle's centroid, edge midpoints and random
points to the triangle's plane; for edges, to the chord): a slide along the surface is a change of parameter, not of
shape, and counting it (as a tensor grid must) multiplied the triangles.
Each vertex is evaluated once and every face is triangulated once, so the two cells on a shared face (also across a
periodic seam, where the min face is the max face seen through the seam map) use the same vertex ids and the same
triangles: neighbours meet on one cut surface, bit for bit. A cell's surface is its six face meshes, oriented outward.
"""

import concurrent.futures
import multiprocessing
import os
import time
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import Delaunay

from .. import geometry
from ..errors import GeometryError
from ..grid import AXES

# Measured points (edge midpoints and quarter points, triangle centroids) are held to this fraction of the
# tolerance: for a smooth surface the linear interpolant's error inside a triangle can exceed its value there.
_SAFETY = 0.8
_MAX_EDGE_SAMPLES = 20000  # per grid edge; beyond this the tolerance is far below what a printer can show
_MAX_FACE_POINTS = 100000  # per grid face, on average
_ROUNDS = 60
_WELD_MM = 1e-6  # points closer than this are one point (collapsed axes map whole faces onto lines or points)
_FADE = 4.0  # half-clearances over which points inside a face follow the slide of its set-back edge
_BULGE = (1e-3, 1e-5, 1e-7)  # how far face boundaries are bowed out so that Delaunay keeps them (fraction of size)
# A spawned worker costs ~2.5 s of CPU (imports, pickling) before it builds anything. This process keeps building
# meanwhile (see _pooled), but on a busy machine the start-up takes 10 s of wall time, and the pieces handed to the
# workers then can hold up the end: measured with the 256-piece twisted torus (compose ~2.7 CPU s) the pool was
# slower than serial, so serial below this estimate.
_POOL_MIN_PIECES = 16
_POOL_MIN_SECONDS = 5.0
_MAIN_TAKES_PIECES = True  # False: the workers build every piece (tests use it to see them do so)
_SECONDS_PER_TRIANGLE = 1e-5  # building, checking and converting one piece triangle (measured, 2 cores, loaded)
_SECONDS_PER_JOINT = 0.005  # the booleans of one pin and its hole


def _others(a):
    return tuple(k for k in range(3) if k != a)


# ------------------------------------------------------------------------------------------------------------
# the lattice of grid vertices, edges and faces, and where periodic seams identify them


class _Lattice:
    """Integer grid: vertex g (3,) indexes the breaks; edge (a, g) runs from g to g + e_a; face (a, g) is the
    rectangle at g spanned by the other two axes (b, c), b < c. Points on a periodic min face are identified with
    points on the max face (their canonical place)."""

    def __init__(self, n, seams):
        self.n = tuple(int(x) for x in n)
        self.seams = tuple(seams)

    def _to_max(self, g, seam):
        a, swap, flip = seam
        b, c = _others(a)
        jb, jc = g[b], g[c]
        # the inverse of Seam.map_max_to_min on the (integer, break-aligned) face coordinates: unflip, then unswap
        if flip[0]:
            jb = self.n[b] - jb
        if flip[1]:
            jc = self.n[c] - jc
        if swap:
            jb, jc = jc, jb
        out = list(g)
        out[a], out[b], out[c] = self.n[a], jb, jc
        return out

    def vertex(self, g):
        g = list(g)
        for _ in range(8):
            moved = False
            for s in self.seams:
                if g[s[0]] == 0:
                    g = self._to_max(g, s)
                    moved = True
            if not moved:
                return tuple(g)
        raise GeometryError("compose: grid vertices did not settle under the periodic seams")

    def edge(self, a, g):
        """-> (canonical key (axis, g0, g1, g2), reversed: the canonical edge runs the other way)."""
        p0, p1 = list(g), list(g)
        p1[a] += 1
        for _ in range(8):
            moved = False
            for s in self.seams:
                if p0[s[0]] == 0 and p1[s[0]] == 0:
                    p0, p1 = self._to_max(p0, s), self._to_max(p1, s)
                    moved = True
            if not moved:
                break
        else:
            raise GeometryError("compose: grid edges did not settle under the periodic seams")
        ax = next(k for k in range(3) if p0[k] != p1[k])
        rev = p0[ax] > p1[ax]
        lo = p1 if rev else p0
        return (ax, *lo), rev

    def face(self, a, g):
        """-> (canonical key (a, g0, g1, g2), seam (a, swap, flip) the face was seen through, or None)."""
        for s in self.seams:
            if s[0] == a and g[a] == 0:
                b, c = _others(a)
                corners = []
                for db, dc in ((0, 0), (1, 0), (0, 1), (1, 1)):
                    p = list(g)
                    p[b] += db
                    p[c] += dc
                    corners.append(self._to_max(p, s))
                lo = np.min(np.array(corners), axis=0)
                return (a, *(int(x) for x in lo)), s
        return (a, *(int(x) for x in g)), None

    def cell_faces(self, index):
        """The six faces of a cell: (canonical key, min side (so reversed), seam or None, own (a, g))."""
        out = []
        for a in range(3):
            for side in (0, 1):
                g = list(index)
                g[a] += side
                key, seam = self.face(a, g)
                out.append((key, side == 0, seam, (a, tuple(g))))
        return out


def _seam_tuples(tiling):
    out = []
    for a in sorted(tiling.seams):
        if a in tiling.periodic:
            s = tiling.seams[a]
            out.append((int(a), bool(s.swap), tuple(bool(x) for x in s.flip)))
    return tuple(out)


def _seen_through(st, seam):
    """Canonical (max face) local coordinates (k, 2) -> the same points in the min face's own coordinates:
    Seam.map_max_to_min, swap then flip (the cut grids are symmetric, so it holds cell by cell)."""
    if seam is None:
        return st
    _, swap, flip = seam
    st = np.array(st[:, ::-1] if swap else st, dtype=float)
    for k in range(2):
        if flip[k]:
            st[:, k] = 1.0 - st[:, k]
    return st


# ------------------------------------------------------------------------------------------------------------
# sampling


@dataclass(frozen=True, eq=False)
class FaceMesh:
    """One canonical grid face: ids (k,) global vertex ids; st (k, 2) their coordinates in the face's rectangle
    ([0, 1]^2 along its axes b < c); tris (m, 3) rows of ids' positions, oriented along +e_axis in parameter space."""

    ids: np.ndarray
    st: np.ndarray
    tris: np.ndarray


@dataclass(frozen=True, eq=False)
class Sampling:
    """The global tessellation of every cell face. breaks: the tiling's three break arrays; seams: (axis, swap, flip)
    tuples; domain (2, 3); uvw (n, 3) parameters and xyz (n, 3) mm of every vertex (each evaluated once); faces:
    {canonical face key: FaceMesh}; max_error_mm: the largest deviation measured between F and its tessellation;
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
        return _Lattice([len(b) - 1 for b in self.breaks], self.seams)

    @property
    def counts(self):
        """(vertices, triangles) of the whole tessellation, each shared face counted once."""
        return len(self.xyz), int(sum(len(f.tris) for f in self.faces.values()))


def _ro(a):
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _knot_values(fmap, a, lo, hi):
    vals = []
    for vol in (fmap.warp, fmap.model):
        if vol is not None:
            k = np.unique(np.asarray(vol.knots[a], dtype=float))
            vals.append(k[(k > lo) & (k < hi)])
    return np.unique(np.concatenate(vals)) if vals else np.empty(0)


def _edge_params(key, breaks, t):
    a, g = key[0], key[1:]
    uvw = np.empty((len(t), 3))
    for k in range(3):
        uvw[:, k] = breaks[k][g[k]]
    uvw[:, a] = breaks[a][g[a]] + t * (breaks[a][g[a] + 1] - breaks[a][g[a]])
    return uvw


def _face_params(key, breaks, st):
    a, g = key[0], key[1:]
    b, c = _others(a)
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


def _deviation(d, corners):
    """Distance (m, k) of points from their triangles' planes, given their offsets d (m, k, 3) from the linear
    interpolant and the triangles' corners (m, 3, 3) in mm: only the part across the surface counts (sliding along
    it is a change of parameter, not of shape). A degenerate triangle (on a collapsed axis) counts the whole offset."""
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    size = np.linalg.norm(n, axis=1)
    scale = np.max(np.linalg.norm(corners - corners[:, :1], axis=2), axis=1)
    flat = size <= 1e-9 * scale ** 2
    n = np.divide(n, size[:, None], out=np.zeros_like(n), where=~flat[:, None])
    out = np.abs(np.einsum("mkd,md->mk", d, n))
    out[flat] = np.linalg.norm(d[flat], axis=2)
    return out


def _sample_edges(keys, breaks, fmap, target, tolerance):
    """Bisect every edge's intervals (all edges in one batch per round) until F's chord error at the quarter
    points and the midpoint is at most target. -> ({key: sorted fractions (k,)}, {key: xyz (k, 3)}, worst)."""
    t_list, e_list = [], []
    for e, key in enumerate(keys):
        a, g = key[0], key[1:]
        lo, hi = breaks[a][g[a]], breaks[a][g[a] + 1]
        kn = (_knot_values(fmap, a, lo, hi) - lo) / (hi - lo)
        t, _ = _merge(np.array([0.0, 0.5, 1.0]), kn, 1e-7)  # a knot a hair off a break or the midpoint is that
        t_list.append(t)
        e_list.append(np.full(len(t), e))
    uvw = (np.concatenate([_edge_params(k, breaks, t) for k, t in zip(keys, t_list, strict=True)])
           if keys else np.empty((0, 3)))
    x = fmap.evaluate(uvw) if len(uvw) else np.empty((0, 3))
    # intervals: edge, t0, t1, x0, x1
    ends = np.cumsum([len(t) for t in t_list])
    first = ends - np.array([len(t) for t in t_list], dtype=int)
    sel0 = np.concatenate([np.arange(f, e - 1) for f, e in zip(first, ends, strict=True)]) if keys else np.empty(0, int)
    T = np.concatenate(t_list) if keys else np.empty(0)
    E = np.concatenate(e_list) if keys else np.empty(0, int)
    ie, t0, t1, x0, x1 = E[sel0], T[sel0], T[sel0 + 1], x[sel0], x[sel0 + 1]
    done = []
    worst = 0.0
    counts = np.array([len(t) for t in t_list])
    fr = np.array([0.25, 0.5, 0.75])
    for _ in range(_ROUNDS):
        if len(ie) == 0:
            break
        q = t0[:, None] + (t1 - t0)[:, None] * fr[None, :]  # (m, 3)
        key_of = [keys[i] for i in ie]
        uvw = np.concatenate([_edge_params(k, breaks, q[i]) for i, k in enumerate(key_of)])
        xq = fmap.evaluate(uvw).reshape(len(ie), 3, 3)
        lin = x0[:, None, :] + fr[None, :, None] * (x1 - x0)[:, None, :]
        err = _off_chord(xq - lin, x1 - x0).max(axis=1)
        bad = err > target
        good = ~bad
        if np.any(good):
            worst = max(worst, float(err[good].max()))
            done.append((ie[good], t0[good], x0[good]))
        if not np.any(bad):
            ie = ie[:0]
            break
        np.add.at(counts, ie[bad], 1)
        if counts.max() > _MAX_EDGE_SAMPLES:
            k = keys[int(np.argmax(counts))]
            raise GeometryError(
                f"output.tolerance: {tolerance:g} mm needs more than {_MAX_EDGE_SAMPLES} samples along "
                f"{AXES[k[0]]} on one cell edge (got tolerance {tolerance:g}, expected a coarser one, "
                f"e.g. {tolerance * 4:g})")
        b_ie, b_t0, b_t1, b_x0, b_x1 = ie[bad], t0[bad], t1[bad], x0[bad], x1[bad]
        tm, xm = 0.5 * (b_t0 + b_t1), xq[bad, 1]
        ie = np.concatenate([b_ie, b_ie])
        t0, t1 = np.concatenate([b_t0, tm]), np.concatenate([tm, b_t1])
        x0, x1 = np.concatenate([b_x0, xm]), np.concatenate([xm, b_x1])
    if len(ie):
        raise GeometryError(f"output.tolerance: the cell edges did not reach {tolerance:g} mm in {_ROUNDS} rounds")
    de = np.concatenate([d[0] for d in done]) if done else np.empty(0, int)
    dt = np.concatenate([d[1] for d in done]) if done else np.empty(0)
    dx = np.concatenate([d[2] for d in done]) if done else np.empty((0, 3))
    order = np.lexsort((dt, de))
    de, dt, dx = de[order], dt[order], dx[order]
    split = np.searchsorted(de, np.arange(len(keys) + 1))
    ts, xs = {}, {}
    for e, key in enumerate(keys):
        s, f = split[e], split[e + 1]
        ts[key] = np.append(dt[s:f], 1.0)
        xs[key] = np.concatenate([dx[s:f], [[np.nan] * 3]])  # the end is a grid vertex
    return ts, xs, worst


def _merge(values, new, eps):
    """Sorted union of values and new, skipping new values within eps of one already there."""
    values = np.asarray(values, dtype=float)
    new = np.asarray(new, dtype=float)
    if new.size == 0:
        return values, False
    pos = np.clip(np.searchsorted(values, new), 1, len(values) - 1)
    near = np.minimum(np.abs(values[pos] - new), np.abs(values[pos - 1] - new)) <= eps
    new = np.unique(new[~near])
    if new.size == 0:
        return values, False
    keep = np.concatenate([[True], np.diff(new) > eps])
    return np.union1d(values, new[keep]), True


def _edge_ref(lat, axis, start, ts, ids):
    """The samples of the edge along axis from grid vertex start, in increasing local order: (t (k,), ids (k,))."""
    key, rev = lat.edge(axis, start)
    t, i = ts[key], ids[key]
    return (1.0 - t[::-1], i[::-1]) if rev else (t, i)


def _face_edges(key):
    """The four edges of a face in its own frame: bottom (t=0), right (s=1), top (t=1), left (s=0), as
    (axis, start) pairs; each runs in increasing s or t."""
    a, g = key[0], list(key[1:])
    b, c = _others(a)
    gb, gc = list(g), list(g)
    gb[b] += 1
    gc[c] += 1
    return (b, g), (c, gb), (b, gc), (c, g)


def _chains(lat, key, ts, ids):
    """-> four (st (k, 2), ids (k,)) chains, each in increasing s or t: bottom, right, top, left."""
    out = []
    for k, (axis, start) in enumerate(_face_edges(key)):
        t, i = _edge_ref(lat, axis, start, ts, ids)
        st = np.empty((len(t), 2))
        if k in (0, 2):
            st[:, 0], st[:, 1] = t, 0.0 if k == 0 else 1.0
        else:
            st[:, 0], st[:, 1] = 1.0 if k == 1 else 0.0, t
        out.append((st, i))
    return out


def _polygon(chains):
    """The four chains -> the face boundary counter-clockwise in (s, t): st (k, 2), ids (k,), each corner once."""
    (sb, ib), (sr, ir), (su, iu), (sl, il) = chains
    st = np.concatenate([sb[:-1], sr[:-1], su[::-1][:-1], sl[::-1][:-1]])
    ids = np.concatenate([ib[:-1], ir[:-1], iu[::-1][:-1], il[::-1][:-1]])
    return st, ids


def _chain_local(chains):
    """Positions in _polygon's order of the four chains' points (each in increasing s or t)."""
    lens = [len(c[1]) for c in chains]
    total = sum(lens) - 4
    o_r = lens[0] - 1
    o_u = o_r + lens[1] - 1
    o_l = o_u + lens[2] - 1
    bottom = np.arange(lens[0])
    right = o_r + np.arange(lens[1])
    top = o_u + (lens[2] - 1 - np.arange(lens[2]))
    left = (o_l + (lens[3] - 1 - np.arange(lens[3]))) % total
    return bottom, right, top, left


def _ladder(rail_l, rail_r, cap_lo, cap_hi):
    """Triangles (as id triples) of a face that F squeezes across the rails' direction: rails l and r carry the same
    levels, and every triangle joins only neighbouring levels, so after welding each has a repeated vertex.
    cap_lo runs from l[0] to r[0], cap_hi from l[-1] to r[-1]."""
    n = len(rail_l) - 1
    L, R = rail_l, rail_r
    tris = []
    if n == 1:
        tris += [(L[1], cap_lo[k], cap_lo[k + 1]) for k in range(len(cap_lo) - 1)]
        tris += [(R[0], cap_hi[k], cap_hi[k + 1]) for k in range(len(cap_hi) - 1)]
        return tris
    tris += [(L[1], cap_lo[k], cap_lo[k + 1]) for k in range(len(cap_lo) - 1)]
    tris.append((L[1], R[0], R[1]))
    for i in range(1, n - 1):
        tris += [(L[i], R[i], R[i + 1]), (L[i], R[i + 1], L[i + 1])]
    tris += [(R[n - 1], cap_hi[k], cap_hi[k + 1]) for k in range(len(cap_hi) - 1)]
    tris.append((L[n - 1], R[n - 1], L[n]))
    return tris


def _signed_area(p, tris):
    a, b, c = p[tris[:, 0]], p[tris[:, 1]], p[tris[:, 2]]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


def _ccw(p, tris):
    area = _signed_area(p, tris)
    tris = np.where((area < 0)[:, None], tris[:, [0, 2, 1]], tris)
    return tris, np.abs(area)


class _FaceWork:
    """One canonical face under refinement: points st (k, 2) in its rectangle, their xyz, the first nb on the
    boundary (counter-clockwise), scaled by the face's lengths in mm for well-shaped triangles."""

    def __init__(self, key, st_b, ids_b, xyz_b, scale, seed):
        self.key = key
        self.nb = len(st_b)
        self.ids_b = ids_b
        self.st = np.concatenate([st_b, seed])
        self.xyz = np.concatenate([xyz_b, np.full((len(seed), 3), np.nan)])
        self.scale = np.asarray(scale, dtype=float)
        self.tris = None
        self.worst = 0.0
        self.rng = np.random.default_rng([int(x) for x in key])

    def triangulate(self):
        nb, n = self.nb, len(self.st)
        s, t = self.st[:, 0], self.st[:, 1]
        true = self.st * self.scale
        total = float(np.prod(self.scale))
        for eps in _BULGE:
            # bow every side outward (zero at the corners) so that collinear boundary points become strictly convex:
            # the hull is then exactly the boundary, and Delaunay keeps every boundary segment
            q = np.stack([(s - 0.5) * (1 + eps * 4 * t * (1 - t)), (t - 0.5) * (1 + eps * 4 * s * (1 - s))], 1)
            try:
                tri = Delaunay(q * self.scale).simplices.astype(np.int64)
            except Exception:  # qhull refuses (e.g. too few distinct points): try a smaller bulge, then give up
                continue
            tri, area = _ccw(true, tri)
            if len(np.unique(tri)) != n or np.min(area) <= 1e-12 * total or abs(area.sum() - total) > 1e-9 * total:
                continue
            e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
            bnd = np.sort(np.stack([np.arange(nb), (np.arange(nb) + 1) % nb], 1), axis=1)
            have = set(map(tuple, e[(e[:, 1] < nb)]))
            if all(tuple(x) in have for x in bnd):
                self.tris = tri
                return tri
        raise GeometryError(f"compose: could not triangulate the {AXES[self.key[0]]} face at grid {self.key[1:]} "
                            f"with {n} points (internal error)")


def _face_lengths(x5):
    """F on a (5, 5) grid of a face (i along s, j along t) -> mean lengths along s and t, collapsed along s / t."""
    ds = np.linalg.norm(np.diff(x5, axis=0), axis=2)  # (4, 5)
    dt = np.linalg.norm(np.diff(x5, axis=1), axis=2)  # (5, 4)
    spread_s = np.linalg.norm(x5 - x5[:1], axis=2).max()
    spread_t = np.linalg.norm(x5 - x5[:, :1], axis=2).max()
    return ds.sum(axis=0).mean(), dt.sum(axis=1).mean(), spread_s <= _WELD_MM, spread_t <= _WELD_MM


def _seed(scale, knots_s, knots_t):
    """A coarse interior grid (about 4 cells across the longer side) plus points on the interior knot lines."""
    h = max(scale) / 4.0
    ks, kt = (max(2, int(round(x / h))) for x in scale)
    s = np.arange(1, ks) / ks
    t = np.arange(1, kt) / kt
    s_all, _ = _merge(np.concatenate([[0.0], s, [1.0]]), knots_s, 1e-9)
    t_all, _ = _merge(np.concatenate([[0.0], t, [1.0]]), knots_t, 1e-9)
    pts = [np.stack(np.meshgrid(s, t_all, indexing="ij"), -1).reshape(-1, 2),
           np.stack(np.meshgrid(s_all, t, indexing="ij"), -1).reshape(-1, 2)]
    pts = np.unique(np.concatenate(pts), axis=0)
    # a knot line a hair inside the face (a file's rounded knots next to a split) would leave sliver triangles
    e = 1e-4
    return pts[(pts[:, 0] > e) & (pts[:, 0] < 1 - e) & (pts[:, 1] > e) & (pts[:, 1] < 1 - e)]


def sample_parameters(tiling, fmap, tolerance):
    """The adaptive tessellation of every cell face: edges bisected, faces refined, until the tessellation deviates
    from F by at most `tolerance` mm at the measured points. -> Sampling."""
    tolerance = float(tolerance)
    if not tolerance > 0:
        raise GeometryError(f"output.tolerance: must be > 0 mm (got {tolerance:g})")
    target = _SAFETY * tolerance
    seams = _seam_tuples(tiling)
    breaks = tuple(np.asarray(b, dtype=float) for b in tiling.breaks)
    lat = _Lattice([len(b) - 1 for b in breaks], seams)

    # canonical faces, edges, vertices
    faces = sorted({lat.face(a, g)[0] for index in sorted(tiling.cells) for a, g in
                    ((a, tuple(index[k] + (side if k == a else 0) for k in range(3)))
                     for a in range(3) for side in (0, 1))})
    edges = sorted({lat.edge(axis, start)[0] for key in faces for axis, start in _face_edges(key)})
    verts = sorted({lat.vertex(g) for key in edges for g in (key[1:], tuple(key[1 + k] + (k == key[0])
                                                                             for k in range(3)))})
    vid = {g: i for i, g in enumerate(verts)}
    v_uvw = np.array([[breaks[k][g[k]] for k in range(3)] for g in verts], dtype=float)

    # how long each face is in mm, and whether F squeezes it onto a line or a point (collapsed axes)
    grid5 = np.linspace(0.0, 1.0, 5)
    st5 = np.stack(np.meshgrid(grid5, grid5, indexing="ij"), -1).reshape(-1, 2)
    x5 = fmap.evaluate(np.concatenate([_face_params(k, breaks, st5) for k in faces]) if faces else np.empty((0, 3)))
    x5 = x5.reshape(len(faces), 5, 5, 3)
    info = {k: _face_lengths(x5[i]) for i, k in enumerate(faces)}

    ts, xs, worst_edge = _sample_edges(edges, breaks, fmap, target, tolerance)
    # a face squeezed across one direction is laddered between its two rails, which must then carry the same levels
    ladders = [k for k in faces if info[k][2] != info[k][3]]
    changed_keys = set()
    for _ in range(64):
        changed = False
        for key in ladders:
            bottom, right, top, left = _face_edges(key)
            rails = (left, right) if info[key][2] else (bottom, top)
            refs = [lat.edge(axis, start) for axis, start in rails]
            local = [1.0 - ts[k][::-1] if rev else ts[k] for k, rev in refs]
            for (k, rev), mine, other in ((refs[0], local[0], local[1]), (refs[1], local[1], local[0])):
                u, ch = _merge(mine, other, 1e-12)
                if ch:
                    ts[k] = 1.0 - u[::-1] if rev else u
                    changed_keys.add(k)
                    changed = True
        if not changed:
            break
    else:
        raise GeometryError("compose: the samples of squeezed faces did not settle (internal error)")
    if changed_keys:
        ck = sorted(changed_keys)
        x = fmap.evaluate(np.concatenate([_edge_params(k, breaks, ts[k]) for k in ck]))
        pos = 0
        for k in ck:
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
        g1 = tuple(key[1 + k] + (k == key[0]) for k in range(3))
        e_ids[key] = np.concatenate([[vid[lat.vertex(key[1:])]], inner, [vid[lat.vertex(g1)]]]).astype(np.int64)
        uvw_parts.append(_edge_params(key, breaks, t[1:-1]))
        xyz_parts.append(xs[key][1:-1])
    xyz_so_far = np.concatenate(xyz_parts)

    meshes, works = {}, []
    for key in faces:
        chains = _chains(lat, key, ts, e_ids)
        st_b, ids_b = _polygon(chains)
        ls, lt, squeezed_s, squeezed_t = info[key]
        if squeezed_s and squeezed_t:
            # a whole face on one point: a fan about its centre, which welding removes
            c = len(st_b)
            tris = np.array([(c, i, (i + 1) % c) for i in range(c)], dtype=np.int64)
            meshes[key] = (np.concatenate([st_b, [[0.5, 0.5]]]), ids_b, tris, True)
        elif squeezed_s or squeezed_t:
            bl, rl, ul, ll = _chain_local(chains)
            rails = (ll, rl, bl, ul) if squeezed_s else (bl, ul, ll, rl)
            meshes[key] = (st_b, ids_b, np.array(_ladder(*rails), dtype=np.int64), False)
        else:
            a, g = key[0], key[1:]
            b, c = _others(a)
            kn = []
            for ax in (b, c):
                lo, hi = breaks[ax][g[ax]], breaks[ax][g[ax] + 1]
                kn.append((_knot_values(fmap, ax, lo, hi) - lo) / (hi - lo))
            scale = np.maximum([ls, lt], 1e-9 * max(ls, lt, 1e-3))
            works.append(_FaceWork(key, st_b, ids_b, xyz_so_far[ids_b], scale, _seed(scale, *kn)))

    worst_face = _refine_faces(works, breaks, fmap, target, tolerance)
    for w in works:
        meshes[w.key] = (w.st, w.ids_b, w.tris, False)

    fm = {}
    for key in faces:
        st, ids_b, tris, centre = meshes[key]
        n_in = len(st) - len(ids_b)
        ids = np.concatenate([ids_b, np.arange(n_ids, n_ids + n_in)]).astype(np.int64)
        n_ids += n_in
        if n_in:
            uvw_in = _face_params(key, breaks, st[len(ids_b):])
            uvw_parts.append(uvw_in)
            w = next((w for w in works if w.key == key), None)
            xyz_parts.append(w.xyz[len(ids_b):] if w is not None else fmap.evaluate(uvw_in))
        tris, _ = _ccw(st, np.asarray(tris, dtype=np.int64))
        if key[0] == 1:  # e_u x e_w = -e_v: counter-clockwise in (s, t) faces -v
            tris = tris[:, [0, 2, 1]]
        fm[key] = FaceMesh(_ro(ids), _ro(st), _ro(tris))
    uvw = np.concatenate(uvw_parts)
    xyz = np.concatenate(xyz_parts)
    if not np.all(np.isfinite(xyz)):
        raise GeometryError("compose: F gave non-finite points on the cell faces")
    return Sampling(breaks, seams, _ro(np.asarray(tiling.domain, dtype=float)), _ro(uvw), _ro(xyz), fm,
                    float(max(worst_edge, worst_face)), tolerance)


def _member(keys, sorted_keys):
    """keys (any shape) found in the sorted 1-d sorted_keys: a binary search, cheaper than np.isin's sort of both."""
    pos = np.clip(np.searchsorted(sorted_keys, keys), 0, len(sorted_keys) - 1)
    return sorted_keys[pos] == keys


def _refine_faces(works, breaks, fmap, target, tolerance):
    """Refine every face from its initial Delaunay triangulation, all faces in one batch per round: triangles whose
    tessellation misses F (at the centroid, the interior edge midpoints and two random points) by more than target
    have their longest interior edge bisected, with the longest-edge closure of Rivara so that triangles stay well
    shaped and the mesh conforming. Boundary segments are never split: they are the neighbours' edges.
    Sets each work's st, xyz and tris. -> the largest error measured on the final triangles."""
    if not works:
        return 0.0
    for w in works:
        w.triangulate()
    sizes = np.array([len(w.st) for w in works])
    off = np.concatenate([[0], np.cumsum(sizes)])
    st = np.concatenate([w.st for w in works])
    xyz = np.concatenate([w.xyz for w in works])
    fid = np.repeat(np.arange(len(works)), sizes)
    tris = np.concatenate([w.tris + off[k] for k, w in enumerate(works)])
    big = np.int64(1) << 31
    bkeys = []
    for k, w in enumerate(works):
        i = np.arange(w.nb)
        e = np.sort(np.stack([i, (i + 1) % w.nb], 1), axis=1) + off[k]
        bkeys.append(e[:, 0] * big + e[:, 1])
    bkeys = np.sort(np.concatenate(bkeys))
    # per face: uvw = base + s ds + t dt
    base = np.zeros((len(works), 3))
    ds = np.zeros((len(works), 3))
    dt = np.zeros((len(works), 3))
    for k, w in enumerate(works):
        a, g = w.key[0], w.key[1:]
        b, c = _others(a)
        base[k] = [breaks[x][g[x]] for x in range(3)]
        ds[k, b] = breaks[b][g[b] + 1] - breaks[b][g[b]]
        dt[k, c] = breaks[c][g[c] + 1] - breaks[c][g[c]]

    axes = np.array([_others(w.key[0]) for w in works])

    def params(p, f):
        return base[f] + p[:, :1] * ds[f] + p[:, 1:] * dt[f]

    rng = np.random.default_rng(20250101)
    err = np.full(len(tris), np.nan)
    # per triangle, computed once when it is made: its edges' keys, which of them are interior, and its longest one
    keys = np.zeros((len(tris), 3), dtype=np.int64)
    interior = np.zeros((len(tris), 3), dtype=bool)
    longest = np.zeros(len(tris), dtype=np.int64)
    for _round in range(4 * _ROUNDS):
        todo = np.isnan(xyz[:, 0])
        if np.any(todo):
            xyz[todo] = fmap.evaluate(params(st[todo], fid[todo]))
        new = np.flatnonzero(np.isnan(err))
        if len(new):
            tn = tris[new]
            e = np.stack([tn[:, [0, 1]], tn[:, [1, 2]], tn[:, [2, 0]]], 1)  # (m, 3, 2)
            k = np.minimum(e[..., 0], e[..., 1]) * big + np.maximum(e[..., 0], e[..., 1])
            keys[new] = k
            interior[new] = bkeys[np.clip(np.searchsorted(bkeys, k), 0, len(bkeys) - 1)] != k
            length = np.linalg.norm(xyz[e[..., 0]] - xyz[e[..., 1]], axis=2)
            # ties by parameter length, then by position in the triangle: deterministic
            plen = np.linalg.norm(st[e[..., 0]] - st[e[..., 1]], axis=2)
            longest[new] = np.argmax(np.where(interior[new], length + 1e-9 * plen, -1.0), axis=1)
            m = len(new)
            lam = rng.dirichlet((1.0, 1.0, 1.0), size=2 * m).reshape(m, 2, 3)
            w3 = np.concatenate([np.full((m, 1, 3), 1 / 3), lam,
                                 np.broadcast_to(np.array([[0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]]), (m, 3, 3))],
                                axis=1)  # (m, 6, 3): centroid, 2 random, 3 edge midpoints
            pts = np.einsum("mkj,mjd->mkd", w3, st[tn]).reshape(-1, 2)
            lin = np.einsum("mkj,mjd->mkd", w3, xyz[tn])
            f_new = fid[tn[:, 0]]
            got = fmap.evaluate(params(pts, np.repeat(f_new, 6))).reshape(m, 6, 3)
            d = _deviation(got - lin, xyz[tn])
            d[:, 3:] *= interior[new]  # boundary segments were fitted with the edges, and stay
            err[new] = d.max(axis=1)
            # a triangle turned over against the surface folds the mesh (the across-only measure cannot see that);
            # splitting mends it inside the face (next to a fixed boundary segment it would only make slivers)
            _, jac = fmap.evaluate_with_jacobian(params(pts.reshape(m, 6, 2)[:, 0], f_new))
            ax = axes[f_new]
            n_s = np.cross(jac[np.arange(m), :, ax[:, 0]], jac[np.arange(m), :, ax[:, 1]])
            c = xyz[tn]
            n_t = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
            norms = np.linalg.norm(n_s, axis=1) * np.linalg.norm(n_t, axis=1)
            scale = np.max(np.linalg.norm(c - c[:, :1], axis=2), axis=1)
            real = (np.linalg.norm(n_t, axis=1) > 1e-9 * scale ** 2) & (norms > 0)
            cos = np.einsum("md,md->m", n_s, n_t) / np.where(norms > 0, norms, 1.0)
            turned = real & (cos < 0.0) & np.all(interior[new], axis=1)
            err[new[turned]] = np.maximum(err[new[turned]], 2 * target + 1.0)
        bad = err > target
        if not np.any(bad):
            break
        if len(st) > _MAX_FACE_POINTS * len(works):
            raise GeometryError(
                f"output.tolerance: {tolerance:g} mm needs more than {_MAX_FACE_POINTS} points per cell face "
                f"(got tolerance {tolerance:g}, expected a coarser one, e.g. {tolerance * 4:g})")
        rows = np.arange(len(tris))
        split = np.unique(keys[rows[bad], longest[bad]])
        while True:
            has = _member(keys, split)
            need = np.any(has, axis=1) & ~has[rows, longest]
            if not np.any(need):
                break
            split = np.union1d(split, keys[rows[need], longest[need]])
        # new midpoints
        lo, hi = split // big, split % big
        mid = len(st) + np.arange(len(split))
        st = np.concatenate([st, 0.5 * (st[lo] + st[hi])])
        xyz = np.concatenate([xyz, np.full((len(split), 3), np.nan)])
        fid = np.concatenate([fid, fid[lo]])
        touched = np.any(has, axis=1)
        t = tris[touched]
        r = longest[touched]
        k = keys[touched]
        h = has[touched]
        n = len(t)
        idx = np.arange(n)
        v0, v1, v2 = t[idx, r], t[idx, (r + 1) % 3], t[idx, (r + 2) % 3]
        ml = mid[np.searchsorted(split, k[idx, r])]
        h1, h2 = h[idx, (r + 1) % 3], h[idx, (r + 2) % 3]
        m1 = np.where(h1, mid[np.clip(np.searchsorted(split, k[idx, (r + 1) % 3]), 0, len(split) - 1)], -1)
        m2 = np.where(h2, mid[np.clip(np.searchsorted(split, k[idx, (r + 2) % 3]), 0, len(split) - 1)], -1)
        out = [np.stack([v0, ml, v2], 1)[~h2], np.stack([v0, ml, m2], 1)[h2], np.stack([ml, v2, m2], 1)[h2],
               np.stack([ml, v1, v2], 1)[~h1], np.stack([ml, v1, m1], 1)[h1], np.stack([ml, m1, v2], 1)[h1]]
        tris = np.concatenate([tris[~touched]] + out)
        made = sum(len(o) for o in out)
        err = np.concatenate([err[~touched], np.full(made, np.nan)])
        keys = np.concatenate([keys[~touched], np.zeros((made, 3), dtype=np.int64)])
        interior = np.concatenate([interior[~touched], np.zeros((made, 3), dtype=bool)])
        longest = np.concatenate([longest[~touched], np.zeros(made, dtype=np.int64)])
    else:
        raise GeometryError(f"output.tolerance: the cell faces did not reach {tolerance:g} mm in {4 * _ROUNDS} rounds")
    # back to the faces, in a fixed order
    tf = fid[tris[:, 0]]
    order = np.argsort(tf, kind="stable")
    tris, tf = tris[order], tf[order]
    tsplit = np.searchsorted(tf, np.arange(len(works) + 1))
    pf_order = np.argsort(fid, kind="stable")
    local = np.empty(len(st), dtype=np.int64)
    psplit = np.searchsorted(fid[pf_order], np.arange(len(works) + 1))
    for k, w in enumerate(works):
        pts = pf_order[psplit[k]:psplit[k + 1]]  # the face's points: its first ones, then its midpoints in order
        local[pts] = np.arange(len(pts))
        w.st, w.xyz = st[pts], xyz[pts]
        w.tris = local[tris[tsplit[k]:tsplit[k + 1]]]
    return float(np.max(err, initial=0.0))


# ------------------------------------------------------------------------------------------------------------
# cell surfaces


def _cell_ids(cell, sampling, lat=None):
    """Triangles of the cell's boundary as global vertex ids (t, 3), oriented outward in parameter space."""
    lat = lat or sampling.lattice
    out = []
    for key, reverse, _, _ in lat.cell_faces(tuple(cell.index)):
        fm = sampling.faces[key]
        t = fm.ids[fm.tris]
        out.append(t[:, [0, 2, 1]] if reverse else t)
    return np.concatenate(out)


def cell_parameter_mesh(cell, sampling):
    """The cell box's boundary in its own parameters, as the faces' tessellation places it: uvw (n, 3), ids (n,)
    (global vertex ids: xyz = sampling.xyz[ids]), faces (m, 3) rows of uvw, outward in parameter space, and
    face_of (n,) int: bit 2a + side set for a point on the min (side 0) or max (side 1) face along a."""
    lat = sampling.lattice
    box = np.array([[sampling.breaks[k][cell.index[k] + s] for k in range(3)] for s in (0, 1)])
    uvw, ids, tris, bits = [], [], [], []
    n = 0
    for key, reverse, seam, (a, _) in lat.cell_faces(tuple(cell.index)):
        fm = sampling.faces[key]
        b, c = _others(a)
        st = _seen_through(np.asarray(fm.st), seam)
        q = np.empty((len(st), 3))
        q[:, a] = box[0 if reverse else 1, a]
        q[:, b] = box[0, b] + st[:, 0] * (box[1, b] - box[0, b])
        q[:, c] = box[0, c] + st[:, 1] * (box[1, c] - box[0, c])
        # exact box values on the rectangle's sides, so that the faces meeting at a box edge share their points
        for k, col in ((b, 0), (c, 1)):
            q[st[:, col] == 0.0, k] = box[0, k]
            q[st[:, col] == 1.0, k] = box[1, k]
        uvw.append(q)
        ids.append(fm.ids)
        t = fm.tris[:, [0, 2, 1]] if reverse else fm.tris
        tris.append(t + n)
        n += len(st)
    uvw, ids, tris = np.concatenate(uvw), np.concatenate(ids), np.concatenate(tris)
    # one point per id, unless the id sits at two places of this box (a cell closing on itself across a seam)
    span = box[1] - box[0]
    _, first_of = np.unique(ids, return_index=True)
    ref = uvw[first_of[np.searchsorted(ids[first_of], ids)]]
    far = np.max(np.abs(uvw - ref) / span, axis=1) > 1e-6
    place = np.zeros((len(uvw), 3), dtype=np.int64)
    place[far] = np.round((uvw[far] - box[0]) / span * 2 ** 20).astype(np.int64)
    _, first, inv = np.unique(np.column_stack([ids, place]), axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    uvw, ids, tris = uvw[first], ids[first], inv[tris]
    tol = 1e-9 * span
    bits = np.zeros(len(uvw), dtype=np.int64)
    for a in range(3):
        bits[np.abs(uvw[:, a] - box[0, a]) <= tol[a]] |= 1 << (2 * a)
        bits[np.abs(uvw[:, a] - box[1, a]) <= tol[a]] |= 1 << (2 * a + 1)
    return uvw, ids, tris, bits


def _is_cut_face(own, sampling):
    """A cell face (a, g) is a cut face, shared with a neighbour, when it is inside the grid or on a periodic seam."""
    a, g = own
    n = len(sampling.breaks[a]) - 1
    return 0 < g[a] < n or any(s[0] == a for s in sampling.seams)


def _setback(xyz, faces, slot, cut, half):
    """Displacements (n, 3) that set every cut face back by `half` mm along its normal while the cell's outer faces
    stay where they are. xyz (n, 3), faces (m, 3) outward, slot (m,) the cell face (0..5) of each triangle, cut (6,)
    bool. Per point (points closer than _WELD_MM count as one: collapsed faces repeat a point under several ids), the
    displacement d is the smallest with d . n_f = -half on each cut face f it lies on and d . n_f = 0 on each outer
    face: a corner of two cut faces moves along both normals, a point where a cut face meets the outside slides
    along the outside. Points inside one face near its edge then follow the edge's slide along the face, fading out
    over _FADE half-clearances, so that none is overtaken by the moving edge (a fold)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    nv = len(xyz)
    cluster = np.arange(nv)
    pairs = cKDTree(xyz).query_pairs(_WELD_MM, output_type="ndarray")
    if len(pairs):
        graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(nv, nv))
        _, cluster = connected_components(graph, directed=False)
    nc = int(cluster.max()) + 1
    t = xyz[faces]
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    normals = np.zeros((nc, 6, 3))
    for k in range(3):
        np.add.at(normals, (cluster[faces[:, k]], slot), cross)
    size = np.linalg.norm(normals, axis=2)
    on = size > 1e-12
    unit = np.where(on[..., None], normals / np.maximum(size, 1e-300)[..., None], 0.0)
    target = np.where(on & np.asarray(cut)[None, :], -float(half), 0.0)
    moving = np.flatnonzero(np.any(target != 0.0, axis=1))
    disp = np.zeros((nc, 3))
    if not len(moving):
        return disp[cluster]
    # minimum-norm least squares, batched; nearly parallel constraints are dropped rather than amplified
    pinv = np.linalg.pinv(unit[moving], rcond=0.05)
    d = np.einsum("nij,nj->ni", pinv, target[moving])
    length = np.linalg.norm(d, axis=1, keepdims=True)
    disp[moving] = d * np.minimum(1.0, 4.0 * half / np.maximum(length, 1e-300))
    # where: clusters on one face only; edges: triangle edges along a line where two faces meet
    pos = np.zeros((nc, 3))
    pos[cluster] = xyz
    count = on.sum(axis=1)
    e = cluster[np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])]
    e = np.unique(np.sort(e, axis=1), axis=0)
    common = on[e[:, 0]] & on[e[:, 1]]
    e, common = e[common.sum(axis=1) >= 2], common[common.sum(axis=1) >= 2]
    single = np.flatnonzero(count == 1)
    if not len(e) or not len(single):
        return disp[cluster]
    reach = _FADE * half
    p0, p1 = pos[e[:, 0]], pos[e[:, 1]]
    seg = p1 - p0
    seg_len2 = np.maximum(np.einsum("ij,ij->i", seg, seg), 1e-300)
    mid = 0.5 * (p0 + p1)
    radius = 0.5 * float(np.sqrt(seg_len2.max())) + reach
    near = cKDTree(mid).query_ball_point(pos[single], radius)
    rows = np.repeat(single, [len(n) for n in near])
    cols = np.fromiter((j for n in near for j in n), dtype=np.int64, count=len(rows))
    face_of = np.argmax(on[rows], axis=1)
    ok = common[cols, face_of]  # the edge bounds the point's own face
    rows, cols, face_of = rows[ok], cols[ok], face_of[ok]
    if not len(rows):
        return disp[cluster]
    lam = np.clip(np.einsum("ij,ij->i", pos[rows] - p0[cols], seg[cols]) / seg_len2[cols], 0.0, 1.0)
    dist = np.linalg.norm(p0[cols] + lam[:, None] * seg[cols] - pos[rows], axis=1)
    # the nearest edge of each point
    order = np.lexsort((dist, rows))
    rows, cols, face_of, lam, dist = rows[order], cols[order], face_of[order], lam[order], dist[order]
    first = np.r_[True, rows[1:] != rows[:-1]]
    rows, cols, face_of, lam, dist = rows[first], cols[first], face_of[first], lam[first], dist[first]
    weight = np.clip(1.0 - dist / reach, 0.0, 1.0)
    slide = (1.0 - lam)[:, None] * disp[e[cols, 0]] + lam[:, None] * disp[e[cols, 1]]
    n = unit[rows, face_of]
    slide -= np.einsum("ij,ij->i", slide, n)[:, None] * n  # only along the point's own face
    disp[rows] += weight[:, None] * slide
    return disp[cluster]


def cell_surface(cell, sampling, fmap, face_clearance=0.0):
    """Closed, outward triangulated boundary of the cell in mm: (vertices (n, 3), faces (m, 3) int). With
    face_clearance > 0 the cut faces are set back by half of it (the neighbour sets its side back by the other
    half), the outer faces stay exact."""
    lat = sampling.lattice
    keys, slots, cut = [], [], np.zeros(6, bool)
    for k, (key, reverse, _, own) in enumerate(lat.cell_faces(tuple(cell.index))):
        fm = sampling.faces[key]
        t = fm.ids[fm.tris]
        keys.append(t[:, [0, 2, 1]] if reverse else t)
        slots.append(np.full(len(t), k))
        cut[k] = _is_cut_face(own, sampling)
    keys = np.concatenate(keys)
    uniq, faces = np.unique(keys.ravel(), return_inverse=True)
    faces = faces.reshape(-1, 3)
    if fmap.orientation < 0:
        faces = faces[:, [0, 2, 1]]
    xyz = sampling.xyz[uniq]
    if face_clearance > 0 and cut.any():
        xyz = xyz + _setback(xyz, faces, np.concatenate(slots), cut, 0.5 * face_clearance)
    return geometry.weld(xyz, faces, _WELD_MM)


def face_clearance_volume(sampling, face_clearance):
    """mm^3 that a face clearance takes out of the puzzle: the clearance times the area of every cut face, each
    shared face counted once (corners and edges add terms of order clearance^2 only)."""
    if face_clearance <= 0:
        return 0.0
    area = 0.0
    for key, fm in sampling.faces.items():
        a, g = key[0], key[1:]
        if not _is_cut_face((a, g), sampling):
            continue
        t = sampling.xyz[fm.ids[fm.tris]]
        area += float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())
    return face_clearance * area


# ------------------------------------------------------------------------------------------------------------
# pieces

@dataclass(frozen=True, eq=False)
class Piece:
    """id 'pi-j-k'; cell index; mesh in mm (closed, outward normals); volume and body_volume (before joints) in mm^3."""

    id: str
    cell: tuple
    mesh: trimesh.Trimesh
    volume: float
    body_volume: float
    triangles: int


def _joint_solids(joints, index):
    """(pins, holes, domain_pins, domain_holes) of this cell, from volpuzzle.joint."""
    pins, holes, dpins, dholes = [], [], [], []
    if not joints:
        return pins, holes, dpins, dholes
    from .. import joint as joint_mod  # a later stage's helpers; imported only when there are joints

    for j in joints:
        style = getattr(j, "style", "pin")
        if style == "none":
            continue
        domain = getattr(j, "space", "physical") == "domain"
        pin_cell, hole_cell = tuple(j.pin_cell), tuple(j.hole_cell)
        if style == "pin" and pin_cell == index:
            if domain:
                dpins.append(joint_mod.pin_solid_domain(j))
            else:
                pins.append(joint_mod.pin_solid(j))
        if hole_cell == index or (style == "dowel" and pin_cell == index):
            if domain:
                dholes.append(joint_mod.hole_solid_domain(j, index))
            else:
                holes.append(joint_mod.hole_solid(j, index))
    return pins, holes, dpins, dholes


def _apply(body, pins, holes, what):
    for k, p in enumerate(pins):
        body = geometry.boolean(body, p, "union", f"{what} (pin {k + 1})")
    for k, h in enumerate(holes):
        body = geometry.boolean(body, h, "difference", f"{what} (hole {k + 1})")
    return body


def _wrap(uvw, sampling):
    """Parameters beyond a periodic face (a pin that crosses the seam) -> the same points on the other side."""
    uvw = np.array(uvw, dtype=float, copy=True)
    lo, hi = sampling.domain
    for a, swap, flip in sampling.seams:
        b, c = _others(a)
        span = hi[a] - lo[a]
        for sign in (1, -1):
            out = uvw[:, a] > hi[a] if sign > 0 else uvw[:, a] < lo[a]
            if not np.any(out):
                continue
            st = (uvw[out][:, [b, c]] - lo[[b, c]]) / (hi[[b, c]] - lo[[b, c]])
            if sign > 0:  # max side -> min side: swap, then flip
                st = st[:, ::-1] if swap else st
                st = np.where(np.array(flip), 1.0 - st, st)
            else:  # min side -> max side: unflip, then unswap
                st = np.where(np.array(flip), 1.0 - st, st)
                st = st[:, ::-1] if swap else st
            moved = uvw[out]
            moved[:, [b, c]] = lo[[b, c]] + st * (hi[[b, c]] - lo[[b, c]])
            moved[:, a] -= sign * span
            uvw[out] = moved
    return uvw


def _on_face_positions(q, todo, face_bit, uvw, ids, tris, bits, xyz_all):
    """Points q[todo] on one box face -> their positions on the face's tessellation (piecewise linear in its
    parameters), so that a face cut by a domain pin or hole still lies exactly on the cut surface the neighbour sees."""
    a = face_bit // 2
    b, c = _others(a)
    on = (bits & (1 << face_bit)) != 0
    ft = tris[np.all(on[tris], axis=1)]
    p = q[todo][:, [b, c]]
    t0, t1, t2 = (uvw[ft[:, k]][:, [b, c]] for k in range(3))
    d1, d2 = t1 - t0, t2 - t0
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    out = np.empty((len(p), 3))
    for i0 in range(0, len(p), 256):
        pp = p[i0:i0 + 256, None, :] - t0[None]
        l1 = (pp[..., 0] * d2[:, 1] - pp[..., 1] * d2[:, 0]) / det
        l2 = (d1[:, 0] * pp[..., 1] - d1[:, 1] * pp[..., 0]) / det
        l0 = 1.0 - l1 - l2
        worst = np.minimum(np.minimum(l0, l1), l2)  # >= 0 inside; the largest is the containing triangle
        k = np.argmax(worst, axis=1)
        r = np.arange(len(k))
        lam = np.clip(np.stack([l0[r, k], l1[r, k], l2[r, k]], 1), 0.0, 1.0)
        lam /= lam.sum(axis=1, keepdims=True)
        out[i0:i0 + 256] = np.einsum("nk,nkd->nd", lam, xyz_all[ids[ft[k]]])
    return out


def _domain_body(cell, sampling, fmap, dpins, dholes, what):
    """Booleans in parameter space on the cell's own tessellated box, then the vertices mapped through F with the
    new triangles off the box faces split until their edges meet the tolerance. -> (vertices, faces) in mm, outward."""
    uvw, ids, tris, bits = cell_parameter_mesh(cell, sampling)
    body = geometry.manifold_from_mesh(uvw, tris, f"{what} (parameter box)")
    body = _apply(body, dpins, dholes, f"{what} (in the domain)")
    out = geometry.to_trimesh(body)
    q = np.asarray(out.vertices, dtype=float)
    f = np.asarray(out.faces, dtype=np.int64)
    box = np.array([[sampling.breaks[k][cell.index[k] + s] for k in range(3)] for s in (0, 1)])
    tol = 1e-10 * (box[1] - box[0])
    mask = np.zeros(len(q), dtype=np.int64)
    for a in range(3):
        mask[np.abs(q[:, a] - box[0, a]) <= tol[a]] |= 1 << (2 * a)
        mask[np.abs(q[:, a] - box[1, a]) <= tol[a]] |= 1 << (2 * a + 1)
    xyz = np.full(q.shape, np.nan)
    # the box's own points keep their exact parameters through the engine, and take the shared positions
    where = {p.tobytes(): i for p, i in zip(uvw, ids, strict=True)}
    for r in np.flatnonzero(mask):
        i = where.get(q[r].tobytes())
        if i is not None:
            xyz[r] = sampling.xyz[i]
    for bit in range(6):
        todo = ((mask & (1 << bit)) != 0) & np.isnan(xyz[:, 0])
        if np.any(todo):
            xyz[todo] = _on_face_positions(q, todo, bit, uvw, ids, tris, bits, sampling.xyz)
    off = np.isnan(xyz[:, 0])
    if np.any(off):
        xyz[off] = fmap.evaluate(_wrap(q[off], sampling))
    q, xyz, f = _refine(q, xyz, f, mask, lambda x: fmap.evaluate(_wrap(x, sampling)),
                        _SAFETY * sampling.tolerance)
    if fmap.orientation < 0:
        f = f[:, [0, 2, 1]]
    return geometry.weld(xyz, f, _WELD_MM)


def _refine(q, xyz, f, mask, evaluate, target):
    """Split edges whose mapped midpoint is farther than target from the chord, at most one per triangle per pass.
    Edges with both ends on one box face (mask bits in common) lie in the flat, already fitted face and stay."""
    q, xyz, f, mask = np.array(q, dtype=float), np.array(xyz, dtype=float), f.copy(), np.array(mask)
    for _ in range(30):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        e = np.unique(e, axis=0)
        cand = e[(mask[e[:, 0]] & mask[e[:, 1]]) == 0]
        if len(cand) == 0:
            break
        mid = 0.5 * (q[cand[:, 0]] + q[cand[:, 1]])
        xm = evaluate(mid)
        err = np.linalg.norm(xm - 0.5 * (xyz[cand[:, 0]] + xyz[cand[:, 1]]), axis=1)
        bad = np.flatnonzero(err > target)
        if len(bad) == 0:
            break
        tri_of_edge = {}
        for t, tri in enumerate(f):
            for k in range(3):
                u, v = tri[k], tri[(k + 1) % 3]
                tri_of_edge.setdefault((min(u, v), max(u, v)), []).append((t, k))
        used = np.zeros(len(f), dtype=bool)
        new_q, new_x, new_f = [], [], []
        n0 = len(q)
        for i in bad[np.argsort(-err[bad])]:
            u, v = cand[i]
            adj = tri_of_edge.get((u, v), [])
            if any(used[t] for t, _ in adj):
                continue
            m = n0 + len(new_q)
            new_q.append(mid[i])
            new_x.append(xm[i])
            for t, k in adj:
                used[t] = True
                a, b, c = f[t, k], f[t, (k + 1) % 3], f[t, (k + 2) % 3]
                new_f.append((a, m, c))
                new_f.append((m, b, c))
        q = np.concatenate([q, np.array(new_q)])
        xyz = np.concatenate([xyz, np.array(new_x)])
        mask = np.concatenate([mask, np.zeros(len(new_q), dtype=mask.dtype)])
        f = np.concatenate([f[~used], np.array(new_f, dtype=np.int64).reshape(-1, 3)])
    return q, xyz, f


def build_piece(cell, sampling, fmap, joints, what=None, face_clearance=0.0):
    """One cell -> Piece: its body through F, cut faces set back by face_clearance / 2, pins united and holes
    subtracted (in mm, or in the domain for joints with space 'domain'); checked to be one closed solid with outward
    normals. (grid: unused, kept for callers of the earlier signature.)"""
    what = what or cell.id
    index = tuple(cell.index)
    verts, faces = cell_surface(cell, sampling, fmap, face_clearance=face_clearance)
    body = geometry.manifold_from_mesh(verts, faces, what)
    body_volume = float(body.volume())
    pins, holes, dpins, dholes = _joint_solids(joints, index)
    if dpins or dholes:
        v2, f2 = _domain_body(cell, sampling, fmap, dpins, dholes, what)
        body = geometry.manifold_from_mesh(v2, f2, f"{what} (mapped from the domain)")
    body = _apply(body, pins, holes, what)
    parts = body.decompose()
    if len(parts) != 1:
        raise GeometryError(f"{what}: the piece falls apart into {len(parts)} bodies after its joints "
                            f"(expected one; a hole may cut through a thin piece: use a smaller joints.radius "
                            f"or joints.length)")
    mesh = geometry.check_solid(geometry.to_trimesh(body), what)
    return Piece(what, index, mesh, float(body.volume()), body_volume, int(len(mesh.faces)))


# ------------------------------------------------------------------------------------------------------------
# all pieces

_WORKER = {}


def _init_worker(tiling, sampling, fmap, joints, face_clearance=0.0):
    _WORKER.update(tiling=tiling, sampling=sampling, fmap=fmap, joints=joints, face_clearance=face_clearance)


def _warm_worker():
    """Load what every piece needs (the compiled kernels, from numba's cache) before the worker is given pieces,
    so that its first piece does not hold up the end of compose. -> the worker's pid"""
    cell = next(iter(_WORKER["tiling"].cells.values()))
    _WORKER["fmap"].evaluate(np.repeat(np.asarray(cell.center, float)[None], 512, axis=0))
    return os.getpid()


def _build_in_worker(index):
    w = _WORKER
    t0 = time.perf_counter()
    p = build_piece(w["tiling"].cell(index), w["sampling"], w["fmap"], w["joints"],
                    face_clearance=w.get("face_clearance", 0.0))
    # plain arrays travel between processes more cheaply and predictably than trimesh objects
    return (p.id, p.cell, np.asarray(p.mesh.vertices), np.asarray(p.mesh.faces), p.volume, p.body_volume,
            time.perf_counter() - t0)


def _piece_from(rec):
    pid, cell, v, f, vol, bvol, _ = rec
    mesh = trimesh.Trimesh(vertices=v, faces=f, process=False)
    return Piece(pid, tuple(cell), mesh, vol, bvol, int(len(f)))


class Pieces(list):
    """The pieces in cell-index order, with the Sampling they were built on (.sampling.max_error_mm for the report)
    and the build time of each piece in seconds (.seconds, by piece id)."""

    sampling = None
    seconds = None


def _use_pool(jobs, n, sampling, joints):
    """A pool only pays when there is enough work: many pieces, and many triangles or booleans to share out."""
    if jobs is None or jobs <= 1 or n <= 1 or n < _POOL_MIN_PIECES:
        return False
    seconds = 2 * sampling.counts[1] * _SECONDS_PER_TRIANGLE + len(joints) * _SECONDS_PER_JOINT
    return seconds >= _POOL_MIN_SECONDS


def _pooled(order, jobs, tiling, sampling, fmap, joints, progress, face_clearance=0.0):
    """Pieces built by this process and jobs - 1 spawned workers together -> {cell index: record}. This process
    takes pieces from the front while the workers start (~2.5 s of imports that it would otherwise wait for) and
    then take pieces from the back, two queued each; a piece still queued when the front reaches it is built
    here. Every piece is built by the same function, so where it is built does not change it."""
    recs, n = {}, len(order)
    pending = list(order)
    running = {}

    def finished(fut, index):
        try:
            recs[index] = fut.result()
        except concurrent.futures.process.BrokenProcessPool as e:
            raise GeometryError(f"compose: a worker process died while building {tiling.cell(index).id} ({e}); "
                                f"try --jobs 1") from e
        if progress:
            progress(len(recs), n, recs[index][0])

    ctx = multiprocessing.get_context("spawn")
    _init_worker(tiling, sampling, fmap, joints, face_clearance)
    pool = concurrent.futures.ProcessPoolExecutor(max_workers=jobs - 1, mp_context=ctx, initializer=_init_worker,
                                                  initargs=(tiling, sampling, fmap, joints, face_clearance))
    # Pieces go to the workers only once one has started: queued behind a worker's start-up they could keep this
    # process waiting at the end for as long as the start-up takes (10 s on a busy machine).
    started = pool.submit(_warm_worker)
    try:
        while pending or running:
            for fut in [f for f in running if f.done()]:
                finished(fut, running.pop(fut))
            # the last pending piece is this process's own, so it never idles while workers start
            # (a pool that could not start leaves every piece to this process)
            while (started.done() and started.exception() is None and pending[_MAIN_TAKES_PIECES:]
                   and len(running) < 2 * (jobs - 1)):
                index = pending.pop()
                running[pool.submit(_build_in_worker, index)] = index
            if _MAIN_TAKES_PIECES:
                if pending:
                    index = pending.pop(0)
                    recs[index] = _build_in_worker(index)
                    if progress:
                        progress(len(recs), n, recs[index][0])
                    continue
                # nothing left here: take back what no worker has started
                pending += [running.pop(f) for f in [f for f in running if f.cancel()]]
                if pending:
                    continue
            if not (pending or running):
                break
            if not running and started.done():  # pieces left that only workers take, and no worker started
                raise GeometryError(f"compose: the worker processes did not start ({started.exception()}); "
                                    f"try --jobs 1")
            concurrent.futures.wait(list(running) or [started], return_when=concurrent.futures.FIRST_COMPLETED)
    finally:
        _WORKER.clear()
        # without waiting for workers still starting: they exit when they find the pool shut
        pool.shutdown(wait=False, cancel_futures=True)
    return recs


def compose(tiling, fmap, joints, tolerance, jobs=1, progress=None, sampling=None, face_clearance=0.0):
    """Every cell -> Piece, in cell-index order (a list, with .sampling and .seconds). jobs > 1 builds in a process
    pool when the work is large enough to pay for one (same results as jobs=1); progress(i, n, piece_id) is called
    as pieces finish. Pass `sampling` to reuse one from sample_parameters. face_clearance (mm): the gap left
    between mating cut faces, half on each side."""
    sampling = sampling if sampling is not None else sample_parameters(tiling, fmap, tolerance)
    order = sorted(tiling.cells)
    n = len(order)
    joints = list(joints or [])
    recs = {}
    if not _use_pool(jobs, n, sampling, joints):
        _init_worker(tiling, sampling, fmap, joints, face_clearance)
        try:
            for k, index in enumerate(order):
                recs[index] = _build_in_worker(index)
                if progress:
                    progress(k + 1, n, recs[index][0])
        finally:
            _WORKER.clear()
    else:
        recs = _pooled(order, int(jobs), tiling, sampling, fmap, joints, progress, face_clearance)
    out = Pieces(_piece_from(recs[index]) for index in order)
    out.sampling = sampling
    out.seconds = {recs[index][0]: recs[index][6] for index in order}
    return out
