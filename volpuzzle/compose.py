"""compose: turn every cell of the tiling into a closed solid in mm, through the map F = M o R, with its joints.

The boundary of each cell box is tessellated on one set of sample parameters per axis, shared by all cells, and
mapped through F. Because the sets are global (and made invariant under every periodic seam), a face shared by
two cells gets the same vertices and the same triangles from both sides, so neighbours meet on one cut surface
without gaps or overlaps. Every grid vertex is evaluated in one fixed batch (the whole plane it lies on, on the
canonical side of a seam), so the coordinates agree to the last bit, not only to a tolerance.
"""

import concurrent.futures
import multiprocessing
import time
from dataclasses import dataclass

import numpy as np
import trimesh

from . import geometry
from .errors import GeometryError

AXES = "uvw"
# Measured points (edge midpoints, quad centres, triangle centroids) are held to this fraction of the tolerance:
# for a smooth surface the linear interpolant's error inside a triangle can exceed its value at those points.
_SAFETY = 0.8
_MAX_SAMPLES = 20000  # per axis; beyond this the tolerance is far below what a printer can show
_WELD_MM = 1e-6  # points closer than this are one point (collapsed axes map whole faces onto lines or points)


def _others(a):
    return tuple(k for k in range(3) if k != a)


# ------------------------------------------------------------------------------------------------------------
# sampling

@dataclass(frozen=True, eq=False)
class Sampling:
    """params: three sorted parameter arrays holding every break; break_index: three int arrays, where each
    break of the tiling sits in params; seams: the tiling's seams as (axis, swap, flip) tuples; domain (2, 3);
    max_error_mm: the largest deviation measured between F and its tessellation; tolerance: the goal in mm."""

    params: tuple
    break_index: tuple
    seams: tuple
    domain: np.ndarray
    max_error_mm: float
    tolerance: float

    @property
    def counts(self):
        return tuple(len(p) for p in self.params)


def _seam_tuples(tiling):
    out = []
    for a in sorted(tiling.seams):
        if a in tiling.periodic:
            s = tiling.seams[a]
            out.append((int(a), bool(s.swap), tuple(bool(x) for x in s.flip)))
    return tuple(out)


def _merge(values, new, eps):
    """Sorted union of values and new, skipping new values within eps of one already there (keeps breaks exact)."""
    values = np.asarray(values, dtype=float)
    new = np.asarray(new, dtype=float)
    if new.size == 0:
        return values, False
    pos = np.clip(np.searchsorted(values, new), 1, len(values) - 1)
    near = np.minimum(np.abs(values[pos] - new), np.abs(values[pos - 1] - new)) <= eps
    new = np.unique(new[~near])
    if new.size == 0:
        return values, False
    # the new values may still be near each other
    keep = np.concatenate([[True], np.diff(new) > eps])
    return np.union1d(values, new[keep]), True


def _symmetrise(params, seams, domain):
    """Add the images of the samples under every seam until the sets no longer change."""
    params = list(params)
    for _ in range(16):
        changed = False
        for a, swap, flip in seams:
            b, c = _others(a)
            lo, hi = domain[0], domain[1]
            nb = (params[b] - lo[b]) / (hi[b] - lo[b])
            nc = (params[c] - lo[c]) / (hi[c] - lo[c])
            s, t = (nc, nb) if swap else (nb, nc)
            s = 1.0 - s if flip[0] else s
            t = 1.0 - t if flip[1] else t
            for axis, img in ((b, s), (c, t)):
                span = hi[axis] - lo[axis]
                vals = np.clip(lo[axis] + img * span, lo[axis], hi[axis])
                params[axis], ch = _merge(params[axis], vals, 1e-11 * span)
                changed |= ch
        if not changed:
            return tuple(params)
    raise GeometryError("compose: the sample sets did not settle under the periodic seams")


