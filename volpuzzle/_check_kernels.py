"""Compiled kernels of the joint check (numba), in their own module: `volpuzzle check` of a small puzzle measures its
few joints with the engine alone rather than start numba (~0.5 s) for them.

A pin's test cylinder that no triangle of the piece comes near lies wholly inside the piece or wholly outside it, and
one ray tells which. So most tests need no Boolean: the engine measures only the cylinders that the surface crosses
or reaches (check._joint_measures).
"""

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def cylinder_side(vertices, faces, center, e1, e2, axis, radius, start, stop, margin):
    """Where the solid round cylinder of `radius` about the line center + t axis, start <= t <= stop (e1, e2, axis:
    an orthonormal frame) lies against the closed, consistently wound mesh (vertices (n, 3), faces (m, 3)): 1 wholly
    inside it, -1 wholly outside, 0 when a triangle comes within `margin` of the cylinder (or the count below cannot
    be trusted), which only the engine can measure.

    Each triangle is clipped to the slab start - margin <= t <= stop + margin and seen along the axis: the clipped
    polygon (convex, up to 5 corners) keeps clear when the axis lies more than radius + margin from it. A cylinder
    that no triangle reaches is connected and untouched, so one point tells its side: the ray from its axis point at
    the middle of the slab along the axis crosses the surface a net once when inside (the triangles seen around
    that point, signed by their winding, _around_axis); a ray that passes within rounding of an edge or a corner
    gives up."""
    reach = radius + margin
    lo, hi = start - margin, stop + margin
    mid = 0.5 * (start + stop)
    poly = np.empty((6, 3))  # the polygon's corners: (along the axis, across e1, across e2)
    tmp = np.empty((6, 3))
    crossings = 0
    for f in range(faces.shape[0]):
        below = above = 0
        for c in range(3):
            q = vertices[faces[f, c]]
            x0, x1, x2 = q[0] - center[0], q[1] - center[1], q[2] - center[2]
            t = x0 * axis[0] + x1 * axis[1] + x2 * axis[2]
            poly[c, 0] = t
            poly[c, 1] = x0 * e1[0] + x1 * e1[1] + x2 * e1[2]
            poly[c, 2] = x0 * e2[0] + x1 * e2[1] + x2 * e2[2]
            below += t < lo
            above += t > hi
        turn = _around_axis(poly)
        if turn == 2:
            return 0
        if turn != 0:
            # where the axis meets the triangle's plane, by the weights of its corners seen along the axis
            w0 = poly[1, 1] * poly[2, 2] - poly[1, 2] * poly[2, 1]
            w1 = poly[2, 1] * poly[0, 2] - poly[2, 2] * poly[0, 1]
            w2 = poly[0, 1] * poly[1, 2] - poly[0, 2] * poly[1, 1]
            if (w0 * poly[0, 0] + w1 * poly[1, 0] + w2 * poly[2, 0]) / (w0 + w1 + w2) > mid:
                crossings += turn
        if below == 3 or above == 3:
            continue
        n = 3
        if below > 0:
            n = _clip(poly, tmp, n, lo, 1.0)
            poly, tmp = tmp, poly
        if above > 0 and n > 0:
            n = _clip(poly, tmp, n, hi, -1.0)
            poly, tmp = tmp, poly
        if n > 0 and _distance_to_axis(poly, n) <= reach:
            return 0
    if crossings == 1 or crossings == -1:
        return 1
    return -1 if crossings == 0 else 0


@njit(cache=True, nogil=True)
def _around_axis(tri):
    """How the triangle tri[:3] (along the axis, across e1, across e2) winds about the axis seen along it: 1 or -1
    when the axis passes strictly inside it, 0 when it passes outside, 2 when it comes within rounding of an edge or
    a corner. Decided exactly, so that the count of crossings is: a triangle whose box the axis misses is outside,
    and an edge's side of the axis is trusted only when its cross product is far above its rounding."""
    if ((tri[0, 1] > 0.0 and tri[1, 1] > 0.0 and tri[2, 1] > 0.0)
            or (tri[0, 1] < 0.0 and tri[1, 1] < 0.0 and tri[2, 1] < 0.0)
            or (tri[0, 2] > 0.0 and tri[1, 2] > 0.0 and tri[2, 2] > 0.0)
            or (tri[0, 2] < 0.0 and tri[1, 2] < 0.0 and tri[2, 2] < 0.0)):
        return 0
    positive = negative = 0
    for i in range(3):
        j = (i + 1) % 3
        side = tri[i, 1] * tri[j, 2] - tri[i, 2] * tri[j, 1]  # the axis's side of edge i -> j
        if abs(side) <= 1e-12 * (abs(tri[i, 1]) + abs(tri[i, 2])) * (abs(tri[j, 1]) + abs(tri[j, 2])):
            return 2
        if side > 0.0:
            positive += 1
        else:
            negative += 1
    if positive == 3:
        return 1
    return -1 if negative == 3 else 0


@njit(cache=True, nogil=True)
def _clip(src, dst, n, bound, sense):
    """The corners of polygon src[:n] with sense * (t - bound) >= 0 kept (Sutherland-Hodgman), into dst -> count."""
    m = 0
    for i in range(n):
        j = (i + 1) % n
        si = sense * (src[i, 0] - bound)
        sj = sense * (src[j, 0] - bound)
        if si >= 0.0:
            for k in range(3):  # element by element: a row assignment costs numba seconds to compile
                dst[m, k] = src[i, k]
            m += 1
        if (si >= 0.0) != (sj >= 0.0):
            w = si / (si - sj)
            for k in range(3):
                dst[m, k] = src[i, k] + w * (src[j, k] - src[i, k])
            m += 1
    return m


@njit(cache=True, nogil=True)
def _distance_to_axis(poly, n):
    """Distance from the origin to the convex polygon poly[:n] seen along the axis (its (e1, e2) coordinates): 0 when
    the origin is inside it, else the distance to its nearest edge (a degenerate polygon is its edges)."""
    positive = negative = 0
    best = np.inf
    for i in range(n):
        j = (i + 1) % n
        ax, ay = poly[i, 1], poly[i, 2]
        dx, dy = poly[j, 1] - ax, poly[j, 2] - ay
        side = ax * dy - ay * dx  # the origin's side of edge i -> j, times its length
        if side > 0.0:
            positive += 1
        elif side < 0.0:
            negative += 1
        ll = dx * dx + dy * dy
        s = 0.0 if ll == 0.0 else min(1.0, max(0.0, -(ax * dx + ay * dy) / ll))
        px, py = ax + s * dx, ay + s * dy
        best = min(best, math.sqrt(px * px + py * py))
    if positive == n or negative == n:
        return 0.0
    return best
