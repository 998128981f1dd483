"""Compiled scattered-point evaluation of a tensor B-spline volume (numba), with homogeneous sums.

Chosen by measurement over the numpy path (scripts/bench_spline.py: ~30-60x). Per point and axis: the Bezier
element (a branch-free count over few breaks, else a binary search), then the p+1 non-zero basis functions from
that element's extraction matrix applied to the Bernstein values (N_i = sum_m ext[e, i, m] B_m(s); NURBS Book 5.3
/ Borden et al. 2011) -- no divisions, ~1.3x faster than A2.2 here. The local (p+1)^3 block of control points is
contracted w-first; for degree <= 3 in v and w those loops run with constant length 4 over a zero-padded net, so
LLVM unrolls them (~1.5x); higher degrees have their own (_high) kernels, so that the common ones compile less code.
Tricubic values have their own kernel with every basis value in a register (~1.5x more). Each call fills one range
of the points; scratch is per call.

`cp` is (n_u, n_v, n_w (+pad), d): d = 3 for polynomial volumes, 4 (homogeneous) for rational ones; the
caller divides by the last coordinate, and passes `mode`: an empty 1-d array for d = 3, 2-d for d = 4 (its
ndim is a compile-time constant, so each case gets its own specialisation: ~25% faster than a run-time
test). The kernels release the GIL (nogil), so callers may run them from several threads.
Parameters are clamped to the domain; NaN propagates (it fails every comparison, so the search
stays in range).
"""

from typing import NamedTuple

import numpy as np
from numba import njit

MAXP = 8  # degree <= 7
# Fused multiply-add only: ~1.5x on the cubic kernel, and no reordering of sums (full fastmath was slower). Results
# can differ from the unfused ones in the last bit, but they are the same for the same input on one machine.
_FM = {"contract"}


class AxisTables(NamedTuple):
    """One axis's tables for the kernels (the kernels take them as four positional arrays, in this order): breaks
    (E+1,) the Bezier elements' ends; inv_width (E,) 1 / their widths; first (E,) int64 the first control point
    index of each element; extraction (E, p+1, p+1): basis function first+i on element e is
    sum_m extraction[e, i, m] B_m."""

    breaks: np.ndarray
    inv_width: np.ndarray
    first: np.ndarray
    extraction: np.ndarray


class KernelTables(NamedTuple):
    """The three axes' AxisTables of a volume."""

    u: AxisTables
    v: AxisTables
    w: AxisTables

    def as_args(self):
        """The kernels' table arguments: (bu, hu, fu, xu, bv, hv, fv, xv, bw, hw, fw, xw) = breaks, inv_width,
        first and extraction of u, then of v, then of w."""
        return (*self.u, *self.v, *self.w)


def axis_tables(knots, degree):
    """Per-axis tables for the kernels -> AxisTables."""
    from .knots import bezier_extract_axis
    knots = np.asarray(knots, dtype=float)
    p = int(degree)
    n = len(knots) - p - 1
    br, seg = bezier_extract_axis(knots, p, np.eye(n)[:, :, None], axis=0)  # (E, p+1, n, 1)
    seg = seg[..., 0]
    first = np.searchsorted(knots, br[:-1], side="right") - 1 - p
    ext = np.stack([seg[e][:, first[e]:first[e] + p + 1].T for e in range(len(br) - 1)])
    return AxisTables(np.ascontiguousarray(br), np.ascontiguousarray(1.0 / np.diff(br)), first.astype(np.int64),
                      np.ascontiguousarray(ext))


def padded_net(net, degrees):
    """net (n_u, n_v, n_w, d) padded with zero layers along v and w up to degree 3, so the kernels' unrolled
    loops of length 4 stay inside the array (the padded entries meet zero basis values)."""
    pv, pw = degrees[1], degrees[2]
    if pv > 3 or pw > 3:
        return net
    return np.ascontiguousarray(np.pad(net, ((0, 0), (0, 3 - pv), (0, 3 - pw), (0, 0))))


