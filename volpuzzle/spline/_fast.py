"""Compiled scattered-point evaluation of a tensor B-spline volume (numba), with homogeneous sums.

Chosen by measurement over the numpy path (see scripts/bench_spline.py): per point we find the three
spans, build the p+1 basis values (and first derivatives) per axis (NURBS Book A2.1/A2.2 and eq. 2.7), and
contract the local (p+1)^3 block of control points w-first so the inner loop runs over contiguous memory.
Points are processed in blocks under `prange`, so scratch arrays are allocated once per block.

`cp` is (n_u, n_v, n_w, d): d = 3 for polynomial volumes, 4 (homogeneous) for rational ones; the
caller divides by the last coordinate. Parameters are clamped to the domain; NaN gives NaN.
"""

import numpy as np
from numba import njit, prange

MAXP = 8  # degree <= 7
BLOCK = 512


@njit(cache=True, fastmath=False)
def _span(knots, p, n, last, t):
    # Largest i in [p, last] with knots[i] <= t (last = last non-empty span, precomputed).
    if t >= knots[last]:
        return last
    lo = p
    hi = last
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if t < knots[mid]:
            hi = mid
        else:
            lo = mid
    return lo


@njit(cache=True, fastmath=False)
def _basis(knots, p, span, t, N, dN, left, right, Nm, want_der):
    # NURBS Book A2.2; the degree p-1 values are kept for the derivative (eq. 2.7).
    N[0] = 1.0
    if p == 1:
        Nm[0] = 1.0
    for j in range(1, p + 1):
        left[j] = t - knots[span + 1 - j]
        right[j] = knots[span + j] - t
        saved = 0.0
        for r in range(j):
            den = right[r + 1] + left[j - r]
            temp = N[r] / den if den != 0.0 else 0.0
            N[r] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        N[j] = saved
        if j == p - 1:
            for r in range(p):
                Nm[r] = N[r]
    if want_der:
        for i in range(p + 1):
            d = 0.0
            if i >= 1:
                den = knots[span + i] - knots[span - p + i]
                if den != 0.0:
                    d += Nm[i - 1] / den
            if i <= p - 1:
                den = knots[span + i + 1] - knots[span - p + i + 1]
                if den != 0.0:
                    d -= Nm[i] / den
            dN[i] = p * d


@njit(cache=True, fastmath=False)
def _clamp(t, lo, hi):
    if t < lo:
        return lo
    if t > hi:
        return hi
    return t


@njit(cache=True, fastmath=False)
def _prepare(uvw, idx, ku, kv, kw, pu, pv, pw, lu, lv, lw, nu, nv, nw, Nu, Nv, Nw, dNu, dNv, dNw,
             left, right, Nm, want_der):
    # Returns the three spans, or -1 for a NaN parameter.
    u = uvw[idx, 0]
    v = uvw[idx, 1]
    w = uvw[idx, 2]
    if u != u or v != v or w != w:
        return -1, -1, -1
    u = _clamp(u, ku[pu], ku[nu])
    v = _clamp(v, kv[pv], kv[nv])
    w = _clamp(w, kw[pw], kw[nw])
    su = _span(ku, pu, nu, lu, u)
    sv = _span(kv, pv, nv, lv, v)
    sw = _span(kw, pw, nw, lw, w)
    _basis(ku, pu, su, u, Nu, dNu, left, right, Nm, want_der)
    _basis(kv, pv, sv, v, Nv, dNv, left, right, Nm, want_der)
    _basis(kw, pw, sw, w, Nw, dNw, left, right, Nm, want_der)
    return su, sv, sw


@njit(cache=True, fastmath=False)
def _block_values(uvw, start, stop, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out):
    # Scalar accumulators (x, y, z, h) keep everything in registers; h is skipped for d = 3.
    nu, nv, nw, D = cp.shape
    rat = D == 4
    Nu = np.empty(MAXP)
    Nv = np.empty(MAXP)
    Nw = np.empty(MAXP)
    left = np.empty(MAXP)
    right = np.empty(MAXP)
    Nm = np.empty(MAXP)
    for idx in range(start, stop):
        su, sv, sw = _prepare(uvw, idx, ku, kv, kw, pu, pv, pw, lu, lv, lw, nu, nv, nw, Nu, Nv, Nw,
                              Nu, Nv, Nw, left, right, Nm, False)
        if su < 0:
            for d in range(D):
                out[idx, d] = np.nan
            continue
        ax = 0.0
        ay = 0.0
        az = 0.0
        ah = 0.0
        for i in range(pu + 1):
            ii = su - pu + i
            bx = 0.0
            by = 0.0
            bz = 0.0
            bh = 0.0
            for j in range(pv + 1):
                jj = sv - pv + j
                cx = 0.0
                cy = 0.0
                cz = 0.0
                ch = 0.0
                for k in range(pw + 1):
                    kk = sw - pw + k
                    nk = Nw[k]
                    cx += nk * cp[ii, jj, kk, 0]
                    cy += nk * cp[ii, jj, kk, 1]
                    cz += nk * cp[ii, jj, kk, 2]
                    if rat:
                        ch += nk * cp[ii, jj, kk, 3]
                nj = Nv[j]
                bx += nj * cx
                by += nj * cy
                bz += nj * cz
                bh += nj * ch
            ni = Nu[i]
            ax += ni * bx
            ay += ni * by
            az += ni * bz
            ah += ni * bh
        out[idx, 0] = ax
        out[idx, 1] = ay
        out[idx, 2] = az
        if rat:
            out[idx, 3] = ah