class _Grid:
    """Positions of grid vertices for one sampling and one map: canonical indices and plane-batched evaluation."""

    def __init__(self, params, break_index, seams, domain, fmap):
        self.params = tuple(np.asarray(p, dtype=float) for p in params)
        self.n = tuple(len(p) for p in self.params)
        self.is_break = []
        for a in range(3):
            m = np.zeros(self.n[a], dtype=bool)
            m[break_index[a]] = True
            self.is_break.append(m)
        self.fmap = fmap
        self.domain = np.asarray(domain, dtype=float)
        self._planes = {}
        self._seams = [self._seam_tables(a, swap, flip) for a, swap, flip in seams]

    def _seam_tables(self, a, swap, flip):
        """Index tables taking a min-face grid point (along a) to the same point on the max face."""
        b, c = _others(a)
        lo, hi = self.domain
        nb = (self.params[b] - lo[b]) / (hi[b] - lo[b])
        nc = (self.params[c] - lo[c]) / (hi[c] - lo[c])

        def find(norm, vals, axis):
            pos = np.clip(np.searchsorted(norm, vals), 1, len(norm) - 1)
            pick = np.where(np.abs(norm[pos] - vals) < np.abs(norm[pos - 1] - vals), pos, pos - 1)
            if np.max(np.abs(norm[pick] - vals)) > 1e-8:
                raise GeometryError(f"compose: the samples along {AXES[axis]} do not match across the "
                                    f"{AXES[a]} seam")
            return pick

        # inverse of g: unflip (s', t'), then unswap
        x = 1.0 - nb if flip[0] else nb  # from the min face's b index
        y = 1.0 - nc if flip[1] else nc  # from the min face's c index
        if swap:
            # max-face b comes from y (min face c index), max-face c from x (min face b index)
            return a, b, c, swap, find(nb, y, b), find(nc, x, c)
        return a, b, c, swap, find(nb, x, b), find(nc, y, c)

    def canonical(self, idx):
        """(m, 3) grid indices -> (m, 3) indices of the same points, moved off every periodic min face."""
        idx = np.array(idx, dtype=np.int64, copy=True)
        for _ in range(8):
            moved = False
            for a, b, c, swap, tb, tc in self._seams:
                on = idx[:, a] == 0
                if not np.any(on):
                    continue
                moved = True
                ib, ic = idx[on, b], idx[on, c]
                if swap:
                    idx[on, b], idx[on, c] = tb[ic], tc[ib]
                else:
                    idx[on, b], idx[on, c] = tb[ib], tc[ic]
                idx[on, a] = self.n[a] - 1
            if not moved:
                return idx
        raise GeometryError("compose: grid indices did not settle under the periodic seams")

    def fill(self):
        """Evaluate every break plane now (before the grid is sent to worker processes)."""
        for a in range(3):
            for i in np.flatnonzero(self.is_break[a]):
                self.plane(a, int(i))
        return self

    def keys(self, idx):
        return np.ravel_multi_index(tuple(np.asarray(idx).T), self.n)

    def plane(self, a, i):
        """F on the whole plane params[a] == params[a][i]: (n_b, n_c, 3), evaluated in one batch."""
        key = (a, i)
        if key not in self._planes:
            b, c = _others(a)
            uvw = np.empty((self.n[b], self.n[c], 3))
            uvw[..., a] = self.params[a][i]
            uvw[..., b] = self.params[b][:, None]
            uvw[..., c] = self.params[c][None, :]
            xyz = self.fmap.evaluate(uvw.reshape(-1, 3)).reshape(self.n[b], self.n[c], 3)
            xyz.setflags(write=False)
            self._planes[key] = xyz
        return self._planes[key]

    def positions(self, cidx):
        """(m, 3) canonical grid indices, each on at least one break plane -> (m, 3) mm."""
        cidx = np.asarray(cidx, dtype=np.int64)
        out = np.empty((len(cidx), 3))
        done = np.zeros(len(cidx), dtype=bool)
        for a in range(3):
            b, c = _others(a)
            sel = ~done & self.is_break[a][cidx[:, a]]
            for i in np.unique(cidx[sel, a]):
                rows = sel & (cidx[:, a] == i)
                out[rows] = self.plane(a, int(i))[cidx[rows, b], cidx[rows, c]]
            done |= sel
        if not np.all(done):
            raise GeometryError("compose: a vertex off every cell face was asked for (internal error)")
        return out