@njit(cache=True, fastmath=_FM, nogil=True)
def _element(br, E, t):
    """Index of the element of the clamped t among breaks br (E+1,)."""
    lo = 0
    if E <= 16:
        # a branch-free count: scattered parameters make a binary search's branches unpredictable (~10% here)
        for m in range(1, E):
            lo += t >= br[m]
        return lo
    hi = E
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if t < br[mid]:
            hi = mid
        else:
            lo = mid
    return lo


@njit(cache=True, fastmath=_FM, nogil=True)
def _locate(br, invh, t):
    """Element of t, clamped to the breaks br (E+1,), and t's local coordinate in it, in [0, 1]."""
    E = br.shape[0] - 1
    if t < br[0]:
        t = br[0]
    if t > br[E]:
        t = br[E]
    lo = _element(br, E, t)
    return lo, (t - br[lo]) * invh[lo]


@njit(cache=True, fastmath=_FM, nogil=True)
def _basis(br, invh, ext, p, t, N, dN, B):
    """Element index of t (clamped) and the p+1 basis values in N and derivatives in dN (N may be dN when only the
    values are wanted: a flag would compile _basis twice, and the derivatives cost little beside the contraction)."""
    lo, s = _locate(br, invh, t)
    r1 = 1.0 - s
    B[0] = 1.0
    for j in range(1, p):
        saved = 0.0
        for r in range(j):
            tmp = B[r]
            B[r] = saved + r1 * tmp
            saved = s * tmp
        B[j] = saved
    # From degree p-1: d/ds B_m = p (B^{p-1}_{m-1} - B^{p-1}_m); times 1/width for d/dt.
    h = p * invh[lo]
    for i in range(p + 1):
        acc = 0.0
        for m in range(p):
            acc += B[m] * (ext[lo, i, m + 1] - ext[lo, i, m])
        dN[i] = h * acc
    saved = 0.0
    for r in range(p):
        tmp = B[r]
        B[r] = saved + r1 * tmp
        saved = s * tmp
    B[p] = saved
    for i in range(p + 1):
        acc = 0.0
        for m in range(p + 1):
            acc += ext[lo, i, m] * B[m]
        N[i] = acc
    return lo


@njit(cache=True, fastmath=_FM, nogil=True)
def values(uvw, start, stop, bu, hu, fu, xu, bv, hv, fv, xv, bw, hw, fw, xw, pu, pv, pw, cp, out, _der, mode):
    # Scalar accumulators (x, y, z, h) keep everything in registers; h only exists when rational.
    rat = mode.ndim == 2  # a compile-time constant
    Nu = np.zeros(MAXP)
    Nv = np.zeros(MAXP)
    Nw = np.zeros(MAXP)
    B = np.empty(MAXP)
    for idx in range(start, stop):
        i0 = fu[_basis(bu, hu, xu, pu, uvw[idx, 0], Nu, Nu, B)]
        j0 = fv[_basis(bv, hv, xv, pv, uvw[idx, 1], Nv, Nv, B)]
        k0 = fw[_basis(bw, hw, xw, pw, uvw[idx, 2], Nw, Nw, B)]
        ax = 0.0
        ay = 0.0
        az = 0.0
        ah = 0.0
        n0 = Nw[0]
        n1 = Nw[1]
        n2 = Nw[2]
        n3 = Nw[3]
        for i in range(pu + 1):
            bx = 0.0
            by = 0.0
            bz = 0.0
            bh = 0.0
            for j in range(4):
                c = cp[i0 + i, j0 + j]
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
        out[idx, 0] = ax
        out[idx, 1] = ay
        out[idx, 2] = az
        if rat:
            out[idx, 3] = ah


