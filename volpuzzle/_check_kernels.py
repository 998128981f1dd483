"""Compiled kernels of the checks (numba), in their own module: `volpuzzle check` of a small puzzle measures its few
joints and face gaps with the engine alone rather than start numba (~0.5 s) for them.

cylinder_side: a pin's test cylinder that no triangle of the piece comes near lies wholly inside the piece or wholly
outside it, and one ray tells which. So most tests need no Boolean: the engine measures only the cylinders that the
surface crosses or reaches (check._joint_measures).

surface_gap: the least distance between two pieces' surfaces (check._face_gaps), exact, in ~half the engine's time
(whose own min_gap was seen ~2e-7 mm off between nearly parallel edges).
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
    the origin is inside it, else the distance to its nearest edge (a degenerate polygon is its edges).
    Inside: on one side of every edge whose side is above its rounding. Clipping a corner that lies on the slab's
    bound (or within rounding of it) leaves an edge of no length, or of a length whose side is noise; counted, it
    called an origin inside the polygon outside, and then a surface crossing the cylinder was passed over. Leaving
    such an edge out can only call inside an origin that is within rounding of the polygon: 0, the engine's case."""
    positive = negative = counted = 0
    best = np.inf
    for i in range(n):
        j = (i + 1) % n
        ax, ay = poly[i, 1], poly[i, 2]
        dx, dy = poly[j, 1] - ax, poly[j, 2] - ay
        side = ax * dy - ay * dx  # the origin's side of edge i -> j, times its length
        if abs(side) > 1e-12 * (abs(ax) + abs(ay)) * (abs(dx) + abs(dy)):
            counted += 1
            if side > 0.0:
                positive += 1
            else:
                negative += 1
        ll = dx * dx + dy * dy
        s = 0.0 if ll == 0.0 else min(1.0, max(0.0, -(ax * dx + ay * dy) / ll))
        px, py = ax + s * dx, ay + s * dy
        best = min(best, math.sqrt(px * px + py * py))
    if counted > 0 and (positive == counted or negative == counted):
        return 0.0
    return best


# ---------------------------------------------------------------------------------------------------------------------
# The least distance between two triangle surfaces


@njit(cache=True, nogil=True)
def surface_gap(va, fa, vb, fb, shift, search, touch):
    """Least distance between the surfaces of two triangle meshes (va (n, 3), fa (m, 3); vb, fb), the first moved by
    shift (3,) mm: the exact distance of the closest pair of triangles, when it is below `search`, else `search`;
    0.0 once a pair comes within `touch` (crossing or touching).

    The first mesh's triangles near the second's box look up the second's in a grid of cells; a pair is kept with a
    lower bound on its distance (_beyond, _across, the boxes' gap) below the search, and the pairs are measured in
    the order of their bounds until a bound reaches the least distance found. Two triangles that do not cross lie
    as far apart as the nearest of their corners to the other triangle and of their edges to the other's edges
    (Ericson, Real-Time Collision Detection, 5.1.5 and 5.1.9); whether an edge crosses the other triangle is asked
    first."""
    ta = _boxes(va, fa, shift)
    zero = np.zeros(3)
    tb = _boxes(vb, fb, zero)
    # the second mesh's box, and the first's, each widened by the search: a triangle outside the other's is too far
    ga = _extent(tb, search)
    gb = _extent(ta, search)
    near_a = _inside(ta, ga)
    near_b = _inside(tb, gb)
    if near_a.shape[0] == 0 or near_b.shape[0] == 0:
        return search
    grid = _grid(tb, near_b, search)
    # every pair whose boxes come within the search, with a lower bound on its distance: the boxes' gap, or all
    # corners of one triangle beyond the other's plane. Measured exactly in the order of that bound, a pair whose
    # bound is no less than the least distance found so far is passed over: neighbours' cut faces, one
    # triangulation set apart by the face clearance, leave a few pairs to measure out of thousands
    seen = np.full(fb.shape[0], -1, np.int64)
    near, gaps = np.empty(fb.shape[0], np.int64), np.empty(fb.shape[0])
    plane_b = _planes(vb, fb, near_b, zero)
    plane_a = _planes(va, fa, near_a, shift)
    found = np.empty((16 * near_a.shape[0] + 16, 3))  # (a, b, bound) of each pair kept
    n = 0
    p = np.empty((3, 3))
    q = np.empty((3, 3))
    for a in near_a:
        _corners(va, fa, a, shift, p)
        for i in range(_near(ta, a, search, tb, grid, seen, a, near, gaps)):
            b = near[i]
            _corners(vb, fb, b, zero, q)
            low = max(gaps[i], _beyond(plane_a, a, q), _beyond(plane_b, b, p), _across(p, q))
            if low >= search:
                continue
            if n == found.shape[0]:
                found = _grown(found)
            found[n, 0], found[n, 1], found[n, 2] = a, b, low
            n += 1
    best = search
    for k in _by_bound(found, n):
        if found[k, 2] >= best:
            break
        _corners(va, fa, int(found[k, 0]), shift, p)
        _corners(vb, fb, int(found[k, 1]), zero, q)
        d = _triangles_apart(p, q, touch)
        if d < best:
            best = d
            if best <= touch:
                return 0.0
    return best


