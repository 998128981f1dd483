"""One grid face's triangulation in its parameter rectangle [0, 1]^2, between the samples of its four edges: a
Delaunay triangulation of the boundary and a coarse seed, then longest-edge bisection of every triangle that misses F
(all faces in one batch per round); a face that F squeezes onto a line is laddered between its rails instead."""

from typing import NamedTuple

import numpy as np
from scipy.spatial import Delaunay

from ..errors import GeometryError
from ..grid import AXES, other_axes

_MAX_FACE_POINTS = 100000  # per grid face, on average
ROUNDS = 60
_BULGE = (1e-3, 1e-5, 1e-7)  # how far face boundaries are bowed out so that Delaunay keeps them (fraction of size)


def merge_sorted(values, new, eps):
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


class _Chain(NamedTuple):
    """One side of a face: st (k, 2) its samples in the face's rectangle, in increasing s or t; ids (k,) global."""

    st: np.ndarray
    ids: np.ndarray


def _edge_ref(lat, axis, start, ts, ids):
    """The samples of the edge along axis from grid vertex start, in increasing local order: (t (k,), ids (k,))."""
    key, reverse = lat.edge(axis, start)
    t, i = ts[key], ids[key]
    return (1.0 - t[::-1], i[::-1]) if reverse else (t, i)


def face_edges(key):
    """The four edges of a face in its own frame: bottom (t=0), right (s=1), top (t=1), left (s=0), as
    (axis, start) pairs; each runs in increasing s or t."""
    g = list(key.corner)
    b, c = other_axes(key.axis)
    gb, gc = list(g), list(g)
    gb[b] += 1
    gc[c] += 1
    return (b, g), (c, gb), (b, gc), (c, g)


def face_chains(lat, key, ts, ids):
    """-> the four _Chains of face `key`: bottom, right, top, left."""
    out = []
    for k, (axis, start) in enumerate(face_edges(key)):
        t, i = _edge_ref(lat, axis, start, ts, ids)
        st = np.empty((len(t), 2))
        if k in (0, 2):
            st[:, 0], st[:, 1] = t, 0.0 if k == 0 else 1.0
        else:
            st[:, 0], st[:, 1] = 1.0 if k == 1 else 0.0, t
        out.append(_Chain(st, i))
    return out


def boundary_polygon(chains):
    """The four chains -> the face boundary counter-clockwise in (s, t): st (k, 2), ids (k,), each corner once."""
    (sb, ib), (sr, ir), (su, iu), (sl, il) = chains
    st = np.concatenate([sb[:-1], sr[:-1], su[::-1][:-1], sl[::-1][:-1]])
    ids = np.concatenate([ib[:-1], ir[:-1], iu[::-1][:-1], il[::-1][:-1]])
    return st, ids


def chain_positions(chains):
    """Positions in boundary_polygon's order of the four chains' points (each in increasing s or t)."""
    lens = [len(c.ids) for c in chains]
    total = sum(lens) - 4
    o_r = lens[0] - 1
    o_u = o_r + lens[1] - 1
    o_l = o_u + lens[2] - 1
    bottom = np.arange(lens[0])
    right = o_r + np.arange(lens[1])
    top = o_u + (lens[2] - 1 - np.arange(lens[2]))
    left = (o_l + (lens[3] - 1 - np.arange(lens[3]))) % total
    return bottom, right, top, left


def ladder(rail_l, rail_r, cap_lo, cap_hi):
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


def ccw(p, tris):
    area = _signed_area(p, tris)
    tris = np.where((area < 0)[:, None], tris[:, [0, 2, 1]], tris)
    return tris, np.abs(area)