@njit(cache=True, fastmath=_FM, nogil=True)
def values_high(uvw, start, stop, bu, hu, fu, xu, bv, hv, fv, xv, bw, hw, fw, xw, pu, pv, pw, cp, out, _der, mode):
    # values for degree > 3 along v or w, whose loops cannot run over a padded 4.
    # Scalar accumulators (x, y, z, h) keep everything in registers; h only exists when rational.
    rat = mode.ndim == 2  # a compile-time constant
    Nu = np.zeros(MAXP)
    Nv = np.zeros(MAXP)
    Nw = np.zeros(MAXP)
    B = np.empty(MAXP)
    for idx in range(start, stop):
        i0 = fu[_basis(bu, hu, xu, pu, uvw[idx, 0], Nu, Nu, B)]
        j0 = fv[_basis(bv, hv, xv, pv, uvw[idx, 1], Nv, Nv, B)]
        k0 = fw[_basis(bw, hw, xw, pw, uvw[idx, 2], Nw, Nw, B)]
        ax = 0.0
        ay = 0.0
        az = 0.0
        ah = 0.0
        for i in range(pu + 1):
            bx = 0.0
            by = 0.0
            bz = 0.0
            bh = 0.0
            for j in range(pv + 1):
                cx = 0.0
                cy = 0.0
                cz = 0.0
                ch = 0.0
                for k in range(pw + 1):
                    nk = Nw[k]
                    cx += nk * cp[i0 + i, j0 + j, k0 + k, 0]
                    cy += nk * cp[i0 + i, j0 + j, k0 + k, 1]
                    cz += nk * cp[i0 + i, j0 + j, k0 + k, 2]
                    if rat:
                        ch += nk * cp[i0 + i, j0 + j, k0 + k, 3]
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


@njit(cache=True, fastmath=_FM, nogil=True)
def derivatives(uvw, start, stop, bu, hu, fu, xu, bv, hv, fv, xv, bw, hw, fw, xw, pu, pv, pw, cp, out, der,
                       mode):
    # Same contraction as values, carrying the value and the three partials in scalars
    # (suffix 0: value; u, v, w: partials; x, y, z, h: channels).
    rat = mode.ndim == 2
    Nu = np.zeros(MAXP)
    Nv = np.zeros(MAXP)
    Nw = np.zeros(MAXP)
    dNu = np.zeros(MAXP)
    dNv = np.zeros(MAXP)
    dNw = np.zeros(MAXP)
    B = np.empty(MAXP)
    for idx in range(start, stop):
        i0 = fu[_basis(bu, hu, xu, pu, uvw[idx, 0], Nu, dNu, B)]
        j0 = fv[_basis(bv, hv, xv, pv, uvw[idx, 1], Nv, dNv, B)]
        k0 = fw[_basis(bw, hw, xw, pw, uvw[idx, 2], Nw, dNw, B)]
        n0 = Nw[0]
        n1 = Nw[1]
        n2 = Nw[2]
        n3 = Nw[3]
        d0 = dNw[0]
        d1 = dNw[1]
        d2 = dNw[2]
        d3 = dNw[3]
        ax0 = ay0 = az0 = ah0 = 0.0
        axu = ayu = azu = ahu = 0.0
        axv = ayv = azv = ahv = 0.0
        axw = ayw = azw = ahw = 0.0
        for i in range(pu + 1):
            bx0 = by0 = bz0 = bh0 = 0.0
            bxv = byv = bzv = bhv = 0.0
            bxw = byw = bzw = bhw = 0.0
            for j in range(4):
                c = cp[i0 + i, j0 + j]
                cx0 = n0 * c[k0, 0] + n1 * c[k0 + 1, 0] + n2 * c[k0 + 2, 0] + n3 * c[k0 + 3, 0]
                cy0 = n0 * c[k0, 1] + n1 * c[k0 + 1, 1] + n2 * c[k0 + 2, 1] + n3 * c[k0 + 3, 1]
                cz0 = n0 * c[k0, 2] + n1 * c[k0 + 1, 2] + n2 * c[k0 + 2, 2] + n3 * c[k0 + 3, 2]
                cxw = d0 * c[k0, 0] + d1 * c[k0 + 1, 0] + d2 * c[k0 + 2, 0] + d3 * c[k0 + 3, 0]
                cyw = d0 * c[k0, 1] + d1 * c[k0 + 1, 1] + d2 * c[k0 + 2, 1] + d3 * c[k0 + 3, 1]
                czw = d0 * c[k0, 2] + d1 * c[k0 + 1, 2] + d2 * c[k0 + 2, 2] + d3 * c[k0 + 3, 2]
                ch0 = 0.0
                chw = 0.0
                if rat:
                    ch0 = n0 * c[k0, 3] + n1 * c[k0 + 1, 3] + n2 * c[k0 + 2, 3] + n3 * c[k0 + 3, 3]
                    chw = d0 * c[k0, 3] + d1 * c[k0 + 1, 3] + d2 * c[k0 + 2, 3] + d3 * c[k0 + 3, 3]
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