@njit(cache=True, nogil=True)
def surfaces_meet(va, fa, vb, fb, shifts, touch):
    """Whether the surface of the first mesh (va (n, 3), fa (m, 3)), moved by each of shifts (k, 3) mm, comes within
    `touch` of the second's -> (k,) bool: False is a proof that no triangle of the one comes that near any of the
    other. The second mesh's triangles near the first's swept box are put in a grid once for every shift."""
    k = shifts.shape[0]
    meet = np.zeros(k, np.bool_)
    zero = np.zeros(3)
    ta = _boxes(va, fa, zero)
    tb = _boxes(vb, fb, zero)
    ga = _extent(ta, touch)
    for c in range(3):  # the first mesh's box swept over every shift
        lo_s, hi_s = np.inf, -np.inf
        for j in range(k):
            lo_s = min(lo_s, shifts[j, c])
            hi_s = max(hi_s, shifts[j, c])
        ga[c] += lo_s
        ga[3 + c] += hi_s
    near_b = _inside(tb, ga)
    if near_b.shape[0] == 0:
        return meet
    gb = _extent(tb, touch)
    grid = _grid(tb, near_b, touch)
    plane_a = _planes(va, fa, np.arange(fa.shape[0]), zero)
    plane_b = _planes(vb, fb, near_b, zero)
    seen = np.full(fb.shape[0], -1, np.int64)
    near, gaps = np.empty(fb.shape[0], np.int64), np.empty(fb.shape[0])
    moved = np.empty((fa.shape[0], 6))
    p = np.empty((3, 3))
    q = np.empty((3, 3))
    back = np.empty((3, 3))
    stamp = 0
    for j in range(k):
        shift = shifts[j]
        unshift = -shift
        for t in range(fa.shape[0]):
            for c in range(3):
                moved[t, c] = ta[t, c] + shift[c]
                moved[t, 3 + c] = ta[t, 3 + c] + shift[c]
        for a in range(fa.shape[0]):
            if not _meets_box(moved, a, gb):
                continue
            stamp += 1
            _corners(va, fa, a, shift, p)
            for i in range(_near(moved, a, touch, tb, grid, seen, stamp, near, gaps)):
                b = near[i]
                _corners(vb, fb, b, zero, q)
                # the first triangle's plane moved: the second's corners moved back against it
                _corners(vb, fb, b, unshift, back)
                if max(_beyond(plane_a, a, back), _beyond(plane_b, b, p), _across(p, q)) >= touch:
                    continue
                if _triangles_apart(p, q, touch) <= touch:
                    meet[j] = True
                    break
            if meet[j]:
                break
    return meet