class FaceWork:
    """One canonical face under refinement: points st (k, 2) in its rectangle, their xyz, the first n_boundary on
    the boundary (counter-clockwise) with global ids boundary_ids; scale: the face's lengths in mm, which the
    triangulation is made in for well-shaped triangles; tris (m, 3) rows of st once triangulated."""

    def __init__(self, key, st_b, ids_b, xyz_b, scale, seed):
        self.key = key
        self.n_boundary = len(st_b)
        self.boundary_ids = ids_b
        self.st = np.concatenate([st_b, seed])
        self.xyz = np.concatenate([xyz_b, np.full((len(seed), 3), np.nan)])
        self.scale = np.asarray(scale, dtype=float)
        self.tris = None

    def triangulate(self):
        nb, n = self.n_boundary, len(self.st)
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
            tri, area = ccw(true, tri)
            if len(np.unique(tri)) != n or np.min(area) <= 1e-12 * total or abs(area.sum() - total) > 1e-9 * total:
                continue
            e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
            bnd = np.sort(np.stack([np.arange(nb), (np.arange(nb) + 1) % nb], 1), axis=1)
            # every boundary segment is an edge of the triangulation (edges as one integer each, lo * n + hi)
            if np.isin(bnd[:, 0] * n + bnd[:, 1], e[:, 0] * n + e[:, 1]).all():
                self.tris = tri
                return tri
        raise GeometryError(f"compose: could not triangulate the {AXES[self.key.axis]} face at grid {self.key.corner} "
                            f"with {n} points (internal error)")


def seed_points(scale, knots_s, knots_t):
    """A coarse interior grid (about 4 cells across the longer side) plus points on the interior knot lines."""
    h = max(scale) / 4.0
    ks, kt = (max(2, int(round(x / h))) for x in scale)
    s = np.arange(1, ks) / ks
    t = np.arange(1, kt) / kt
    s_all, _ = merge_sorted(np.concatenate([[0.0], s, [1.0]]), knots_s, 1e-9)
    t_all, _ = merge_sorted(np.concatenate([[0.0], t, [1.0]]), knots_t, 1e-9)
    pts = [np.stack(np.meshgrid(s, t_all, indexing="ij"), -1).reshape(-1, 2),
           np.stack(np.meshgrid(s_all, t, indexing="ij"), -1).reshape(-1, 2)]
    pts = np.unique(np.concatenate(pts), axis=0)
    # a knot line a hair inside the face (a file's rounded knots next to a split) would leave sliver triangles
    e = 1e-4
    return pts[(pts[:, 0] > e) & (pts[:, 0] < 1 - e) & (pts[:, 1] > e) & (pts[:, 1] < 1 - e)]


class _EdgeIndex:
    """The triangles' edge keys (m, 3) sorted once, to find where given keys occur without a pass over all of them:
    the longest-edge closure asks this a few times a round, each time of a few new keys."""

    def __init__(self, edge_keys):
        flat = edge_keys.ravel()
        self.order = np.argsort(flat, kind="stable")
        self.sorted = flat[self.order]

    def where(self, keys):
        """Flat positions (into edge_keys.ravel()) of every entry equal to one of the sorted unique keys."""
        lo = np.searchsorted(self.sorted, keys, side="left")
        count = np.searchsorted(self.sorted, keys, side="right") - lo
        start = np.repeat(lo - (np.cumsum(count) - count), count)
        return self.order[start + np.arange(int(count.sum()))]