@njit(cache=True, fastmath=_FM, nogil=True)
def derivatives_high(uvw, start, stop, bu, hu, fu, xu, bv, hv, fv, xv, bw, hw, fw, xw, pu, pv, pw, cp, out, der,
    # derivatives for degree > 3 along v or w, whose loops cannot run over a padded 4.
                       mode):
    # Same contraction as values, carrying the value and the three partials in scalars
    # (suffix 0: value; u, v, w: partials; x, y, z, h: channels).
    rat = mode.ndim == 2
    Nu = np.zeros(MAXP)
    Nv = np.zeros(MAXP)
    Nw = np.zeros(MAXP)
    dNu = np.zeros(MAXP)
    dNv = np.zeros(MAXP)
    dNw = np.zeros(MAXP)
    B = np.empty(MAXP)
    for idx in range(start, stop):
        i0 = fu[_basis(bu, hu, xu, pu, uvw[idx, 0], Nu, dNu, B)]
        j0 = fv[_basis(bv, hv, xv, pv, uvw[idx, 1], Nv, dNv, B)]
        k0 = fw[_basis(bw, hw, xw, pw, uvw[idx, 2], Nw, dNw, B)]
        ax0 = ay0 = az0 = ah0 = 0.0
        axu = ayu = azu = ahu = 0.0
        axv = ayv = azv = ahv = 0.0
        axw = ayw = azw = ahw = 0.0
        for i in range(pu + 1):
            bx0 = by0 = bz0 = bh0 = 0.0
            bxv = byv = bzv = bhv = 0.0
            bxw = byw = bzw = bhw = 0.0
            for j in range(pv + 1):
                cx0 = cy0 = cz0 = ch0 = 0.0
                cxw = cyw = czw = chw = 0.0
                for k in range(pw + 1):
                    nk = Nw[k]
                    dk = dNw[k]
                    x = cp[i0 + i, j0 + j, k0 + k, 0]
                    y = cp[i0 + i, j0 + j, k0 + k, 1]
                    z = cp[i0 + i, j0 + j, k0 + k, 2]
                    cx0 += nk * x
                    cy0 += nk * y
                    cz0 += nk * z
                    cxw += dk * x
                    cyw += dk * y
                    czw += dk * z
                    if rat:
                        h = cp[i0 + i, j0 + j, k0 + k, 3]
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


@njit(cache=True, fastmath=_FM, nogil=True)
def _extract4(x, b0, b1, b2, b3):
    """The 4x4 extraction matrix x applied to four Bernstein values (or derivatives)."""
    return (x[0, 0] * b0 + x[0, 1] * b1 + x[0, 2] * b2 + x[0, 3] * b3,
            x[1, 0] * b0 + x[1, 1] * b1 + x[1, 2] * b2 + x[1, 3] * b3,
            x[2, 0] * b0 + x[2, 1] * b1 + x[2, 2] * b2 + x[2, 3] * b3,
            x[3, 0] * b0 + x[3, 1] * b1 + x[3, 2] * b2 + x[3, 3] * b3)