@njit(cache=True, nogil=True)
def _near(boxes, a, limit, tb, grid, seen, stamp, near, gaps):
    """The second mesh's triangles (boxes tb (m, 6), in `grid` of _grid) whose boxes come within `limit` of box a of
    boxes, each once (seen (m,) marked with stamp), into near[:n] with their boxes' gaps in gaps[:n] -> n."""
    lo, size, dims, start, items = grid
    i0, j0, k0, i1, j1, k1 = _cells(boxes, a, 0.0, lo, size, dims)
    n = 0
    for x in range(i0, i1 + 1):
        for y in range(j0, j1 + 1):
            for z in range(k0, k1 + 1):
                cell = (x * dims[1] + y) * dims[2] + z
                for r in range(start[cell], start[cell + 1]):
                    b = items[r]
                    if seen[b] == stamp:
                        continue
                    seen[b] = stamp
                    gap2 = 0.0
                    for c in range(3):
                        g = max(tb[b, c] - boxes[a, 3 + c], boxes[a, c] - tb[b, 3 + c], 0.0)
                        gap2 += g * g
                    if gap2 < limit * limit:
                        near[n], gaps[n] = b, math.sqrt(gap2)
                        n += 1
    return n


@njit(cache=True, nogil=True)
def _meets_box(boxes, a, box):
    """Whether box a of boxes meets box (6,)."""
    for c in range(3):
        if boxes[a, c] > box[3 + c] or boxes[a, 3 + c] < box[c]:
            return False
    return True


@njit(cache=True, nogil=True)
def _grid(tb, near, search):
    """A grid of cells over the triangles `near` (boxes tb, widened by search), about one triangle a cell -> (least
    corner (3,), cell size, cells along each axis (3,), start (cells + 1,), items): the triangles of cell c are
    items[start[c]:start[c + 1]]."""
    lo = np.empty(3)
    hi = np.empty(3)
    size = 0.0
    for c in range(3):
        lo[c] = np.inf
        hi[c] = -np.inf
    for i in near:
        for c in range(3):
            lo[c] = min(lo[c], tb[i, c] - search)
            hi[c] = max(hi[c], tb[i, 3 + c] + search)
            size += tb[i, 3 + c] - tb[i, c]
    size = max(size / (3.0 * near.shape[0]), search, 1e-9)
    dims = np.empty(3, np.int64)
    while True:
        total = 1
        for c in range(3):
            dims[c] = max(1, min(int((hi[c] - lo[c]) / size) + 1, 1 << 20))
            total *= dims[c]
        if total <= 8 * near.shape[0] + 64:
            break
        size *= 1.5
    start = np.zeros(total + 1, np.int64)
    for i in near:
        i0, j0, k0, i1, j1, k1 = _cells(tb, i, search, lo, size, dims)
        for x in range(i0, i1 + 1):
            for y in range(j0, j1 + 1):
                for z in range(k0, k1 + 1):
                    start[(x * dims[1] + y) * dims[2] + z + 1] += 1
    for c in range(total):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    items = np.empty(start[total], np.int64)
    for i in near:
        i0, j0, k0, i1, j1, k1 = _cells(tb, i, search, lo, size, dims)
        for x in range(i0, i1 + 1):
            for y in range(j0, j1 + 1):
                for z in range(k0, k1 + 1):
                    cell = (x * dims[1] + y) * dims[2] + z
                    items[fill[cell]] = i
                    fill[cell] += 1
    return lo, size, dims, start, items


@njit(cache=True, nogil=True)
def _by_bound(found, n):
    """Indices 0 .. n - 1 of found's rows in increasing order of their bound (column 2): a shell sort, which numba
    compiles in a fraction of the time its own argsort takes."""
    order = np.arange(n)
    gap = 1
    while gap < n // 3:
        gap = 3 * gap + 1
    while gap > 0:
        for i in range(gap, n):
            k = order[i]
            j = i
            while j >= gap and found[order[j - gap], 2] > found[k, 2]:
                order[j] = order[j - gap]
                j -= gap
            order[j] = k
        gap //= 3
    return order


@njit(cache=True, nogil=True)
def _corners(v, f, t, shift, out):
    """The corners of triangle t, moved by shift, into out (3, 3)."""
    for c in range(3):
        for k in range(3):
            out[c, k] = v[f[t, c], k] + shift[k]


