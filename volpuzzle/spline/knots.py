"""Knot vectors: uniform ones, Greville abscissae, and operations on homogeneous control nets (insertion, Bezier
extraction, sub-boxes).

All functions work along one `axis` of an array of homogeneous points (..., 4) so that a rational
volume is refined exactly (The NURBS Book, section 5.2: insert in homogeneous space, project later).
"""

import numpy as np

from ..errors import ModelError
from ..grid import AXES


def uniform_knots(n, lo=0.0, hi=1.0, degree=3):
    """Clamped uniform knot vector (n + degree + 1,) on [lo, hi] for n control points."""
    inner = np.linspace(lo, hi, n - degree + 1)
    return np.concatenate([np.full(degree, lo), inner, np.full(degree, hi)])


def greville(knots, degree=3):
    """Greville abscissae (n,): knot averages that reproduce the identity (NURBS Book, section 9.2.3)."""
    k = np.asarray(knots, dtype=float)
    n = len(k) - degree - 1
    return np.array([k[i + 1:i + degree + 1].mean() for i in range(n)])


def multiplicity(knots, t):
    """How many times t occurs in knots (exact comparison: knots are data, not results of arithmetic)."""
    knots = np.asarray(knots, dtype=float)
    return int(np.count_nonzero(knots == t))


def breaks(knots, degree):
    """Distinct knots of the domain [k_p, k_n], sorted: the element boundaries along one axis."""
    knots = np.asarray(knots, dtype=float)
    n = len(knots) - degree - 1
    return np.unique(knots[degree:n + 1])


def insert_knot(knots, degree, hpoints, t, times=1, axis=0):
    """Boehm's algorithm (NURBS Book A5.1) along `axis` of hpoints (..., n, ..., d).

    Returns (new_knots (m + times,), new_hpoints with n + times along axis). t must lie in the domain
    [knots[p], knots[n]) (its start too, for clamping a floating knot vector),
    and its multiplicity after insertion may not exceed the degree.
    """
    knots = np.asarray(knots, dtype=float)
    p = int(degree)
    times = int(times)
    P = np.moveaxis(np.asarray(hpoints, dtype=float), axis, 0)
    n = P.shape[0]
    lo, hi = knots[p], knots[n]
    if times < 0:
        raise ModelError(f"insert_knot: times must be >= 0, got {times}")
    # t == lo is allowed: clamping a floating knot vector inserts at the start of its domain.
    if not (lo <= t < hi):
        raise ModelError(f"insert_knot: parameter {t!r} along {AXES[axis] if axis < 3 else axis} is not inside "
                         f"the domain [{lo:g}, {hi:g})")
    s = multiplicity(knots, t)
    if s + times > p:
        raise ModelError(f"insert_knot: inserting {t:g} {times} time(s) would give multiplicity {s + times}, "
                         f"more than the degree {p}; at most {p - s} more insertion(s) fit")
    if times == 0:
        return knots.copy(), np.moveaxis(P.copy(), 0, axis)
    r = times
    k = int(np.searchsorted(knots, t, side="right") - 1)  # span with knots[k] <= t < knots[k+1]
    new_knots = np.concatenate([knots[:k + 1], np.full(r, float(t)), knots[k + 1:]])
    Q = np.empty((n + r,) + P.shape[1:])
    Q[:k - p + 1] = P[:k - p + 1]
    Q[k - s + r:] = P[k - s:]
    R = P[k - p:k - s + 1].copy()
    L = k - p + 1
    for j in range(1, r + 1):
        L = k - p + j
        for i in range(p - j - s + 1):
            alpha = (t - knots[L + i]) / (knots[i + k + 1] - knots[L + i])
            R[i] = alpha * R[i + 1] + (1.0 - alpha) * R[i]
        Q[L] = R[0]
        Q[k + r - j - s] = R[p - j - s]
    for i in range(L + 1, k - s):
        Q[i] = R[i - L]
    return new_knots, np.moveaxis(Q, 0, axis)


def refine_to_multiplicity(knots, degree, hpoints, values, target, axis=0):
    """Insert every value in `values` (inside the domain) until its multiplicity is at least `target`."""
    knots = np.asarray(knots, dtype=float)
    p = int(degree)
    n = np.asarray(hpoints).shape[axis]
    lo, hi = knots[p], knots[n]
    for t in sorted(set(float(x) for x in values)):
        if not (lo < t < hi):
            continue
        need = target - multiplicity(knots, t)
        if need > 0:
            knots, hpoints = insert_knot(knots, p, hpoints, t, need, axis)
    return knots, hpoints


def bezier_extract_axis(knots, degree, hpoints, axis=0):
    """Split along one axis into Bezier segments (every interior knot raised to multiplicity p).

    Returns (breaks (E+1,), segments) with segments of shape (E, p+1) inserted at `axis`, i.e. the axis of
    length n becomes two axes (E, p+1).
    """
    knots = np.asarray(knots, dtype=float)
    p = int(degree)
    br = breaks(knots, p)
    knots, hp = refine_to_multiplicity(knots, p, hpoints, br[1:-1], p, axis)
    hp = np.moveaxis(hp, axis, 0)
    E = len(br) - 1
    # The refined net has p*E + 1 points; segment e uses points e*p .. e*p + p (shared ends).
    assert hp.shape[0] == p * E + 1, (hp.shape, p, E)
    idx = np.arange(E)[:, None] * p + np.arange(p + 1)[None, :]
    seg = hp[idx]  # (E, p+1, ...)
    return br, np.moveaxis(np.moveaxis(seg, 1, axis + 1), 0, axis)


def sub_range(knots, degree, hpoints, lo, hi, axis=0):
    """Knots and control points of the same spline restricted to [lo, hi] along axis (clamped result)."""
    knots = np.asarray(knots, dtype=float)
    p = int(degree)
    knots, hp = refine_to_multiplicity(knots, p, hpoints, [lo, hi], p, axis)
    i0 = int(np.searchsorted(knots, lo, side="right")) - 1 - p
    j1 = int(np.searchsorted(knots, hi, side="left"))
    sub_knots = knots[i0:j1 + p + 1].copy()
    sub_knots[:p + 1] = lo
    sub_knots[-p - 1:] = hi
    hp = np.take(hp, np.arange(i0, j1), axis=axis)
    return sub_knots, hp