@njit(cache=True, fastmath=_FM, nogil=True)
def _cubic(br, invh, ext, t):
    """Element of t (clamped) and its four cubic basis values, all in registers."""
    lo, s = _locate(br, invh, t)
    r = 1.0 - s
    n0, n1, n2, n3 = _extract4(ext[lo], r * r * r, 3.0 * s * r * r, 3.0 * s * s * r, s * s * s)
    return lo, n0, n1, n2, n3


@njit(cache=True, fastmath=_FM, nogil=True)
def values_cubic(uvw, start, stop, bu, hu, fu, xu, bv, hv, fv, xv, bw, hw, fw, xw, _pu, _pv, _pw, cp, out, _der,
                        mode):
    # Tricubic volumes, the common case: every loop has constant length and every basis value is a scalar, so the
    # whole contraction stays in registers (~1.5x over values).
    rat = mode.ndim == 2
    for idx in range(start, stop):
        eu, a0, a1, a2, a3 = _cubic(bu, hu, xu, uvw[idx, 0])
        ev, b0, b1, b2, b3 = _cubic(bv, hv, xv, uvw[idx, 1])
        ew, c0, c1, c2, c3 = _cubic(bw, hw, xw, uvw[idx, 2])
        i0 = fu[eu]
        j0 = fv[ev]
        k0 = fw[ew]
        ax = 0.0
        ay = 0.0
        az = 0.0
        ah = 0.0
        for i in range(4):
            bx = 0.0
            by = 0.0
            bz = 0.0
            bh = 0.0
            for j in range(4):
                c = cp[i0 + i, j0 + j]
                cx = c0 * c[k0, 0] + c1 * c[k0 + 1, 0] + c2 * c[k0 + 2, 0] + c3 * c[k0 + 3, 0]
                cy = c0 * c[k0, 1] + c1 * c[k0 + 1, 1] + c2 * c[k0 + 2, 1] + c3 * c[k0 + 3, 1]
                cz = c0 * c[k0, 2] + c1 * c[k0 + 1, 2] + c2 * c[k0 + 2, 2] + c3 * c[k0 + 3, 2]
                nj = b0 if j == 0 else (b1 if j == 1 else (b2 if j == 2 else b3))
                bx += nj * cx
                by += nj * cy
                bz += nj * cz
                if rat:
                    bh += nj * (c0 * c[k0, 3] + c1 * c[k0 + 1, 3] + c2 * c[k0 + 2, 3] + c3 * c[k0 + 3, 3])
            ni = a0 if i == 0 else (a1 if i == 1 else (a2 if i == 2 else a3))
            ax += ni * bx
            ay += ni * by
            az += ni * bz
            ah += ni * bh
        out[idx, 0] = ax
        out[idx, 1] = ay
        out[idx, 2] = az
        if rat:
            out[idx, 3] = ah


@njit(cache=True, fastmath=_FM, nogil=True)
def _cubic_der(br, invh, ext, t):
    """Element of t (clamped), its four cubic basis values and their four derivatives d/dt."""
    lo, s = _locate(br, invh, t)
    h = invh[lo]
    r = 1.0 - s
    x = ext[lo]
    n0, n1, n2, n3 = _extract4(x, r * r * r, 3.0 * s * r * r, 3.0 * s * s * r, s * s * s)
    m0, m1, m2, m3 = _extract4(x, -3.0 * r * r * h, 3.0 * r * (r - 2.0 * s) * h, 3.0 * s * (2.0 * r - s) * h,
                               3.0 * s * s * h)
    return lo, n0, n1, n2, n3, m0, m1, m2, m3


