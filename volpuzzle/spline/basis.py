"""B-spline basis functions, vectorised over parameters (The NURBS Book, A2.1-A2.3)."""

import numpy as np


def find_span(knots, degree, t):
    """Knot span index of each parameter (NURBS Book A2.1), vectorised.

    knots (m,), t (n,) -> (n,) int, with t == last knot mapped to the last non-empty span.
    """
    knots = np.asarray(knots, dtype=float)
    t = np.asarray(t, dtype=float)
    span = np.searchsorted(knots, t, side="right") - 1
    return np.clip(span, degree, last_span(knots, degree))


def last_span(knots, degree):
    """Index of the last non-empty knot span of the domain (so t == end knot never lands in an empty span)."""
    knots = np.asarray(knots, dtype=float)
    n = len(knots) - degree - 1  # number of control points
    return int(np.searchsorted(knots, knots[n], side="left") - 1)


def basis_functions(knots, degree, t, span=None):
    """Non-zero basis functions N[span-p .. span] at t (NURBS Book A2.2). t (n,) -> (n, p+1)."""
    t = np.asarray(t, dtype=float)
    if span is None:
        span = find_span(knots, degree, t)
    return basis_derivatives(knots, degree, t, 0, span)[:, 0, :]


def basis_derivatives(knots, degree, t, order, span=None):
    """Basis functions and derivatives up to `order` (NURBS Book A2.3). t (n,) -> (n, order+1, p+1)."""
    knots = np.asarray(knots, dtype=float)
    t = np.atleast_1d(np.asarray(t, dtype=float))
    p = degree
    if span is None:
        span = find_span(knots, p, t)
    n = t.shape[0]
    ndu = np.zeros((n, p + 1, p + 1))
    ndu[:, 0, 0] = 1.0
    left = np.zeros((n, p + 1))
    right = np.zeros((n, p + 1))
    for j in range(1, p + 1):
        left[:, j] = t - knots[span + 1 - j]
        right[:, j] = knots[span + j] - t
        saved = np.zeros(n)
        for r in range(j):
            ndu[:, j, r] = right[:, r + 1] + left[:, j - r]
            denom = ndu[:, j, r]
            temp = np.divide(ndu[:, r, j - 1], denom, out=np.zeros(n), where=denom != 0)
            ndu[:, r, j] = saved + right[:, r + 1] * temp
            saved = left[:, j - r] * temp
        ndu[:, j, j] = saved
    ders = np.zeros((n, order + 1, p + 1))
    ders[:, 0, :] = ndu[:, :, p]
    if order == 0:
        return ders
    for r in range(p + 1):
        a = np.zeros((n, 2, p + 1))
        a[:, 0, 0] = 1.0
        s1, s2 = 0, 1
        for k in range(1, order + 1):
            d = np.zeros(n)
            rk, pk = r - k, p - k
            if r >= k:
                den = ndu[:, pk + 1, rk]
                a[:, s2, 0] = np.divide(a[:, s1, 0], den, out=np.zeros(n), where=den != 0)
                d = a[:, s2, 0] * ndu[:, rk, pk]
            j1 = 1 if rk >= -1 else -rk
            j2 = k - 1 if r - 1 <= pk else p - r
            for j in range(j1, j2 + 1):
                den = ndu[:, pk + 1, rk + j]
                a[:, s2, j] = np.divide(a[:, s1, j] - a[:, s1, j - 1], den, out=np.zeros(n), where=den != 0)
                d = d + a[:, s2, j] * ndu[:, rk + j, pk]
            if r <= pk:
                den = ndu[:, pk + 1, r]
                a[:, s2, k] = np.divide(-a[:, s1, k - 1], den, out=np.zeros(n), where=den != 0)
                d = d + a[:, s2, k] * ndu[:, r, pk]
            ders[:, k, r] = d
            s1, s2 = s2, s1
    fac = p
    for k in range(1, order + 1):
        ders[:, k, :] *= fac
        fac *= p - k
    return ders


def basis_matrix(knots, degree, t, order=0):
    """Dense basis matrices for a tensor grid: t (a,) -> (order+1, a, n) with [k, i, j] = N_j^(k)(t_i).

    Parameters are clamped to the domain. Dense is fine here: grids are contracted axis by axis, so the
    cost is a*n per axis, small next to the final a*b*c contraction.
    """
    knots = np.asarray(knots, dtype=float)
    p = int(degree)
    n = len(knots) - p - 1
    t = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), knots[p], knots[n])
    span = find_span(knots, p, t)
    ders = basis_derivatives(knots, p, t, order, span)  # (a, order+1, p+1)
    out = np.zeros((order + 1, t.shape[0], n))
    cols = span[:, None] - p + np.arange(p + 1)
    rows = np.broadcast_to(np.arange(t.shape[0])[:, None], cols.shape)
    for k in range(order + 1):
        out[k, rows, cols] = ders[:, k, :]
    return out
