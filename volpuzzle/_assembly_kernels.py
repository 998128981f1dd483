"""Compiled kernel of the assembly replay (numba), in its own module so that what only judges finished pieces
(`volpuzzle check`'s overlap test, which shares assembly's part extents) does not import numba (~0.5 s).

It keeps numpy's arithmetic (the same subtractions and divisions, compared the same way), so the sweep measures the
same samples the array code did, bit for bit.
"""

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def parts_meet(em, ef, s, ts, near):
    """Which offsets may let a moving solid meet a fixed one, by their parts' extents: em (pm, 2, k), ef (pf, 2, k)
    least and greatest projections of each part onto k directions, s (k,) those directions' cosines with the unit
    travel, ts (n,) offsets along it, near (n,) bool (the offsets still in question) -> (n,) bool, near and some pair
    of parts overlapping in projection along every direction.

    Along a direction e a pair overlaps only while  fixed least - moving greatest < t s_e < fixed greatest - moving
    least; across the travel (|s_e| <= 1e-12) a direction separates at every offset or at none. The pair may meet on
    the open interval (the greatest entry, the least exit); a pair is dropped as soon as it is empty, which the array
    code (_Scene._meeting_times before) computed over every direction of every pair: ~0.3 ms a pair, 18k pairs at
    1024 pieces."""
    n, k = ts.shape[0], s.shape[0]
    out = np.zeros(n, np.bool_)
    left = 0
    for t in range(n):
        left += near[t]
    for i in range(em.shape[0]):
        for j in range(ef.shape[0]):
            if left == 0:
                return out
            lo, hi = -np.inf, np.inf
            for e in range(k):
                a = ef[j, 0, e] - em[i, 1, e]
                b = ef[j, 1, e] - em[i, 0, e]
                if abs(s[e]) > 1e-12:
                    sa, sb = a / s[e], b / s[e]
                    t_lo, t_hi = min(sa, sb), max(sa, sb)
                elif a < 0 and b > 0:
                    t_lo, t_hi = -np.inf, np.inf
                else:
                    t_lo, t_hi = np.inf, -np.inf
                lo, hi = max(lo, t_lo), min(hi, t_hi)
                if not lo < hi:
                    break
            if lo < hi:
                for t in range(n):
                    if near[t] and not out[t] and lo < ts[t] < hi:
                        out[t] = True
                        left -= 1
    return out