@njit(cache=True, fastmath=_FM, nogil=True)
def derivatives_cubic(uvw, start, stop, bu, hu, fu, xu, bv, hv, fv, xv, bw, hw, fw, xw, _pu, _pv, _pw, cp, out,
                             der, mode):
    # derivatives for tricubic volumes, with the basis values and derivatives in registers.
    rat = mode.ndim == 2
    nch = 4 if rat else 3
    for idx in range(start, stop):
        eu, a0, a1, a2, a3, e0, e1, e2, e3 = _cubic_der(bu, hu, xu, uvw[idx, 0])
        ev, b0, b1, b2, b3, f0, f1, f2, f3 = _cubic_der(bv, hv, xv, uvw[idx, 1])
        ew, c0, c1, c2, c3, g0, g1, g2, g3 = _cubic_der(bw, hw, xw, uvw[idx, 2])
        i0 = fu[eu]
        j0 = fv[ev]
        k0 = fw[ew]
        for ch in range(nch):  # one channel at a time keeps the 16 sums in registers
            a_0 = 0.0
            a_u = 0.0
            a_v = 0.0
            a_w = 0.0
            for i in range(4):
                s_0 = 0.0
                s_v = 0.0
                s_w = 0.0
                for j in range(4):
                    c = cp[i0 + i, j0 + j]
                    q0 = c[k0, ch]
                    q1 = c[k0 + 1, ch]
                    q2 = c[k0 + 2, ch]
                    q3 = c[k0 + 3, ch]
                    w0 = c0 * q0 + c1 * q1 + c2 * q2 + c3 * q3
                    ww = g0 * q0 + g1 * q1 + g2 * q2 + g3 * q3
                    nj = b0 if j == 0 else (b1 if j == 1 else (b2 if j == 2 else b3))
                    dj = f0 if j == 0 else (f1 if j == 1 else (f2 if j == 2 else f3))
                    s_0 += nj * w0
                    s_v += dj * w0
                    s_w += nj * ww
                ni = a0 if i == 0 else (a1 if i == 1 else (a2 if i == 2 else a3))
                di = e0 if i == 0 else (e1 if i == 1 else (e2 if i == 2 else e3))
                a_0 += ni * s_0
                a_u += di * s_0
                a_v += ni * s_v
                a_w += ni * s_w
            out[idx, ch] = a_0
            der[idx, ch, 0] = a_u
            der[idx, ch, 1] = a_v
            der[idx, ch, 2] = a_w


@njit(cache=True, fastmath=_FM, nogil=True)
def _basis2(br, invh, ext, p, t, N, dN, ddN, B):
    """Element index of t (clamped) and the p+1 basis values, first and second derivatives in N, dN, ddN: N and dN
    as _basis gives them, ddN from the Bernstein values of degree p-2 (d^2/ds^2 B^p_m = p (p-1) (B^{p-2}_{m-2} -
    2 B^{p-2}_{m-1} + B^{p-2}_m))."""
    for i in range(p + 1):
        ddN[i] = 0.0
    if p >= 2:
        lo, s = _locate(br, invh, t)
        r1 = 1.0 - s
        B[0] = 1.0
        for j in range(1, p - 1):
            saved = 0.0
            for r in range(j):
                tmp = B[r]
                B[r] = saved + r1 * tmp
                saved = s * tmp
            B[j] = saved
        h2 = p * (p - 1) * invh[lo] * invh[lo]
        for i in range(p + 1):
            acc = 0.0
            for m in range(p - 1):
                acc += B[m] * (ext[lo, i, m + 2] - 2.0 * ext[lo, i, m + 1] + ext[lo, i, m])
            ddN[i] = h2 * acc
    return _basis(br, invh, ext, p, t, N, dN, B)