def _face_quads(grid, a, i, rb, rc):
    """Quads of plane (a, i) over b indices rb, c indices rc: (own indices (nb, nc, 3), canonical keys (nb, nc),
    positions (nb, nc, 3), main (nb-1, nc-1) bool: True where the diagonal 00-11 is used)."""
    b, c = _others(a)
    idx = np.empty((len(rb), len(rc), 3), dtype=np.int64)
    idx[..., a] = i
    idx[..., b] = np.asarray(rb)[:, None]
    idx[..., c] = np.asarray(rc)[None, :]
    flat = idx.reshape(-1, 3)
    cidx = grid.canonical(flat)
    keys = grid.keys(cidx).reshape(len(rb), len(rc))
    pos = grid.positions(cidx).reshape(len(rb), len(rc), 3)
    p00, p10, p01, p11 = pos[:-1, :-1], pos[1:, :-1], pos[:-1, 1:], pos[1:, 1:]
    d_main = np.linalg.norm(p11 - p00, axis=-1)
    d_anti = np.linalg.norm(p01 - p10, axis=-1)
    k00, k10, k01, k11 = keys[:-1, :-1], keys[1:, :-1], keys[:-1, 1:], keys[1:, 1:]
    # the shorter diagonal; exact ties go by the smallest canonical key, which both sides of a face share
    tie_main = np.minimum(k00, k11) < np.minimum(k10, k01)
    main = (d_main < d_anti) | ((d_main == d_anti) & tie_main)
    return idx, keys, pos, main


def _measure(grid, fmap, tol_target):
    """Largest deviation of the tessellation from F on every break plane; flags per axis interval to bisect."""
    flags = [np.zeros(n - 1, dtype=bool) for n in grid.n]
    worst = 0.0
    periodic_axes = {s[0] for s in grid._seams}
    for a in range(3):
        b, c = _others(a)
        pb, pc = grid.params[b], grid.params[c]
        for i in np.flatnonzero(grid.is_break[a]):
            if a in periodic_axes and i == 0:
                continue  # the same surface as the max plane, which is measured
            _, _, g, main = _face_quads(grid, a, int(i), np.arange(len(pb)), np.arange(len(pc)))
            t = grid.params[a][i]
            mb = 0.5 * (pb[:-1] + pb[1:])
            mc = 0.5 * (pc[:-1] + pc[1:])

            def ev(bb, cc):
                bb, cc = np.broadcast_arrays(bb, cc)
                uvw = np.empty(bb.shape + (3,))
                uvw[..., a], uvw[..., b], uvw[..., c] = t, bb, cc
                return fmap.evaluate(uvw.reshape(-1, 3)).reshape(bb.shape + (3,))

            eb = np.linalg.norm(ev(mb[:, None], pc[None, :]) - 0.5 * (g[:-1] + g[1:]), axis=-1)  # (nb-1, nc)
            ec = np.linalg.norm(ev(pb[:, None], mc[None, :]) - 0.5 * (g[:, :-1] + g[:, 1:]), axis=-1)  # (nb, nc-1)
            flags[b] |= eb.max(axis=1) > tol_target
            flags[c] |= ec.max(axis=0) > tol_target
            worst = max(worst, float(eb.max(initial=0)), float(ec.max(initial=0)))
            p00, p10, p01, p11 = g[:-1, :-1], g[1:, :-1], g[:-1, 1:], g[1:, 1:]
            b0, b1 = pb[:-1, None], pb[1:, None]
            c0, c1 = pc[None, :-1], pc[None, 1:]
            centre = ev(0.5 * (b0 + b1), 0.5 * (c0 + c1))
            dmid = np.where(main[..., None], 0.5 * (p00 + p11), 0.5 * (p10 + p01))
            eq = np.linalg.norm(centre - dmid, axis=-1)
            # triangle centroids: main (00,10,11), (00,11,01); anti (00,10,01), (10,11,01)
            third = lambda x0, x1: (2 * x0 + x1) / 3  # noqa: E731
            for bm, cm, lm, ba, ca, la in (
                    (third(b1, b0), third(c0, c1), (p00 + p10 + p11) / 3,
                     third(b0, b1), third(c0, c1), (p00 + p10 + p01) / 3),
                    (third(b0, b1), third(c1, c0), (p00 + p11 + p01) / 3,
                     third(b1, b0), third(c1, c0), (p10 + p11 + p01) / 3)):
                xyz = ev(np.where(main, bm, ba), np.where(main, cm, ca))
                eq = np.maximum(eq, np.linalg.norm(xyz - np.where(main[..., None], lm, la), axis=-1))
            worst = max(worst, float(eq.max(initial=0)))
            bad = eq > tol_target
            if np.any(bad):
                lb = np.linalg.norm(p10 - p00, axis=-1)
                lc = np.linalg.norm(p01 - p00, axis=-1)
                flags[b] |= np.any(bad & (lb >= lc), axis=1)
                flags[c] |= np.any(bad & (lc > lb), axis=0)
    return worst, flags