@njit(cache=True, nogil=True)
def _grown(rows):
    """rows (m, 3) copied into an array of twice as many rows, element by element (a slice copy of a generic
    array took numba seconds to compile)."""
    out = np.empty((2 * rows.shape[0], 3))
    for i in range(rows.shape[0]):
        for c in range(3):
            out[i, c] = rows[i, c]
    return out


@njit(cache=True, nogil=True)
def _boxes(v, f, shift):
    """(m, 6) least and greatest corner of each triangle, moved by shift."""
    out = np.empty((f.shape[0], 6))
    for t in range(f.shape[0]):
        for c in range(3):
            a = v[f[t, 0], c] + shift[c]
            b = v[f[t, 1], c] + shift[c]
            d = v[f[t, 2], c] + shift[c]
            out[t, c] = min(a, b, d)
            out[t, 3 + c] = max(a, b, d)
    return out


@njit(cache=True, nogil=True)
def _planes(v, f, which, shift):
    """(m, 4) unit normal and offset of the plane of each triangle listed in `which` (the others left 0), moved by
    shift; all 0 for a triangle without area."""
    out = np.zeros((f.shape[0], 4))
    for t in which:
        a, b, c = f[t, 0], f[t, 1], f[t, 2]
        e1x, e1y, e1z = v[b, 0] - v[a, 0], v[b, 1] - v[a, 1], v[b, 2] - v[a, 2]
        e2x, e2y, e2z = v[c, 0] - v[a, 0], v[c, 1] - v[a, 1], v[c, 2] - v[a, 2]
        nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        size = math.sqrt(nx * nx + ny * ny + nz * nz)
        if size > 0.0:
            nx, ny, nz = nx / size, ny / size, nz / size
            out[t, 0], out[t, 1], out[t, 2] = nx, ny, nz
            out[t, 3] = nx * (v[a, 0] + shift[0]) + ny * (v[a, 1] + shift[1]) + nz * (v[a, 2] + shift[2])
    return out


@njit(cache=True, nogil=True)
def _beyond(planes, t, s):
    """How far every corner of triangle s (3, 3) lies beyond the plane of triangle t, all on one side (the least of
    them); 0 when they straddle it or t has no area."""
    nx, ny, nz, d = planes[t, 0], planes[t, 1], planes[t, 2], planes[t, 3]
    if nx == 0.0 and ny == 0.0 and nz == 0.0:
        return 0.0
    d0 = nx * s[0, 0] + ny * s[0, 1] + nz * s[0, 2] - d
    d1 = nx * s[1, 0] + ny * s[1, 1] + nz * s[1, 2] - d
    d2 = nx * s[2, 0] + ny * s[2, 1] + nz * s[2, 2] - d
    if d0 > 0.0 and d1 > 0.0 and d2 > 0.0:
        return min(d0, d1, d2)
    if d0 < 0.0 and d1 < 0.0 and d2 < 0.0:
        return -max(d0, d1, d2)
    return 0.0


@njit(cache=True, nogil=True)
def _across(p, q):
    """How far apart triangles p and q (3, 3) lie along the line through their centroids (0 when they overlap along
    it): a lower bound on their distance, which oblique neighbours' planes do not give."""
    ux = q[0, 0] + q[1, 0] + q[2, 0] - p[0, 0] - p[1, 0] - p[2, 0]
    uy = q[0, 1] + q[1, 1] + q[2, 1] - p[0, 1] - p[1, 1] - p[2, 1]
    uz = q[0, 2] + q[1, 2] + q[2, 2] - p[0, 2] - p[1, 2] - p[2, 2]
    size = math.sqrt(ux * ux + uy * uy + uz * uz)
    if not size > 0.0:
        return 0.0
    ux, uy, uz = ux / size, uy / size, uz / size
    hi = max(p[0, 0] * ux + p[0, 1] * uy + p[0, 2] * uz, p[1, 0] * ux + p[1, 1] * uy + p[1, 2] * uz,
             p[2, 0] * ux + p[2, 1] * uy + p[2, 2] * uz)
    lo = min(q[0, 0] * ux + q[0, 1] * uy + q[0, 2] * uz, q[1, 0] * ux + q[1, 1] * uy + q[1, 2] * uz,
             q[2, 0] * ux + q[2, 1] * uy + q[2, 2] * uz)
    return max(lo - hi, 0.0)


