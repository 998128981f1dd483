"""Trivariate cages around a closed mesh (paper section 5): the cage Mc is the model the puzzle is cut from, and each
piece is then intersected with the mesh. Curved cages make the cuts follow the shape (the paper's Fig. 14).

Every cage has the domain [0, 1]^3, is in mm and right-handed (det J > 0 inside; it may vanish on a collapsed face):
  box       (u, v, w) = the three box axes; no periodic axis.
  cylinder  (u, v, w) = (radius, angle, height); v is periodic (the seam v=0 ~ v=1); u=0 collapses to the axis.
  sphere    (u, v, w) = (radius, polar angle, azimuth); w is periodic; u=0 collapses to the centre, v=0 and v=1 to
            the poles' half-axes.
  nurbs     any model file; periodic axes are whatever the file has (find them with spline.seams.find_seams).
The circles are exact rational quadratics (The NURBS Book, section 7.5, nine-point circle; section 8.5 for the
sphere as a surface of revolution).
"""

import numpy as np
import trimesh

from .errors import ModelError
from .geometry import hull_points_of
from .grid import frame_from_direction
from .spline.knots import greville, uniform_knots
from .spline.volume import Volume

__all__ = ["make_cage", "check_inside", "cage_boundary", "mesh_mass", "PERIODIC_AXES"]

PERIODIC_AXES = {"box": [], "cylinder": [1], "sphere": [2]}
_S = np.sqrt(0.5)
# nine-point rational circle of radius 1 (square control polygon), four quarter arcs
_CIRCLE_XY = np.array([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1], [1, 0]], float)
_CIRCLE_W = np.array([1, _S, 1, _S, 1, _S, 1, _S, 1])
_CIRCLE_KNOTS = np.array([0, 0, 0, .25, .25, .5, .5, .75, .75, 1, 1, 1])
# half circle from the north pole to the south pole in the (rho, z) half-plane, two quarter arcs
_HALF_RZ = np.array([[0, 1], [1, 1], [1, 0], [1, -1], [0, -1]], float)
_HALF_W = np.array([1, _S, 1, _S, 1])
_HALF_KNOTS = np.array([0, 0, 0, .5, .5, 1, 1, 1])


def _right_handed(axes):
    """axes (3, 3) rows -> rows reordered to be nearest x, y, z, pointing along them, with det > 0."""
    axes = np.asarray(axes, float)
    order, used = [], set()
    for k in range(3):
        cand = [i for i in range(3) if i not in used]
        i = max(cand, key=lambda i: abs(axes[i, k]))
        used.add(i)
        order.append(i)
    r = axes[order].copy()
    for k in range(3):
        if r[k, k] < 0:
            r[k] = -r[k]
    if np.linalg.det(r) < 0:
        r[2] = -r[2]
    return r


def _frame_box(pts, axes, pad):
    local = pts @ axes.T
    llo, lhi = local.min(axis=0), local.max(axis=0)
    return axes, axes.T @ ((llo + lhi) / 2), (lhi - llo) / 2 + pad


def _balance(mesh, frame, grid, n=24):
    """The largest over the smallest cell's share of the mesh when a box in `frame` is cut by balanced splits."""
    from .tile import _balanced, _cell_masses

    axes, center, half = frame
    t = (np.arange(n) + 0.5) / n
    local = (np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * 2 - 1) * half
    w = _inside(mesh, center + local @ axes).reshape(n, n, n).astype(float)
    if w.sum() <= 0:
        return np.inf
    w /= w.sum()
    breaks = _balanced(tuple(np.linspace(0.0, 1.0, g + 1) for g in grid), w, [a for a in range(3) if grid[a] > 1],
                       sweeps=2, steps=16)
    prefix = np.zeros((n + 1,) * 3)
    prefix[1:, 1:, 1:] = w.cumsum(0).cumsum(1).cumsum(2)
    cells = _cell_masses(prefix, [np.asarray(b) * n for b in breaks])
    return float(cells.max() / max(cells.min(), 1e-9))