def _initial_params(tiling, fmap):
    params = []
    src = fmap.warp if fmap.warp is not None else fmap.model
    for a in range(3):
        br = np.asarray(tiling.breaks[a], dtype=float)
        k = np.asarray(src.knots[a], dtype=float)
        k = k[(k > br[0]) & (k < br[-1])]
        mids = 0.5 * (br[:-1] + br[1:])
        vals = np.unique(np.concatenate([br, mids]))
        vals, _ = _merge(vals, k, 1e-9 * (br[-1] - br[0]))
        params.append(vals)
    return params


def _break_index(params, breaks):
    out = []
    for p, br in zip(params, breaks):
        i = np.searchsorted(p, br)
        i = np.clip(i, 0, len(p) - 1)
        assert np.all(p[i] == br)
        out.append(i.astype(np.int64))
    return tuple(out)


def sample_parameters(tiling, fmap, tolerance):
    """Adaptive per-axis sample parameters, refined by bisection until the tessellation of every cell face deviates
    from F by at most `tolerance` mm at the measured points. -> Sampling."""
    tolerance = float(tolerance)
    if not tolerance > 0:
        raise GeometryError(f"output.tolerance: must be > 0 mm (got {tolerance:g})")
    seams = _seam_tuples(tiling)
    domain = np.asarray(tiling.domain, dtype=float)
    params = _symmetrise(_initial_params(tiling, fmap), seams, domain)
    target = _SAFETY * tolerance
    for _ in range(64):
        bi = _break_index(params, tiling.breaks)
        grid = _Grid(params, bi, seams, domain, fmap)
        worst, flags = _measure(grid, fmap, target)
        if not any(f.any() for f in flags):
            return Sampling(tuple(_ro(p) for p in params), bi, seams, _ro(domain), worst, tolerance)
        new = []
        for a in range(3):
            p = params[a]
            mids = 0.5 * (p[:-1] + p[1:])[flags[a]]
            new.append(np.union1d(p, mids))
            if len(new[a]) > _MAX_SAMPLES:
                raise GeometryError(
                    f"output.tolerance: {tolerance:g} mm needs more than {_MAX_SAMPLES} samples along "
                    f"{AXES[a]} (got tolerance {tolerance:g}, expected a coarser one, e.g. {tolerance * 4:g})")
        params = _symmetrise(new, seams, domain)
    raise GeometryError(f"output.tolerance: the tessellation did not reach {tolerance:g} mm (worst {worst:g} mm)")


def _ro(a):
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _grid_for(sampling, fmap):
    return _Grid(sampling.params, sampling.break_index, sampling.seams, sampling.domain, fmap)


# ------------------------------------------------------------------------------------------------------------
# cell surfaces

def _cell_boundary(cell, sampling, grid):
    """Triangles of the cell box's boundary as own grid indices (t, 3, 3) and canonical keys (t, 3),
    oriented outward in parameter space."""
    idx3 = []
    keys3 = []
    rng = []
    for a in range(3):
        lo = int(sampling.break_index[a][cell.index[a]])
        hi = int(sampling.break_index[a][cell.index[a] + 1])
        rng.append(np.arange(lo, hi + 1))
    for a in range(3):
        b, c = _others(a)
        sign = -1 if a == 1 else 1  # e_b x e_c = sign * e_a for b < c
        for side, i in ((-1, rng[a][0]), (1, rng[a][-1])):
            idx, keys, _, main = _face_quads(grid, a, int(i), rng[b], rng[c])
            q = [(slice(None, -1), slice(None, -1)), (slice(1, None), slice(None, -1)),
                 (slice(1, None), slice(1, None)), (slice(None, -1), slice(1, None))]
            ki = [idx[s].reshape(-1, 3) for s in q]
            kk = [keys[s].ravel() for s in q]
            m = main.ravel()
            # corners 0=00, 1=10, 2=11, 3=01 counter-clockwise about e_b x e_c
            tri_main = [(0, 1, 2), (0, 2, 3)]
            tri_anti = [(0, 1, 3), (1, 2, 3)]
            for tm, ta in zip(tri_main, tri_anti):
                order = [np.where(m, tm[k], ta[k]) for k in range(3)]
                if sign * side < 0:
                    order = [order[0], order[2], order[1]]
                ti = np.stack([_pick(ki, o) for o in order], axis=1)
                tk = np.stack([_pick(kk, o) for o in order], axis=1)
                idx3.append(ti)
                keys3.append(tk)
    return np.concatenate(idx3), np.concatenate(keys3)