@njit(cache=True, nogil=True)
def _extent(boxes, pad):
    """The box (6,) of all boxes, widened by pad."""
    out = np.empty(6)
    for c in range(3):
        out[c] = np.inf
        out[3 + c] = -np.inf
    for t in range(boxes.shape[0]):
        for c in range(3):
            out[c] = min(out[c], boxes[t, c] - pad)
            out[3 + c] = max(out[3 + c], boxes[t, 3 + c] + pad)
    return out


@njit(cache=True, nogil=True)
def _inside(boxes, box):
    """Indices of the boxes that meet box (6,)."""
    keep = np.empty(boxes.shape[0], np.int64)
    n = 0
    for t in range(boxes.shape[0]):
        ok = True
        for c in range(3):
            if boxes[t, c] > box[3 + c] or boxes[t, 3 + c] < box[c]:
                ok = False
        if ok:
            keep[n] = t
            n += 1
    return keep[:n]


@njit(cache=True, nogil=True)
def _cell(x, lo, size, n):
    """The grid index of coordinate x along one axis, clamped to 0 .. n - 1."""
    return min(max(int(math.floor((x - lo) / size)), 0), n - 1)


@njit(cache=True, nogil=True)
def _cells(boxes, t, pad, lo, size, dims):
    """The range of grid cells (i0, j0, k0, i1, j1, k1) that box t widened by pad covers, clamped to the grid."""
    return (_cell(boxes[t, 0] - pad, lo[0], size, dims[0]), _cell(boxes[t, 1] - pad, lo[1], size, dims[1]),
            _cell(boxes[t, 2] - pad, lo[2], size, dims[2]), _cell(boxes[t, 3] + pad, lo[0], size, dims[0]),
            _cell(boxes[t, 4] + pad, lo[1], size, dims[1]), _cell(boxes[t, 5] + pad, lo[2], size, dims[2]))


@njit(cache=True, nogil=True)
def _triangles_apart(p, q, touch):
    """Distance between triangles p and q (3, 3); 0.0 when an edge of one crosses the other."""
    for i in range(3):
        j = (i + 1) % 3
        if _edge_crosses(p, i, j, q) or _edge_crosses(q, i, j, p):
            return 0.0
    best = np.inf
    for i in range(3):
        best = min(best, _point_triangle2(p, i, q), _point_triangle2(q, i, p))
        for j in range(3):
            best = min(best, _segments2(p, i, (i + 1) % 3, q, j, (j + 1) % 3))
        if best <= touch * touch:
            return 0.0
    return math.sqrt(best)


@njit(cache=True, nogil=True)
def _edge_crosses(s, i, j, t):
    """Whether the edge s[i]-s[j] passes through the inside of triangle t (3, 3), its ends strictly on either side
    of the plane (an edge that only grazes it comes near an edge or a corner of t, which the distances find)."""
    e1x, e1y, e1z = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    e2x, e2y, e2z = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
    da = nx * (s[i, 0] - t[0, 0]) + ny * (s[i, 1] - t[0, 1]) + nz * (s[i, 2] - t[0, 2])
    db = nx * (s[j, 0] - t[0, 0]) + ny * (s[j, 1] - t[0, 1]) + nz * (s[j, 2] - t[0, 2])
    if (da > 0.0 and db > 0.0) or (da < 0.0 and db < 0.0) or da == db:
        return False
    w = da / (da - db)  # where the edge meets the plane
    x = s[i, 0] + w * (s[j, 0] - s[i, 0])
    y = s[i, 1] + w * (s[j, 1] - s[i, 1])
    z = s[i, 2] + w * (s[j, 2] - s[i, 2])
    for a in range(3):  # inside when on the inner side of all three edges
        b = (a + 1) % 3
        ux, uy, uz = t[b, 0] - t[a, 0], t[b, 1] - t[a, 1], t[b, 2] - t[a, 2]
        vx, vy, vz = x - t[a, 0], y - t[a, 1], z - t[a, 2]
        if (uy * vz - uz * vy) * nx + (uz * vx - ux * vz) * ny + (ux * vy - uy * vx) * nz <= 0.0:
            return False
    return True