def refine_faces(works, breaks, fmap, target, tolerance):
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
    face_of = np.repeat(np.arange(len(works)), sizes)
    tris = np.concatenate([w.tris + off[k] for k, w in enumerate(works)])
    key_base = np.int64(1) << 31
    boundary_keys = []
    for k, w in enumerate(works):
        i = np.arange(w.n_boundary)
        e = np.sort(np.stack([i, (i + 1) % w.n_boundary], 1), axis=1) + off[k]
        boundary_keys.append(e[:, 0] * key_base + e[:, 1])
    boundary_keys = np.sort(np.concatenate(boundary_keys))
    # per face: uvw = base + s ds + t dt
    base = np.zeros((len(works), 3))
    ds = np.zeros((len(works), 3))
    dt = np.zeros((len(works), 3))
    for k, w in enumerate(works):
        g = w.key.corner
        b, c = other_axes(w.key.axis)
        base[k] = [breaks[x][g[x]] for x in range(3)]
        ds[k, b] = breaks[b][g[b] + 1] - breaks[b][g[b]]
        dt[k, c] = breaks[c][g[c] + 1] - breaks[c][g[c]]

    axes = np.array([other_axes(w.key.axis) for w in works])

    def params(p, f):
        return base[f] + p[:, :1] * ds[f] + p[:, 1:] * dt[f]

    rng = np.random.default_rng(20250101)
    err = np.full(len(tris), np.nan)
    # per triangle, computed once when it is made: its edges' keys (lo * key_base + hi), which of them are interior,
    # and its longest one
    edge_keys = np.zeros((len(tris), 3), dtype=np.int64)
    interior = np.zeros((len(tris), 3), dtype=bool)
    longest = np.zeros(len(tris), dtype=np.int64)
    for _round in range(4 * ROUNDS):
        todo = np.isnan(xyz[:, 0])
        if np.any(todo):
            xyz[todo] = fmap.evaluate(params(st[todo], face_of[todo]))
        new = np.flatnonzero(np.isnan(err))
        if len(new):
            new_tris = tris[new]
            e = np.stack([new_tris[:, [0, 1]], new_tris[:, [1, 2]], new_tris[:, [2, 0]]], 1)  # (m, 3, 2)
            k = np.minimum(e[..., 0], e[..., 1]) * key_base + np.maximum(e[..., 0], e[..., 1])
            edge_keys[new] = k
            interior[new] = boundary_keys[np.clip(np.searchsorted(boundary_keys, k), 0, len(boundary_keys) - 1)] != k
            length = np.linalg.norm(xyz[e[..., 0]] - xyz[e[..., 1]], axis=2)
            # ties by parameter length, then by position in the triangle: deterministic
            plen = np.linalg.norm(st[e[..., 0]] - st[e[..., 1]], axis=2)
            longest[new] = np.argmax(np.where(interior[new], length + 1e-9 * plen, -1.0), axis=1)
            m = len(new)
            lam = rng.dirichlet((1.0, 1.0, 1.0), size=2 * m).reshape(m, 2, 3)
            weights = np.concatenate([np.full((m, 1, 3), 1 / 3), lam,
                                 np.broadcast_to(np.array([[0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]]), (m, 3, 3))],
                                axis=1)  # (m, 6, 3): centroid, 2 random, 3 edge midpoints
            pts = np.einsum("mkj,mjd->mkd", weights, st[new_tris])
            lin = np.einsum("mkj,mjd->mkd", weights, xyz[new_tris])
            new_face = face_of[new_tris[:, 0]]
            # an edge that two new triangles share has one midpoint (the halves of the same two corners, to the last
            # bit), so F is evaluated there once: 2 in 5 of the midpoints asked for on the twisted torus
            _, first, again = np.unique(k, return_index=True, return_inverse=True)
            inner = params(pts[:, :3].reshape(-1, 2), np.repeat(new_face, 3))  # centroid, 2 random, per triangle
            mids = params(pts[:, 3:].reshape(-1, 2)[first], np.repeat(new_face, 3)[first])
            val = fmap.evaluate(np.concatenate([inner, mids]))
            got = np.concatenate([val[:3 * m].reshape(m, 3, 3), val[3 * m:][again.reshape(m, 3)]], axis=1)
            d = _deviation(got - lin, xyz[new_tris])
            d[:, 3:] *= interior[new]  # boundary segments were fitted with the edges, and stay
            err[new] = d.max(axis=1)
            # a triangle turned over against the surface folds the mesh (the across-only measure cannot see that);
            # splitting mends it
            _, jac = fmap.evaluate_with_jacobian(inner.reshape(m, 3, 3)[:, 0])
            ax = axes[new_face]
            n_s = np.cross(jac[np.arange(m), :, ax[:, 0]], jac[np.arange(m), :, ax[:, 1]])
            c = xyz[new_tris]
            n_t = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
            norms = np.linalg.norm(n_s, axis=1) * np.linalg.norm(n_t, axis=1)
            scale = np.max(np.linalg.norm(c - c[:, :1], axis=2), axis=1)
            real = (np.linalg.norm(n_t, axis=1) > 1e-9 * scale ** 2) & (norms > 0)
            cos = np.einsum("md,md->m", n_s, n_t) / np.where(norms > 0, norms, 1.0)
            inner = interior[new]
            # next to a fixed boundary segment only while its other edges are much longer (a fan from a far point,
            # which turns over on a curved face): splitting then brings the point closer and ends, where splitting a
            # short one made slivers forever (quarter torus at 0.5 mm)
            far = np.max(np.where(inner, length, 0.0), axis=1) > 2.0 * np.max(np.where(inner, 0.0, length), axis=1)
            fan = np.any(inner, axis=1) & ~np.all(inner, axis=1) & far
            turned = real & (cos < 0.0) & (np.all(inner, axis=1) | fan)
            err[new[turned]] = np.maximum(err[new[turned]], 2 * target + 1.0)
        bad = err > target
        if not np.any(bad):
            break
        if len(st) > _MAX_FACE_POINTS * len(works):
            raise GeometryError(
                f"output.tolerance: {tolerance:g} mm needs more than {_MAX_FACE_POINTS} points per cell face "
                f"(got tolerance {tolerance:g}, expected a coarser one, e.g. {tolerance * 4:g})")
        rows = np.arange(len(tris))
        split = np.unique(edge_keys[rows[bad], longest[bad]])
        # the closure: a triangle with an edge to split has its longest split too, until none is missing. Only the
        # triangles that the keys added last touch can miss one, so each pass looks at those alone
        index = _EdgeIndex(edge_keys)
        has = np.zeros(edge_keys.shape, dtype=bool)  # has[t, e]: edge e of triangle t is split
        added = split
        while len(added):
            hit = index.where(added)
            has.ravel()[hit] = True
            touched = np.unique(hit // 3)
            need = touched[~has[touched, longest[touched]]]
            added = np.unique(edge_keys[need, longest[need]])  # none of them split yet: has is False there
            split = np.union1d(split, added)
        # new midpoints
        lo, hi = split // key_base, split % key_base
        mid = len(st) + np.arange(len(split))
        st = np.concatenate([st, 0.5 * (st[lo] + st[hi])])
        xyz = np.concatenate([xyz, np.full((len(split), 3), np.nan)])
        face_of = np.concatenate([face_of, face_of[lo]])
        touched = np.any(has, axis=1)
        t = tris[touched]
        r = longest[touched]
        k = edge_keys[touched]
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
        edge_keys = np.concatenate([edge_keys[~touched], np.zeros((made, 3), dtype=np.int64)])
        interior = np.concatenate([interior[~touched], np.zeros((made, 3), dtype=bool)])
        longest = np.concatenate([longest[~touched], np.zeros(made, dtype=np.int64)])
    else:
        raise GeometryError(f"output.tolerance: the cell faces did not reach {tolerance:g} mm in {4 * ROUNDS} rounds")
    # back to the faces, in a fixed order
    tri_face = face_of[tris[:, 0]]
    order = np.argsort(tri_face, kind="stable")
    tris, tri_face = tris[order], tri_face[order]
    tri_split = np.searchsorted(tri_face, np.arange(len(works) + 1))
    by_face = np.argsort(face_of, kind="stable")
    local = np.empty(len(st), dtype=np.int64)
    point_split = np.searchsorted(face_of[by_face], np.arange(len(works) + 1))
    for k, w in enumerate(works):
        # the face's points: its first ones, then its midpoints in order
        pts = by_face[point_split[k]:point_split[k + 1]]
        local[pts] = np.arange(len(pts))
        w.st, w.xyz = st[pts], xyz[pts]
        w.tris = local[tris[tri_split[k]:tri_split[k + 1]]]
    return float(np.max(err, initial=0.0))