@njit(cache=True, fastmath=_FM, nogil=True)
def _sums2_at(u, v, bu, hu, fu, xu, bv, hv, fv, xv, pu, pv, cp, H, Nu, dNu, ddNu, Nv, dNv, ddNv, B):
    """Homogeneous sums of a surface at (u, v) and their partials up to second order into H (6, d): S, S_u, S_v,
    S_uu, S_uv, S_vv. Generic loops: the surface path (shell offsets) is far smaller than the volumes' and does not
    earn unrolled variants."""
    i0 = fu[_basis2(bu, hu, xu, pu, u, Nu, dNu, ddNu, B)]
    j0 = fv[_basis2(bv, hv, xv, pv, v, Nv, dNv, ddNv, B)]
    for c in range(cp.shape[2]):
        a00 = a10 = a01 = a20 = a11 = a02 = 0.0
        for i in range(pu + 1):
            b0 = b1 = b2 = 0.0
            for j in range(pv + 1):
                x = cp[i0 + i, j0 + j, c]
                b0 += Nv[j] * x
                b1 += dNv[j] * x
                b2 += ddNv[j] * x
            a00 += Nu[i] * b0
            a10 += dNu[i] * b0
            a20 += ddNu[i] * b0
            a01 += Nu[i] * b1
            a11 += dNu[i] * b1
            a02 += Nu[i] * b2
        H[0, c] = a00
        H[1, c] = a10
        H[2, c] = a01
        H[3, c] = a20
        H[4, c] = a11
        H[5, c] = a02


@njit(cache=True, fastmath=_FM, nogil=True)
def surface_sums2(uv, start, stop, bu, hu, fu, xu, bv, hv, fv, xv, pu, pv, cp, out):
    """_sums2_at at scattered points: uv (n, 2), cp (n_u, n_v, d) -> out[start:stop] (n, 6, d)."""
    Nu = np.zeros(MAXP)
    dNu = np.zeros(MAXP)
    ddNu = np.zeros(MAXP)
    Nv = np.zeros(MAXP)
    dNv = np.zeros(MAXP)
    ddNv = np.zeros(MAXP)
    B = np.empty(MAXP)
    for idx in range(start, stop):
        _sums2_at(uv[idx, 0], uv[idx, 1], bu, hu, fu, xu, bv, hv, fv, xv, pu, pv, cp, out[idx], Nu, dNu, ddNu,
                  Nv, dNv, ddNv, B)


@njit(cache=True, fastmath=_FM, nogil=True)
def _gap(H, x):
    """|S - x| from homogeneous sums H (6, 4)."""
    w = H[0, 3]
    return np.sqrt((H[0, 0] / w - x[0]) ** 2 + (H[0, 1] / w - x[1]) ** 2 + (H[0, 2] / w - x[2]) ** 2)