def _pick(arrs, which):
    out = np.empty_like(arrs[0])
    for k, arr in enumerate(arrs):
        sel = which == k
        out[sel] = arr[sel]
    return out


def _surface_from_keys(grid, keys, orientation):
    """Canonical keys (t, 3) -> welded, outward vertices (n, 3) mm and faces (m, 3)."""
    uniq, faces = np.unique(keys.ravel(), return_inverse=True)
    faces = faces.reshape(-1, 3)
    cidx = np.stack(np.unravel_index(uniq, grid.n), axis=1)
    verts = grid.positions(cidx)
    if orientation < 0:
        faces = faces[:, [0, 2, 1]]
    return geometry.weld(verts, faces, _WELD_MM)


def cell_surface(cell, sampling, fmap, grid=None):
    """Closed, outward triangulated boundary of the cell in mm: (vertices (n, 3), faces (m, 3) int)."""
    grid = grid if grid is not None else _grid_for(sampling, fmap)
    _, keys = _cell_boundary(cell, sampling, grid)
    return _surface_from_keys(grid, keys, fmap.orientation)


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
    from . import joint as joint_mod  # a later stage's helpers; imported only when there are joints

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


def _face_positions(cell, sampling, grid, q):
    """Vertices on the cell box's faces take the mapped grid's piecewise-linear positions, so a face cut by a pin
    or hole in the domain still lies exactly on the cut surface the neighbour sees.
    -> xyz (n, 3) (NaN off the faces), mask (n,) int: bit 2a+side set when on that face."""
    xyz = np.full(q.shape, np.nan)
    mask = np.zeros(len(q), dtype=np.int64)
    rng = []
    for a in range(3):
        lo = int(sampling.break_index[a][cell.index[a]])
        hi = int(sampling.break_index[a][cell.index[a] + 1])
        rng.append(np.arange(lo, hi + 1))
    for a in range(3):
        b, c = _others(a)
        eps = 1e-10 * (sampling.domain[1][a] - sampling.domain[0][a])
        for side, i in ((0, rng[a][0]), (1, rng[a][-1])):
            on = np.abs(q[:, a] - sampling.params[a][i]) <= eps
            if not np.any(on):
                continue
            mask[on] |= 1 << (2 * a + side)
            todo = on & np.isnan(xyz[:, 0])
            if not np.any(todo):
                continue
            _, _, pos, main = _face_quads(grid, a, int(i), rng[b], rng[c])
            pb, pc = sampling.params[b][rng[b]], sampling.params[c][rng[c]]
            x, y = q[todo, b], q[todo, c]
            ib = np.clip(np.searchsorted(pb, x) - 1, 0, len(pb) - 2)
            ic = np.clip(np.searchsorted(pc, y) - 1, 0, len(pc) - 2)
            s = np.clip((x - pb[ib]) / (pb[ib + 1] - pb[ib]), 0, 1)
            t = np.clip((y - pc[ic]) / (pc[ic + 1] - pc[ic]), 0, 1)
            p00, p10 = pos[ib, ic], pos[ib + 1, ic]
            p01, p11 = pos[ib, ic + 1], pos[ib + 1, ic + 1]
            m = main[ib, ic][:, None]
            s, t = s[:, None], t[:, None]
            # main diagonal 00-11: below it (s >= t) triangle (00, 10, 11), above it (00, 11, 01)
            lower = np.where(s >= t, p00 + s * (p10 - p00) + t * (p11 - p10), p00 + t * (p01 - p00) + s * (p11 - p01))
            # anti diagonal 10-01: (00, 10, 01) where s + t <= 1, else (10, 11, 01)
            anti = np.where(s + t <= 1, p00 + s * (p10 - p00) + t * (p01 - p00),
                            p11 + (1 - s) * (p01 - p11) + (1 - t) * (p10 - p11))
            xyz[todo] = np.where(m, lower, anti)
    return xyz, mask


