"""Compiled point-to-triangle distances (numba) for the dense-mesh simplification check (io.mesh.simplify_dense).

Chosen by measurement over trimesh.triangles.closest_point on gathered (n, 3, 3) arrays: at 1.2M faces the check
made ~3M point-triangle pairs, and numpy's passes over them (and the gathers feeding them) took 8 CPU s; here it
is one pass without temporaries. The closest point is Ericson's (Real-Time Collision Detection 5.1.5: vertex,
edge and face regions from six dot products); a collapsed triangle (a segment or a point) has no face region and
is measured as its three edges, and every answer is bounded by the nearest corner.
"""

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _point_segment2(px, py, pz, ax, ay, az, bx, by, bz):
    """Squared distance from a point to the segment ab (a point when a == b)."""
    ux, uy, uz = bx - ax, by - ay, bz - az
    wx, wy, wz = px - ax, py - ay, pz - az
    uu = ux * ux + uy * uy + uz * uz
    s = 0.0
    if uu > 0.0:
        s = min(max((ux * wx + uy * wy + uz * wz) / uu, 0.0), 1.0)
    qx, qy, qz = wx - s * ux, wy - s * uy, wz - s * uz
    return qx * qx + qy * qy + qz * qz


@njit(cache=True, nogil=True)
def _along2(px, py, pz, ax, ay, az, ex, ey, ez, v):
    """Squared distance from a point to a + v e, the closest point of an edge from a along e."""
    qx, qy, qz = ax + v * ex - px, ay + v * ey - py, az + v * ez - pz
    return qx * qx + qy * qy + qz * qz


@njit(cache=True, nogil=True)
def _point_triangle(px, py, pz, vt, a, b, c):
    """Distance from the point (px, py, pz) to the triangle of the vertices vt[a], vt[b], vt[c]."""
    ax, ay, az = vt[a, 0], vt[a, 1], vt[a, 2]
    abx, aby, abz = vt[b, 0] - ax, vt[b, 1] - ay, vt[b, 2] - az
    acx, acy, acz = vt[c, 0] - ax, vt[c, 1] - ay, vt[c, 2] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    bpx, bpy, bpz = px - vt[b, 0], py - vt[b, 1], pz - vt[b, 2]
    cpx, cpy, cpz = px - vt[c, 0], py - vt[c, 1], pz - vt[c, 2]
    corner = min(apx * apx + apy * apy + apz * apz, bpx * bpx + bpy * bpy + bpz * bpz,
                 cpx * cpx + cpy * cpy + cpz * cpz)
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:  # vertex region of a
        return math.sqrt(apx * apx + apy * apy + apz * apz)
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:  # vertex region of b
        return math.sqrt(min(corner, bpx * bpx + bpy * bpy + bpz * bpz))
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0 and d1 - d3 > 0.0:  # edge ab
        return math.sqrt(min(corner, _along2(px, py, pz, ax, ay, az, abx, aby, abz, d1 / (d1 - d3))))
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:  # vertex region of c
        return math.sqrt(min(corner, cpx * cpx + cpy * cpy + cpz * cpz))
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0 and d2 - d6 > 0.0:  # edge ac
        return math.sqrt(min(corner, _along2(px, py, pz, ax, ay, az, acx, acy, acz, d2 / (d2 - d6))))
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0 and (d4 - d3) + (d5 - d6) > 0.0:  # edge bc
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return math.sqrt(min(corner, _along2(px, py, pz, vt[b, 0], vt[b, 1], vt[b, 2], vt[c, 0] - vt[b, 0],
                                             vt[c, 1] - vt[b, 1], vt[c, 2] - vt[b, 2], w)))
    s = va + vb + vc  # = |ab x ac|^2
    if s > 1e-12 * (abx * abx + aby * aby + abz * abz) * (acx * acx + acy * acy + acz * acz):
        v, w = vb / s, vc / s
        if v >= 0.0 and w >= 0.0 and v + w <= 1.0:
            qx, qy, qz = ax + v * abx + w * acx - px, ay + v * aby + w * acy - py, az + v * abz + w * acz - pz
            return math.sqrt(min(corner, qx * qx + qy * qy + qz * qz))
    # collapsed onto a segment or a point, or so nearly (sin^2 of the angle at a below 1e-12) that the regions above
    # are lost to rounding: the nearest point lies on one of its edges
    ab = _point_segment2(px, py, pz, ax, ay, az, vt[b, 0], vt[b, 1], vt[b, 2])
    ac = _point_segment2(px, py, pz, ax, ay, az, vt[c, 0], vt[c, 1], vt[c, 2])
    bc = _point_segment2(px, py, pz, vt[b, 0], vt[b, 1], vt[b, 2], vt[c, 0], vt[c, 1], vt[c, 2])
    return math.sqrt(min(corner, ab, ac, bc))


@njit(cache=True, nogil=True)
def nearest_of(points, v, f, ptr, cand, best):
    """best[i] = min(best[i], distance from points[i] to each triangle f[cand[ptr[i]:ptr[i+1]]] of the vertices v).
    points (n, 3), v (k, 3) float64; f (m, 3), ptr (n+1,), cand int64; best (n,) updated in place and returned."""
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        b = best[i]
        for j in range(ptr[i], ptr[i + 1]):
            t = cand[j]
            d = _point_triangle(px, py, pz, v, f[t, 0], f[t, 1], f[t, 2])
            if d < b:
                b = d
        best[i] = b
    return best


@njit(cache=True, nogil=True)
def centres_and_reach(v, f):
    """The centres (m, 3) of the triangles f (m, 3) of the vertices v (k, 3), and the largest distance from a
    centre to a corner of its triangle, in one pass (numpy's gathers and norms made 200 MB of temporaries at 1.2M
    faces). A centre is (a + b + c) / 3 in that order, as numpy's mean over the corners is."""
    m = f.shape[0]
    centre = np.empty((m, 3))
    reach2 = 0.0
    for t in range(m):
        for k in range(3):
            centre[t, k] = (v[f[t, 0], k] + v[f[t, 1], k] + v[f[t, 2], k]) / 3.0
        for j in range(3):
            dx = v[f[t, j], 0] - centre[t, 0]
            dy = v[f[t, j], 1] - centre[t, 1]
            dz = v[f[t, j], 2] - centre[t, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 > reach2:
                reach2 = d2
    return centre, math.sqrt(reach2)


def nearest_distances(points, v, f, near, best=None):
    """Per point, the least distance to the triangles listed for it. points (n, 3), v (k, 3) vertices, f (m, 3)
    int64 triangles, near (n, j) int indices into f -> (n,) (the elementwise minimum with `best` when given)."""
    near = np.ascontiguousarray(near, dtype=np.int64)
    n, k = near.shape
    best = np.full(n, np.inf) if best is None else np.array(best, dtype=np.float64)
    ptr = np.arange(0, n * k + 1, k, dtype=np.int64)
    return nearest_of(np.ascontiguousarray(points, dtype=np.float64), v, f, ptr, near.reshape(-1), best)
