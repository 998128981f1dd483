"""Compiled scattered-point evaluation of a tensor B-spline volume (numba), with homogeneous sums.

Chosen by measurement over the numpy path (see scripts/bench_spline.py): per point we find the three
spans, build the p+1 basis values (and first derivatives) per axis (NURBS Book A2.1/A2.2 and eq. 2.7), and
contract the local (p+1)^3 block of control points w-first so the inner loop runs over contiguous memory.
Points are processed in blocks under `prange`, so scratch arrays are allocated once per block.

`cp` is (n_u, n_v, n_w, d): d = 3 for polynomial volumes, 4 (homogeneous) for rational ones; the
caller divides by the last coordinate, and passes `mode`: an empty 1-d array for d = 3, 2-d for d = 4 (its
ndim is a compile-time constant, so each case gets its own specialisation: ~25% faster than a run-time
test). Parameters are clamped to the domain; NaN gives NaN.
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
def _block_values(uvw, start, stop, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, mode):
    # Scalar accumulators (x, y, z, h) keep everything in registers; h is skipped for d = 3.
    # cp may be padded with zeros along v and w (see padded_net); nu, nv, nw come from the knots.
    nu = ku.shape[0] - pu - 1
    nv = kv.shape[0] - pv - 1
    nw = kw.shape[0] - pw - 1
    D = cp.shape[3]
    rat = mode.ndim == 2  # a compile-time constant: one specialisation each for d = 3 and d = 4
    small = pv <= 3 and pw <= 3 and cp.shape[1] >= nv + 3 - pv and cp.shape[2] >= nw + 3 - pw
    Nu = np.empty(MAXP)
    Nv = np.empty(MAXP)
    Nw = np.empty(MAXP)
    left = np.empty(MAXP)
    right = np.empty(MAXP)
    Nm = np.empty(MAXP)
    for idx in range(start, stop):
        # NaN needs no test: it fails every comparison, so the span search stays in range and NaN propagates.
        u = _clamp(uvw[idx, 0], ku[pu], ku[nu])
        v = _clamp(uvw[idx, 1], kv[pv], kv[nv])
        w = _clamp(uvw[idx, 2], kw[pw], kw[nw])
        su = _span(ku, pu, nu, lu, u)
        sv = _span(kv, pv, nv, lv, v)
        sw = _span(kw, pw, nw, lw, w)
        _basis(ku, pu, su, u, Nu, Nu, left, right, Nm, False)
        _basis(kv, pv, sv, v, Nv, Nv, left, right, Nm, False)
        _basis(kw, pw, sw, w, Nw, Nw, left, right, Nm, False)
        ax = 0.0
        ay = 0.0
        az = 0.0
        ah = 0.0
        if small:
            # v and w loops of constant length 4 (basis zero-padded, net padded): LLVM unrolls them,
            # which measured ~1.5x faster than loops of run-time length.
            for t in range(pv + 1, 4):
                Nv[t] = 0.0
            for t in range(pw + 1, 4):
                Nw[t] = 0.0
            k0 = sw - pw
            n0 = Nw[0]
            n1 = Nw[1]
            n2 = Nw[2]
            n3 = Nw[3]
            for i in range(pu + 1):
                ii = su - pu + i
                bx = 0.0
                by = 0.0
                bz = 0.0
                bh = 0.0
                for j in range(4):
                    c = cp[ii, sv - pv + j]
                    cx = n0 * c[k0, 0] + n1 * c[k0 + 1, 0] + n2 * c[k0 + 2, 0] + n3 * c[k0 + 3, 0]
                    cy = n0 * c[k0, 1] + n1 * c[k0 + 1, 1] + n2 * c[k0 + 2, 1] + n3 * c[k0 + 3, 1]
                    cz = n0 * c[k0, 2] + n1 * c[k0 + 1, 2] + n2 * c[k0 + 2, 2] + n3 * c[k0 + 3, 2]
                    nj = Nv[j]
                    bx += nj * cx
                    by += nj * cy
                    bz += nj * cz
                    if rat:
                        ch = n0 * c[k0, 3] + n1 * c[k0 + 1, 3] + n2 * c[k0 + 2, 3] + n3 * c[k0 + 3, 3]
                        bh += nj * ch
                ni = Nu[i]
                ax += ni * bx
                ay += ni * by
                az += ni * bz
                ah += ni * bh
        else:
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
def _block_derivatives(uvw, start, stop, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der, mode):
    # Same w-first contraction as _block_values, carrying value and the three partials in scalars.
    nu = ku.shape[0] - pu - 1
    nv = kv.shape[0] - pv - 1
    nw = kw.shape[0] - pw - 1
    D = cp.shape[3]
    rat = mode.ndim == 2  # a compile-time constant: one specialisation each for d = 3 and d = 4
    small = pv <= 3 and pw <= 3 and cp.shape[1] >= nv + 3 - pv and cp.shape[2] >= nw + 3 - pw
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
        # NaN needs no test: it fails every comparison, so the span search stays in range and NaN propagates.
        u = _clamp(uvw[idx, 0], ku[pu], ku[nu])
        v = _clamp(uvw[idx, 1], kv[pv], kv[nv])
        w = _clamp(uvw[idx, 2], kw[pw], kw[nw])
        su = _span(ku, pu, nu, lu, u)
        sv = _span(kv, pv, nv, lv, v)
        sw = _span(kw, pw, nw, lw, w)
        _basis(ku, pu, su, u, Nu, dNu, left, right, Nm, True)
        _basis(kv, pv, sv, v, Nv, dNv, left, right, Nm, True)
        _basis(kw, pw, sw, w, Nw, dNw, left, right, Nm, True)
        # a*: totals; suffix 0 value, u/v/w partials; x, y, z, h channels.
        if small:
            for t in range(pv + 1, 4):
                Nv[t] = 0.0
                dNv[t] = 0.0
            for t in range(pw + 1, 4):
                Nw[t] = 0.0
                dNw[t] = 0.0
            ax0 = ay0 = az0 = ah0 = 0.0
            axu = ayu = azu = ahu = 0.0
            axv = ayv = azv = ahv = 0.0
            axw = ayw = azw = ahw = 0.0
            for i in range(pu + 1):
                ii = su - pu + i
                bx0 = by0 = bz0 = bh0 = 0.0
                bxv = byv = bzv = bhv = 0.0
                bxw = byw = bzw = bhw = 0.0
                for j in range(4):
                    jj = sv - pv + j
                    cx0 = cy0 = cz0 = ch0 = 0.0
                    cxw = cyw = czw = chw = 0.0
                    for k in range(4):
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
        else:
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
def eval_parallel(uvw, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der, want_der, mode):
    n = uvw.shape[0]
    nblocks = (n + BLOCK - 1) // BLOCK
    for b in prange(nblocks):
        stop = min(n, (b + 1) * BLOCK)
        if want_der:
            _block_derivatives(uvw, b * BLOCK, stop, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der, mode)
        else:
            _block_values(uvw, b * BLOCK, stop, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, mode)


@njit(cache=True, fastmath=False)
def eval_serial(uvw, ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der, want_der, mode):
    if want_der:
        _block_derivatives(uvw, 0, uvw.shape[0], ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, der, mode)
    else:
        _block_values(uvw, 0, uvw.shape[0], ku, kv, kw, pu, pv, pw, lu, lv, lw, cp, out, mode)


def padded_net(net, degrees):
    """net (n_u, n_v, n_w, d) padded with zero layers along v and w up to degree 3, so the kernels' unrolled
    loops of length 4 stay inside the array (the padded entries meet zero basis values)."""
    pv, pw = degrees[1], degrees[2]
    if pv > 3 or pw > 3:
        return net
    return np.ascontiguousarray(np.pad(net, ((0, 0), (0, 3 - pv), (0, 3 - pw), (0, 0))))
