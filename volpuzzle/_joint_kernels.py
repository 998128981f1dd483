"""Compiled kernels of the joint stage (numba), in their own module so that what only reads joints (`volpuzzle
check`, the report's joint figures) does not import numba (~0.5 s).

Both keep numpy's arithmetic in numpy's order (a dot product x0 y0 + x1 y1 + x2 y2, the first of equal nearest
samples), so that they place the same joints the array code did, bit for bit.
"""

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def cylinders_apart(p0, p1, rp, q0, q1, rq, gap):
    """_Cylinders.apart_all on arrays: p0, p1 (k, 3), rp; q0, q1 (m, 3), rq (m,) -> (k,) bool. Compiled: placing the
    joints of 1024 pieces asks it ~12k times, each of ~169 points against a few joints, which numpy spent ~6 s on in
    call overhead alone (the serial joint stage). Dot products are written out (x0 y0 + x1 y1 + x2 y2, numpy's
    order), as one kernel compiles once on a new machine where helpers would compile once per argument type."""
    k, m = p0.shape[0], q0.shape[0]
    out = np.ones(k, np.bool_)
    for i in range(k):
        a0, a1, a2 = p0[i, 0], p0[i, 1], p0[i, 2]
        d0, d1, d2 = p1[i, 0] - a0, p1[i, 1] - a1, p1[i, 2] - a2
        a = d0 * d0 + d1 * d1 + d2 * d2
        la = np.sqrt(a)
        u0, u1, u2 = d0 / la, d1 / la, d2 / la
        e0 = u0 * a0 + u1 * a1 + u2 * a2
        e1 = u0 * p1[i, 0] + u1 * p1[i, 1] + u2 * p1[i, 2]
        p_lo, p_hi = min(e0, e1), max(e0, e1)
        for j in range(m):
            b0, b1, b2 = q0[j, 0], q0[j, 1], q0[j, 2]
            c0, c1, c2 = q1[j, 0] - b0, q1[j, 1] - b1, q1[j, 2] - b2
            e = c0 * c0 + c1 * c1 + c2 * c2
            r0, r1, r2 = a0 - b0, a1 - b1, a2 - b2
            f = r0 * c0 + r1 * c1 + r2 * c2
            cc = d0 * r0 + d1 * r1 + d2 * r2
            bb = d0 * c0 + d1 * c1 + d2 * c2
            # closest points of the two axes (segments), clamped to their ends
            denom = a * e - bb * bb
            s = min(max((bb * f - cc * e) / denom, 0.0), 1.0) if denom > 1e-12 * a * e else 0.0
            t = (bb * s + f) / e
            if t < 0:
                s = min(max(-cc / a, 0.0), 1.0)
            elif t > 1:
                s = min(max((bb - cc) / a, 0.0), 1.0)
            t = min(max(t, 0.0), 1.0)
            x0 = a0 + d0 * s - (b0 + c0 * t)
            x1 = a1 + d1 * s - (b1 + c1 * t)
            x2 = a2 + d2 * s - (b2 + c2 * t)
            if np.sqrt(x0 * x0 + x1 * x1 + x2 * x2) >= rp + rq[j] + gap - 1e-9:
                continue
            le = np.sqrt(e)
            v0, v1, v2 = c0 / le, c1 / le, c2 / le
            cs = min(max(u0 * v0 + u1 * v1 + u2 * v2, -1.0), 1.0)
            sn = np.sqrt(1.0 - cs * cs)
            # q beyond an end plane of p
            g0 = u0 * b0 + u1 * b1 + u2 * b2
            g1 = u0 * q1[j, 0] + u1 * q1[j, 1] + u2 * q1[j, 2]
            if min(g0, g1) - rq[j] * sn >= p_hi + gap - 1e-9 or max(g0, g1) + rq[j] * sn <= p_lo - gap + 1e-9:
                continue
            # p beyond an end plane of q
            h0 = a0 * v0 + a1 * v1 + a2 * v2
            h1 = p1[i, 0] * v0 + p1[i, 1] * v1 + p1[i, 2] * v2
            f0 = b0 * v0 + b1 * v1 + b2 * v2
            f1 = q1[j, 0] * v0 + q1[j, 1] * v1 + q1[j, 2] * v2
            if (min(h0, h1) - rp * sn >= max(f0, f1) + gap - 1e-9
                    or max(h0, h1) + rp * sn <= min(f0, f1) - gap + 1e-9):
                continue
            out[i] = False
            break
    return out


@njit(cache=True, nogil=True)
def face_distance(p, x, nrm, inner, use):
    """_Sides.distance over sampled faces: points p (n, 3); samples x (f, m, 3), their unit normals nrm (f, m, 3)
    (zero where collapsed) and whether each lies inside its face (f, m); the faces to measure, use (f,) -> (n,) mm to
    the nearest of them (inf if none): across the tangent plane of the nearest sample inside a face, straight to a
    sample on its rim. Compiled: placing the joints of 1024 pieces measures ~8k point sets, which numpy spent ~5 s on
    (the serial joint stage)."""
    n, f, m = p.shape[0], x.shape[0], x.shape[1]
    out = np.full(n, np.inf)
    for i in range(n):
        for g in range(f):
            if not use[g]:
                continue
            best, near = np.inf, 0
            for s in range(m):
                d0, d1, d2 = p[i, 0] - x[g, s, 0], p[i, 1] - x[g, s, 1], p[i, 2] - x[g, s, 2]
                dd = d0 * d0 + d1 * d1 + d2 * d2
                if dd < best:  # the first of equal ones, as argmin
                    best, near = dd, s
            a0, a1, a2 = nrm[g, near, 0], nrm[g, near, 1], nrm[g, near, 2]
            if inner[g, near] and (a0 != 0.0 or a1 != 0.0 or a2 != 0.0):
                d = abs((p[i, 0] - x[g, near, 0]) * a0 + (p[i, 1] - x[g, near, 1]) * a1
                        + (p[i, 2] - x[g, near, 2]) * a2)
            else:
                d = np.sqrt(best)
            out[i] = min(out[i], d)
    return out