@njit(cache=True, nogil=True)
def _point_triangle2(s, i, t):
    """Squared distance from corner s[i] to triangle t (3, 3) (Ericson 5.1.5); a triangle without area is its
    edges."""
    px, py, pz = s[i, 0], s[i, 1], s[i, 2]
    abx, aby, abz = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    acx, acy, acz = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    apx, apy, apz = px - t[0, 0], py - t[0, 1], pz - t[0, 2]
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return apx * apx + apy * apy + apz * apz
    bpx, bpy, bpz = px - t[1, 0], py - t[1, 1], pz - t[1, 2]
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bpx * bpx + bpy * bpy + bpz * bpz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        rx, ry, rz = apx - v * abx, apy - v * aby, apz - v * abz
        return rx * rx + ry * ry + rz * rz
    cpx, cpy, cpz = px - t[2, 0], py - t[2, 1], pz - t[2, 2]
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cpx * cpx + cpy * cpy + cpz * cpz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        rx, ry, rz = apx - w * acx, apy - w * acy, apz - w * acz
        return rx * rx + ry * ry + rz * rz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        rx = bpx - w * (t[2, 0] - t[1, 0])
        ry = bpy - w * (t[2, 1] - t[1, 1])
        rz = bpz - w * (t[2, 2] - t[1, 2])
        return rx * rx + ry * ry + rz * rz
    total = va + vb + vc
    if not total > 0.0:  # no area: the nearest of its edges
        return min(_point_segment2(px, py, pz, t, 0, 1), _point_segment2(px, py, pz, t, 1, 2),
                   _point_segment2(px, py, pz, t, 2, 0))
    v, w = vb / total, vc / total
    rx, ry, rz = apx - v * abx - w * acx, apy - v * aby - w * acy, apz - v * abz - w * acz
    return rx * rx + ry * ry + rz * rz


@njit(cache=True, nogil=True)
def _point_segment2(px, py, pz, t, i, j):
    """Squared distance from a point to the segment t[i]-t[j]."""
    dx, dy, dz = t[j, 0] - t[i, 0], t[j, 1] - t[i, 1], t[j, 2] - t[i, 2]
    rx, ry, rz = px - t[i, 0], py - t[i, 1], pz - t[i, 2]
    ll = dx * dx + dy * dy + dz * dz
    s = 0.0 if not ll > 0.0 else min(max((rx * dx + ry * dy + rz * dz) / ll, 0.0), 1.0)
    rx, ry, rz = rx - s * dx, ry - s * dy, rz - s * dz
    return rx * rx + ry * ry + rz * rz


@njit(cache=True, nogil=True)
def _segments2(u, i0, i1, w, j0, j1):
    """Squared distance between the segments u[i0]-u[i1] and w[j0]-w[j1] (Ericson 5.1.9)."""
    d1x, d1y, d1z = u[i1, 0] - u[i0, 0], u[i1, 1] - u[i0, 1], u[i1, 2] - u[i0, 2]
    d2x, d2y, d2z = w[j1, 0] - w[j0, 0], w[j1, 1] - w[j0, 1], w[j1, 2] - w[j0, 2]
    rx, ry, rz = u[i0, 0] - w[j0, 0], u[i0, 1] - w[j0, 1], u[i0, 2] - w[j0, 2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    s = t = 0.0
    if a <= 0.0 and e <= 0.0:
        pass
    elif a <= 0.0:
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if e <= 0.0:
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            denom = a * e - b * b
            s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > 0.0 else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                s, t = min(max(-c / a, 0.0), 1.0), 0.0
            elif t > 1.0:
                s, t = min(max((b - c) / a, 0.0), 1.0), 1.0
    x, y, z = rx + s * d1x - t * d2x, ry + s * d1y - t * d2y, rz + s * d1z - t * d2z
    return x * x + y * y + z * z