def _domain_body(cell, sampling, fmap, grid, dpins, dholes, what):
    """Booleans in parameter space on the cell's own grid, then the vertices mapped through F with the new
    triangles off the box faces split until their edges meet the tolerance. -> (vertices, faces) in mm, outward."""
    idx3, _ = _cell_boundary(cell, sampling, grid)
    own_keys = np.ravel_multi_index(tuple(idx3.reshape(-1, 3).T), grid.n)
    uniq, inv = np.unique(own_keys, return_inverse=True)
    own_idx = np.stack(np.unravel_index(uniq, grid.n), axis=1)
    uvw = np.stack([sampling.params[a][own_idx[:, a]] for a in range(3)], axis=1)
    body = geometry.manifold_from_mesh(uvw, inv.reshape(-1, 3), f"{what} (parameter box)")
    body = _apply(body, dpins, dholes, f"{what} (in the domain)")
    out = geometry.to_trimesh(body)
    q = np.asarray(out.vertices, dtype=float)
    f = np.asarray(out.faces, dtype=np.int64)
    xyz, mask = _face_positions(cell, sampling, grid, q)
    # grid vertices keep their exact parameters through the engine; they take the shared, canonical positions
    on = np.ones(len(q), dtype=bool)
    gi = np.empty((len(q), 3), dtype=np.int64)
    for a in range(3):
        p = sampling.params[a]
        k = np.clip(np.searchsorted(p, q[:, a]), 0, len(p) - 1)
        on &= p[k] == q[:, a]
        gi[:, a] = k
    on &= mask != 0
    if np.any(on):
        xyz[on] = grid.positions(grid.canonical(gi[on]))
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


def build_piece(cell, tiling, sampling, fmap, joints, what=None, grid=None):
    """One cell -> Piece: its body through F, pins united and holes subtracted (in mm, or in the domain for
    joints with space 'domain'); checked to be one closed solid with outward normals."""
    what = what or cell.id
    grid = grid if grid is not None else _grid_for(sampling, fmap)
    index = tuple(cell.index)
    verts, faces = cell_surface(cell, sampling, fmap, grid)
    body = geometry.manifold_from_mesh(verts, faces, what)
    body_volume = float(body.volume())
    pins, holes, dpins, dholes = _joint_solids(joints, index)
    if dpins or dholes:
        v2, f2 = _domain_body(cell, sampling, fmap, grid, dpins, dholes, what)
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


def _init_worker(tiling, sampling, fmap, joints, grid=None):
    grid = grid if grid is not None else _grid_for(sampling, fmap)
    _WORKER.update(tiling=tiling, sampling=sampling, fmap=fmap, joints=joints, grid=grid)


def _build_in_worker(index):
    w = _WORKER
    t0 = time.perf_counter()
    p = build_piece(w["tiling"].cell(index), w["tiling"], w["sampling"], w["fmap"], w["joints"], grid=w["grid"])
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


def compose(tiling, fmap, joints, tolerance, jobs=1, progress=None, sampling=None):
    """Every cell -> Piece, in cell-index order (a list, with .sampling and .seconds). jobs > 1 builds in a process
    pool (same results as jobs=1); progress(i, n, piece_id) is called as pieces finish. Pass `sampling` to reuse one
    from sample_parameters."""
    sampling = sampling if sampling is not None else sample_parameters(tiling, fmap, tolerance)
    order = sorted(tiling.cells)
    n = len(order)
    joints = list(joints or [])
    recs = {}
    if jobs is None or jobs <= 1 or n <= 1:
        _init_worker(tiling, sampling, fmap, joints)
        try:
            for k, index in enumerate(order):
                recs[index] = _build_in_worker(index)
                if progress:
                    progress(k + 1, n, recs[index][0])
        finally:
            _WORKER.clear()
    else:
        ctx = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(max_workers=int(jobs), mp_context=ctx, initializer=_init_worker,
                                                    initargs=(tiling, sampling, fmap, joints,
                                                              _grid_for(sampling, fmap).fill())) as pool:
            futures = {pool.submit(_build_in_worker, index): index for index in order}
            for k, fut in enumerate(concurrent.futures.as_completed(futures)):
                try:
                    rec = fut.result()
                except concurrent.futures.process.BrokenProcessPool as e:
                    raise GeometryError(f"compose: a worker process died while building "
                                        f"{tiling.cell(futures[fut]).id} ({e}); try --jobs 1") from e
                recs[futures[fut]] = rec
                if progress:
                    progress(k + 1, n, rec[0])
    out = Pieces(_piece_from(recs[index]) for index in order)
    out.sampling = sampling
    out.seconds = {recs[index][0]: recs[index][6] for index in order}
    return out