def _box(mesh, pad, cps, balance_grid=None):
    """balance_grid: the grid of balanced splits, when they are asked for: the box's frame is then the one (axis-
    aligned, smallest box, principal axes of inertia) whose pieces come out the most even, not the smallest box
    (the bunny's smallest box leaves its octants 3.3x apart, its axes of inertia 1.3x)."""
    pts = hull_points_of(mesh)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    aabb = (np.eye(3), (lo + hi) / 2, (hi - lo) / 2 + pad)
    best, kind = aabb, "axis-aligned"
    frames = [(aabb, "axis-aligned")]
    try:
        cand = _frame_box(pts, _right_handed(np.asarray(mesh.bounding_box_oriented.primitive.transform)[:3, :3].T),
                          pad)
        frames.append((cand, "principal axes"))
        if np.prod(cand[2]) < np.prod(aabb[2]) * (1 - 1e-6):
            best, kind = cand, "principal axes"
    except Exception:  # trimesh's oriented bounds can fail on degenerate hulls; the axis-aligned box stands
        pass
    if balance_grid is not None and any(g > 1 for g in balance_grid):
        try:
            frames.append((_frame_box(pts, _right_handed(np.asarray(mesh.principal_inertia_vectors, float)), pad),
                           "axes of inertia"))
        except Exception:  # a degenerate inertia tensor: the other frames stand
            pass
        scores = [_balance(mesh, f, balance_grid) for f, _ in frames]
        k = int(np.argmin(scores))
        # the smallest box is one of the frames scored: its score again would cost another pass over the mesh
        if scores[k] < scores[next(i for i, (f, _) in enumerate(frames) if f is best)] * (1 - 1e-6):
            best, kind = frames[k]
    axes, center, half = best
    n = (2, 2, 2) if cps is None else tuple(int(c) for c in cps)
    degrees = tuple(1 if cps is None else min(3, k - 1) for k in n)
    knots = tuple(uniform_knots(k, degree=p) for k, p in zip(n, degrees, strict=True))
    # control points at the Greville abscissae: the spline reproduces the linear map exactly (linear precision)
    g = [(greville(kn, p) * 2 - 1) * h for kn, p, h in zip(knots, degrees, half, strict=True)]
    local = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1)
    cp = center + local @ axes
    vol = Volume(degrees, knots, cp)
    info = {"type": "box", "frame": kind, "center_mm": center.tolist(), "axes": axes.tolist(),
            "size_mm": (2 * half).tolist()}
    return vol, info


def _min_circle(points2d):
    c, r = trimesh.nsphere.minimum_nsphere(points2d)
    return np.asarray(c, float), float(r)


def _cylinder(mesh, pad):
    pts = hull_points_of(mesh)
    cands = [np.eye(3)[k] for k in range(3)]
    try:
        cands += list(np.asarray(mesh.principal_inertia_vectors, float))
        cands += list(np.asarray(mesh.bounding_box_oriented.primitive.transform)[:3, :3].T)
    except Exception:
        pass
    best = None
    for a in cands:
        a = np.asarray(a, float)
        e1, e2, a = frame_from_direction(a / np.linalg.norm(a))
        p2 = np.stack([pts @ e1, pts @ e2], axis=1)
        c2, r = _min_circle(p2)
        h = pts @ a
        size = np.pi * (r + pad) ** 2 * (h.max() - h.min() + 2 * pad)
        if best is None or size < best[0] * (1 - 1e-9):
            best = (size, e1, e2, a, c2, r, h.min(), h.max())
    _, e1, e2, a, c2, r, h0, h1 = best
    R = r + pad
    radii = np.array([0.0, R])
    heights = np.array([h0 - pad, h1 + pad])
    ring = _CIRCLE_XY[:, 0:1] * e1 + _CIRCLE_XY[:, 1:2] * e2  # (9, 3)
    base = c2[0] * e1 + c2[1] * e2
    cp = (base + radii[:, None, None, None] * ring[None, :, None, :]
          + heights[None, None, :, None] * a[None, None, None, :])
    w = np.broadcast_to(_CIRCLE_W[None, :, None], (2, 9, 2)).copy()
    vol = Volume((1, 2, 1), (np.array([0, 0, 1, 1.0]), _CIRCLE_KNOTS, np.array([0, 0, 1, 1.0])), cp, w)
    info = {"type": "cylinder", "axis": a.tolist(), "center_mm": (base + heights[0] * a).tolist(), "radius_mm": R,
            "height_mm": float(heights[1] - heights[0])}
    return vol, info