@njit(cache=True, fastmath=_FM, nogil=True)
def surface_distance(x, uv, start, stop, bu, hu, fu, xu, bv, hv, fv, xv, pu, pv, cp, dom, iterations, dist):
    """Distance from points x (n, 3) to a surface with homogeneous net cp (n_u, n_v, 4), by Newton from uv (n, 2),
    each point alone -> dist[start:stop]. The algorithm and its constants are shell.distance_to's (see there why
    Newton and not Gauss-Newton, and the halving); dom (2, 2) the domain it clamps to."""
    Nu = np.zeros(MAXP)
    dNu = np.zeros(MAXP)
    ddNu = np.zeros(MAXP)
    Nv = np.zeros(MAXP)
    dNv = np.zeros(MAXP)
    ddNv = np.zeros(MAXP)
    B = np.empty(MAXP)
    H = np.empty((6, 4))  # the sums at the current (u, v): an accepted trial's are kept, not recomputed
    T = np.empty((6, 4))  # and at a trial point
    S = np.empty((6, 3))
    for idx in range(start, stop):
        xi = x[idx]
        u = min(max(uv[idx, 0], dom[0, 0]), dom[0, 1])
        v = min(max(uv[idx, 1], dom[1, 0]), dom[1, 1])
        _sums2_at(u, v, bu, hu, fu, xu, bv, hv, fv, xv, pu, pv, cp, H, Nu, dNu, ddNu, Nv, dNv, ddNv, B)
        d = _gap(H, xi)
        for _ in range(iterations):
            w = H[0, 3]
            for c in range(3):  # the quotient rule (NURBS Book A4.4) up to second order
                s0 = H[0, c] / w
                su = (H[1, c] - H[1, 3] * s0) / w
                sv = (H[2, c] - H[2, 3] * s0) / w
                S[0, c] = s0 - xi[c]
                S[1, c] = su
                S[2, c] = sv
                S[3, c] = (H[3, c] - 2.0 * H[1, 3] * su - H[3, 3] * s0) / w
                S[4, c] = (H[4, c] - H[1, 3] * sv - H[2, 3] * su - H[4, 3] * s0) / w
                S[5, c] = (H[5, c] - 2.0 * H[2, 3] * sv - H[5, 3] * s0) / w
            a = b = c_ = ha = hb = hc = ru = rv = 0.0
            for c in range(3):
                r = S[0, c]
                a += S[1, c] * S[1, c]
                b += S[1, c] * S[2, c]
                c_ += S[2, c] * S[2, c]
                ha += r * S[3, c]
                hb += r * S[4, c]
                hc += r * S[5, c]
                ru += S[1, c] * r
                rv += S[2, c] * r
            ha += a
            hb += b
            hc += c_
            if ha > 0 and ha * hc - hb * hb > 0:
                a, b, c_ = ha, hb, hc
            reg = 1e-12 * (abs(a) + abs(c_))
            a += reg
            c_ += reg
            det = a * c_ - b * b
            step_u = (c_ * ru - b * rv) / det
            step_v = (a * rv - b * ru) / det
            nu, nv, nd = u, v, d
            for _halve in range(8):
                tu = min(max(u - step_u, dom[0, 0]), dom[0, 1])
                tv = min(max(v - step_v, dom[1, 0]), dom[1, 1])
                _sums2_at(tu, tv, bu, hu, fu, xu, bv, hv, fv, xv, pu, pv, cp, T, Nu, dNu, ddNu, Nv, dNv, ddNv, B)
                td = _gap(T, xi)
                if td <= d:
                    nu, nv, nd = tu, tv, td
                    H[:] = T
                    break
                step_u *= 0.5
                step_v *= 0.5
            gain = d - nd
            u, v, d = nu, nv, nd
            if not gain > 1e-9:
                break
        dist[idx] = d


# The four block functions are the entries, called from Python on [start, stop) of the points (volume.py splits large
# batches over threads, which these nogil kernels allow). numba's prange entries cost a parfor compilation each and
# made every block function compile twice (a literal and an int64 start): 16 versions and 38.8 s on a cold cache.
# On an empty cache the quarter torus compiles four entries (values and derivatives, general and tricubic) in ~8.9
# CPU s, most of it numba's typing and lowering in Python and its one-off registry set-up, LLVM ~1/5: NUMBA_OPT=1 or 2
# left the cold build's CPU time as it was (15.2-16.1 s against 15.8 s), so a lower optimisation level buys nothing.
# The tricubic entries cost ~3.4 CPU s of that but cannot simply go: the general ones differ from them in the last bits.


def kernel_name(degrees, want_der):
    """Which entry evaluates a volume of these degrees."""
    kind = ""
    if tuple(degrees) == (3, 3, 3):
        kind = "_cubic"
    elif degrees[1] > 3 or degrees[2] > 3:
        kind = "_high"
    return ("derivatives" if want_der else "values") + kind


def kernel(degrees, want_der):
    """The compiled entry for a volume of these degrees: fn(uvw, start, stop, *tables.as_args(), pu, pv, pw, cp, out,
    der, mode), tables a KernelTables, fills out[start:stop] (and der[start:stop] for derivatives)."""
    return globals()[kernel_name(degrees, want_der)]