@njit(cache=True, fastmath=False)
def _block_derivatives(uvw, start, stop, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der):
    # Same w-first contraction as _block_values, carrying value and the three partials in scalars.
    nu, nv, nw, D = cp.shape
    rat = D == 4
    Nu = np.empty(MAXP)
    Nv = np.empty(MAXP)
    Nw = np.empty(MAXP)
    dNu = np.empty(MAXP)
    dNv = np.empty(MAXP)
    dNw = np.empty(MAXP)
    left = np.empty(MAXP)
    right = np.empty(MAXP)
    Nm = np.empty(MAXP)
    for idx in range(start, stop):
        su, sv, sw = _prepare(uvw, idx, ku, kv, kw, pu, pv, pw, lu, lv, lw, nu, nv, nw, Nu, Nv, Nw,
                              dNu, dNv, dNw, left, right, Nm, True)
        if su < 0:
            for d in range(D):
                out[idx, d] = np.nan
                for e in range(3):
                    der[idx, d, e] = np.nan
            continue
        # a*: totals; suffix 0 value, u/v/w partials; x, y, z, h channels.
        ax0 = ay0 = az0 = ah0 = 0.0
        axu = ayu = azu = ahu = 0.0
        axv = ayv = azv = ahv = 0.0
        axw = ayw = azw = ahw = 0.0
        for i in range(pu + 1):
            ii = su - pu + i
            bx0 = by0 = bz0 = bh0 = 0.0
            bxv = byv = bzv = bhv = 0.0
            bxw = byw = bzw = bhw = 0.0
            for j in range(pv + 1):
                jj = sv - pv + j
                cx0 = cy0 = cz0 = ch0 = 0.0
                cxw = cyw = czw = chw = 0.0
                for k in range(pw + 1):
                    kk = sw - pw + k
                    nk = Nw[k]
                    dk = dNw[k]
                    x = cp[ii, jj, kk, 0]
                    y = cp[ii, jj, kk, 1]
                    z = cp[ii, jj, kk, 2]
                    cx0 += nk * x
                    cy0 += nk * y
                    cz0 += nk * z
                    cxw += dk * x
                    cyw += dk * y
                    czw += dk * z
                    if rat:
                        h = cp[ii, jj, kk, 3]
                        ch0 += nk * h
                        chw += dk * h
                nj = Nv[j]
                dj = dNv[j]
                bx0 += nj * cx0
                by0 += nj * cy0
                bz0 += nj * cz0
                bh0 += nj * ch0
                bxv += dj * cx0
                byv += dj * cy0
                bzv += dj * cz0
                bhv += dj * ch0
                bxw += nj * cxw
                byw += nj * cyw
                bzw += nj * czw
                bhw += nj * chw
            ni = Nu[i]
            di = dNu[i]
            ax0 += ni * bx0
            ay0 += ni * by0
            az0 += ni * bz0
            ah0 += ni * bh0
            axu += di * bx0
            ayu += di * by0
            azu += di * bz0
            ahu += di * bh0
            axv += ni * bxv
            ayv += ni * byv
            azv += ni * bzv
            ahv += ni * bhv
            axw += ni * bxw
            ayw += ni * byw
            azw += ni * bzw
            ahw += ni * bhw
        out[idx, 0] = ax0
        out[idx, 1] = ay0
        out[idx, 2] = az0
        der[idx, 0, 0] = axu
        der[idx, 1, 0] = ayu
        der[idx, 2, 0] = azu
        der[idx, 0, 1] = axv
        der[idx, 1, 1] = ayv
        der[idx, 2, 1] = azv
        der[idx, 0, 2] = axw
        der[idx, 1, 2] = ayw
        der[idx, 2, 2] = azw
        if rat:
            out[idx, 3] = ah0
            der[idx, 3, 0] = ahu
            der[idx, 3, 1] = ahv
            der[idx, 3, 2] = ahw


@njit(cache=True, fastmath=False, parallel=True)
def eval_parallel(uvw, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der, want_der):
    n = uvw.shape[0]
    nblocks = (n + BLOCK - 1) // BLOCK
    for b in prange(nblocks):
        stop = min(n, (b + 1) * BLOCK)
        if want_der:
            _block_derivatives(uvw, b * BLOCK, stop, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der)
        else:
            _block_values(uvw, b * BLOCK, stop, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out)


@njit(cache=True, fastmath=False)
def eval_serial(uvw, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der, want_der):
    if want_der:
        _block_derivatives(uvw, 0, uvw.shape[0], ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der)
    else:
        _block_values(uvw, 0, uvw.shape[0], ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out)