def _sphere(mesh, pad):
    pts = hull_points_of(mesh)
    c, r = trimesh.nsphere.minimum_nsphere(pts)
    c, R = np.asarray(c, float), float(r) + pad
    radii = np.array([0.0, R])
    # surface of revolution (The NURBS Book, A8.1): the polar half circle's rho scales the azimuth circle
    xy = _CIRCLE_XY  # (9, 2)
    pol = _HALF_RZ  # (5, 2): rho, z
    unit = np.zeros((5, 9, 3))
    unit[..., 0] = pol[:, None, 0] * xy[None, :, 0]
    unit[..., 1] = pol[:, None, 0] * xy[None, :, 1]
    unit[..., 2] = pol[:, None, 1]
    cp = c + radii[:, None, None, None] * unit[None]
    w = np.broadcast_to((_HALF_W[:, None] * _CIRCLE_W[None, :])[None], (2, 5, 9)).copy()
    vol = Volume((1, 2, 2), (np.array([0, 0, 1, 1.0]), _HALF_KNOTS, _CIRCLE_KNOTS), cp, w)
    info = {"type": "sphere", "center_mm": c.tolist(), "radius_mm": R}
    return vol, info


def make_cage(mesh, cage_spec, scale=1.0, balance_grid=None):
    """A cage Volume (mm, domain [0, 1]^3 for the built-in types) around `mesh` (mm) -> (Volume, info dict).

    cage_spec: spec.CageSpec. scale: mm per unit of a NURBS cage file -- the mesh's whole scale (units and size),
    so that a cage drawn around the unscaled mesh still fits it. balance_grid: the grid, when its splits are balanced
    (a box cage then takes the frame that cuts the mesh most evenly). info holds 'type', 'periodic' (axis indices of
    the closed seams, for the spec's `periodic`) and the cage's measures.
    """
    kind = cage_spec.type
    pad = float(cage_spec.padding or 0.0)
    if kind == "box":
        vol, info = _box(mesh, pad, cage_spec.control_points, balance_grid)
    elif kind == "cylinder":
        vol, info = _cylinder(mesh, pad)
    elif kind == "sphere":
        vol, info = _sphere(mesh, pad)
    elif kind == "nurbs":
        from .io import load_model
        from .spline.seams import find_seams

        vol = load_model(cage_spec.nurbs, patch=cage_spec.patch)
        if scale != 1.0:
            vol = vol.scaled(scale)
        info = {"type": "nurbs", "file": str(cage_spec.nurbs), "patch": cage_spec.patch,
                "periodic": sorted(int(a) for a in find_seams(vol))}
        return vol, info
    else:
        raise ModelError(f"model.cage.type: unknown cage {kind!r} (expected box, cylinder, sphere or nurbs)")
    info["padding_mm"] = pad
    info["periodic"] = list(PERIODIC_AXES[kind])
    return vol, info


def _samples(vol, a, n_min=8, per_span=6, n_max=64):
    lo, hi = vol.domain[a]
    kn = np.unique(vol.knots[a])
    spans = max(1, len(kn) - 1)
    n = int(np.clip(per_span * spans * max(1, vol.degrees[a]), n_min, n_max))
    t = np.linspace(lo, hi, n + 1)
    return np.unique(np.concatenate([t, kn[(kn >= lo) & (kn <= hi)]]))


def _weld(v, f, tol):
    """Merge vertices equal up to tol (a collapsed face puts thousands on one point, where a pairwise search would
    crawl), drop triangles that lose an edge, and cancel pairs of opposite triangles (the two faces of a seam).

    Not geometry.weld on purpose: that one clusters by distance (a KD-tree's close pairs, slow on such a pile) and
    keeps the vertices in order; this one snaps to a tol grid and drops unused vertices, and the cage boundary's
    vertices and faces (hence check_inside's answers) depend on that."""
    key = np.round(v / tol).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    f = inv.ravel()[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    srt = np.sort(f, axis=1)
    _, tinv, tcount = np.unique(srt, axis=0, return_inverse=True, return_counts=True)
    f = f[tcount[tinv.ravel()] == 1]  # a triangle met twice is a seam's pair (or a fold, which the check catches)
    used, f = np.unique(f, return_inverse=True)
    return v[first][used], f.reshape(-1, 3)


def cage_boundary(vol):
    """The cage's boundary as a closed trimesh (mm), outward-facing: its six faces sampled on a grid, welded so that
    collapsed faces (an axis, a pole) vanish and the two faces of a periodic seam cancel."""
    ts = [_samples(vol, a) for a in range(3)]
    verts, faces, n = [], [], 0
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        for side in (0, 1):
            grids = [None, None, None]
            grids[a] = np.array([ts[a][0] if side == 0 else ts[a][-1]])
            grids[b], grids[c] = ts[b], ts[c]
            xyz = vol.evaluate_grid(*grids)  # (.., .., .., 3) in axis order u, v, w
            # index as (b, c)
            xyz = np.moveaxis(xyz, (b, c), (0, 1)).reshape(len(ts[b]), len(ts[c]), 3)
            nb, nc = xyz.shape[:2]
            idx = np.arange(nb * nc).reshape(nb, nc) + n
            q0, q1, q2, q3 = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
            # d/db x d/dc points along +a on a right-handed map: outward on the max face
            t = np.concatenate([np.stack([q0, q1, q2], -1).reshape(-1, 3), np.stack([q0, q2, q3], -1).reshape(-1, 3)])
            if side == 0:
                t = t[:, ::-1]
            verts.append(xyz.reshape(-1, 3))
            faces.append(t)
            n += nb * nc
    v = np.concatenate(verts)
    span = float(np.ptp(v, axis=0).max()) or 1.0
    v, f = _weld(v, np.concatenate(faces), 1e-9 * span)
    mesh = trimesh.Trimesh(v, f, process=False)
    if mesh.volume < 0:  # a left-handed cage file
        mesh.invert()
    return mesh


def _farthest(surface, pts, keep=64):
    """The points farthest from `surface` and their distances: a k-d tree over the surface's vertices and triangle
    centres picks candidates, the exact point-triangle distance (no rtree needed) settles them."""
    from scipy.spatial import cKDTree

    probe = np.concatenate([surface.vertices, surface.triangles_center])
    approx, _ = cKDTree(probe).query(pts)
    pick = np.argsort(approx)[::-1][:keep]
    _, dist, _ = trimesh.proximity.closest_point_naive(surface, pts[pick])
    return pts[pick], np.asarray(dist)


def _inside_convex(mesh, bnd):
    """True when the cage's boundary `bnd` is convex (a box, a cylinder, a sphere: it encloses its own hull) and every
    corner of the mesh's hull lies in it, so the whole mesh does. A Boolean of the whole mesh says the same at a cost
    that grows with the mesh (seconds at 1.2M faces); False leaves the question to it."""
    try:
        hull = bnd.convex_hull
    except Exception:  # a flat or folded boundary: the Boolean judges
        return False
    if not bnd.volume >= hull.volume * (1 - 1e-9):
        return False
    pts = hull_points_of(mesh)
    normals = np.asarray(hull.face_normals, float)
    offsets = np.einsum("ij,ij->i", normals, np.asarray(hull.triangles, float)[:, 0])
    span = max(float(np.max(hull.extents)), 1.0)
    return bool(np.max(pts @ normals.T - offsets) <= 1e-9 * span)


def check_inside(mesh, cage, tol=1e-6):
    """Raise ModelError unless every point of `mesh` (mm) lies inside the cage Volume, saying how far (mm) the mesh
    reaches outside. The cage's boundary is sampled (chords cut curved faces by a little: keep some padding).
    -> the boundary mesh used, for reuse."""
    from .geometry import boolean, from_trimesh, solid_of

    bnd = cage_boundary(cage)
    try:
        cm = from_trimesh(bnd, "cage boundary")
    except Exception as e:
        raise ModelError(f"model.cage: its boundary is not a closed surface ({e}); is the cage folded?") from None
    if _inside_convex(mesh, bnd):
        return bnd
    mm = solid_of(mesh, "mesh model")  # the compose stage intersects the same solid with the pieces
    out = boolean(mm, cm, "difference", "mesh outside the cage")
    scale = max(float(np.max(mesh.extents)), 1.0)
    if out.is_empty() or out.volume() <= tol * scale ** 3:
        return bnd
    from .geometry import to_trimesh

    pts = np.asarray(to_trimesh(out).vertices)
    pts, dist = _farthest(bnd, pts)
    worst = int(np.argmax(dist))
    raise ModelError(
        f"model.cage: the mesh is not inside the cage: it reaches {float(dist[worst]):.3g} mm outside, at "
        f"({', '.join(f'{x:.4g}' for x in pts[worst])}) mm ({out.volume():.4g} mm^3 of it outside); "
        "enlarge the cage or its padding, or shrink the mesh (model.size)")


def _binned(mesh, bins):
    """The mesh's triangles (n, 3, 3) binned on a bins x bins grid over the mesh's own xy extent -> (triangles, xy
    min (2,), xy max (2,), bin size, sorted bin keys (k,), their triangles (k,)). Made once per mesh (geometry.memo):
    the cage's frames and the mass grid all ask of the same mesh, and at 1.2M faces this costs a second a time."""
    tri = np.asarray(mesh.triangles, float)
    txy = np.ascontiguousarray(tri[:, :, :2])
    tmin, tmax = txy.min(axis=1), txy.max(axis=1)
    lo, hi = tmin.min(axis=0), tmax.max(axis=0)
    h = (float(np.max(hi - lo)) or 1.0) / bins
    tlo = np.floor((tmin - lo) / h).astype(np.int64)
    thi = np.floor((tmax - lo) / h).astype(np.int64)
    nx, ny = thi[:, 0] - tlo[:, 0] + 1, thi[:, 1] - tlo[:, 1] + 1
    count = nx * ny
    tid = np.repeat(np.arange(len(tri)), count)
    off = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    key = (tlo[tid, 0] + off % nx[tid]) * (bins + 2) + tlo[tid, 1] + off // nx[tid]
    order = np.argsort(key, kind="stable")
    return tri, lo, hi, h, key[order], tid[order]


def _inside(mesh, pts, bins=128, chunk=4096):
    """Bool (n,) for points (n, 3) inside a closed mesh: the parity of the mesh's crossings with a ray along +z from
    each point. Triangles are binned on an xy grid so that each point meets only its bin's triangles (no rtree)."""
    from .geometry import memo

    tri, tlo, thi, h, key, tid = memo(mesh, ("inside_bins", bins), lambda: _binned(mesh, bins))
    pts = np.asarray(pts, float)
    lo = np.minimum(tlo, pts[:, :2].min(axis=0))
    size = float(np.max(np.maximum(thi, pts[:, :2].max(axis=0)) - lo)) or 1.0
    # rays off the grid of nice numbers, so that none runs exactly along an edge of a symmetric mesh
    pts = pts + np.array([0.31830989, 0.23570226, 0.0]) * 1e-7 * size
    out = np.zeros(len(pts), bool)
    for s in range(0, len(pts), chunk):
        p = pts[s:s + chunk]
        pb = np.floor((p[:, :2] - tlo) / h).astype(np.int64)
        # beside the mesh's xy extent no triangle lies over a point (its key would alias another row's bin)
        on = np.flatnonzero(np.all((pb >= 0) & (pb <= bins), axis=1))
        pk = pb[on, 0] * (bins + 2) + pb[on, 1]
        first, last = np.searchsorted(key, pk, "left"), np.searchsorted(key, pk, "right")
        cnt = last - first
        pid = np.repeat(np.arange(len(on)), cnt)
        t = tid[np.repeat(first, cnt) + np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)]
        a, b, c, q = tri[t, 0], tri[t, 1], tri[t, 2], p[on][pid]
        v0, v1, v2 = b - a, c - a, q - a
        den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):  # edge-on triangles (den 0) never count
            u = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
            v = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
            hit = (den != 0) & (u >= 0) & (v >= 0) & (u + v <= 1)
            hit &= a[:, 2] + u * v0[:, 2] + v * v1[:, 2] > q[:, 2]
        out[s + on] = np.bincount(pid[hit], minlength=len(on)) % 2 == 1
    return out


def mesh_mass(fmap, mesh, n=32):
    """How the mesh's volume spreads over the parameters of the piece map (the cage, warped when randomized), for
    balanced splits: (n, n, n) fractions of the mesh volume in the n^3 equal boxes of the domain. fmap: mapping.Map;
    each box is sampled at its centre mapped through it, weighted by |det J| and by whether it lies inside the mesh."""
    lo, hi = np.asarray(fmap.domain, float).T
    t = (np.arange(n) + 0.5) / n
    uvw = lo + np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * (hi - lo)
    xyz, jac = fmap.evaluate_with_jacobian(uvw)
    weight = np.abs(np.linalg.det(jac)) * _inside(mesh, xyz)
    total = float(weight.sum())
    return weight.reshape(n, n, n) / (total if total > 0 else 1.0)
