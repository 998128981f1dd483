"""The exact Jacobian determinant of a Volume as a piecewise Bernstein polynomial, and sign certificates.

Per Bezier element the partials of the (homogeneous) map are Bezier volumes one degree lower along their
axis (NURBS Book eq. 3.17 per direction), and det J is a sum of triple products of them. Products of
Bernstein polynomials are exact in the *scaled* basis: multiply coefficient (i, j, k) by the binomials
C(p, i) C(q, j) C(r, k), convolve, divide by the binomials of the product degree (Farouki & Rajan 1988).

Polynomial M: det J = det[M_u, M_v, M_w], degree (3p-1, 3q-1, 3r-1) per element.
Rational M = P / W: with G = (W, P) the homogeneous map, det[G; G_u; G_v; G_w] (rows, 4x4) = W^4 det J
(subtract W_u / W times the first row from the second etc.; expand along the W column). This numerator,
of degree (4p-1, 4q-1, 4r-1), has the sign of det J since W > 0, and is what we bound.

Coefficients are in the global parameters (the 1/element-width factors of the chain rule included), so
for a polynomial M they bound det J itself; for a rational M they bound W^4 det J.
"""

import weakref
from dataclasses import dataclass
from itertools import permutations
from math import comb

import numpy as np

_CHUNK = 256  # elements per batch, to bound memory of the intermediate products


def _binomials(shape):
    """(a+1, b+1, c+1) tensor of C(a, i) C(b, j) C(c, k) for a coefficient array of that shape."""
    bs = [np.array([comb(n - 1, i) for i in range(n)], dtype=float) for n in shape]
    return bs[0][:, None, None] * bs[1][None, :, None] * bs[2][None, None, :]


def _scaled(c, ncomp_axes=1):
    """Bernstein coefficients (K, a, b, c, *comp) -> scaled coefficients (times the binomials)."""
    shape = c.shape[1:4]
    b = _binomials(shape)
    return c * b.reshape((1,) + shape + (1,) * ncomp_axes)


def _levi_civita(n):
    eps = np.zeros((n,) * n)
    for perm in permutations(range(n)):
        # sign = parity of the permutation
        p = list(perm)
        sign = 1
        for i in range(n):
            while p[i] != i:
                j = p[i]
                p[i], p[j] = p[j], p[i]
                sign = -sign
        eps[perm] = sign
    return eps


def _shifted_products(a, b):
    """Scaled Bernstein products of every component pair: a (m, s1, s2, s3, K), b (n, t1, t2, t3, K)
    -> (m, n, s1+t1-1, s2+t2-1, s3+t3-1, K). Elements run along the last (contiguous) axis."""
    m, s = a.shape[0], a.shape[1:4]
    n, t = b.shape[0], b.shape[1:4]
    K = a.shape[-1]
    out = np.zeros((m, n, s[0] + t[0] - 1, s[1] + t[1] - 1, s[2] + t[2] - 1, K))
    bb = b[None]
    for i in range(s[0]):
        for j in range(s[1]):
            for k in range(s[2]):
                out[:, :, i:i + t[0], j:j + t[1], k:k + t[2]] += a[:, None, i, j, k, None, None, None, :] * bb
    return out


def _shifted_dot(a, b):
    """sum_c a_c * b_c as scaled Bernstein products: a (m, s.., K), b (m, t.., K) -> (s+t-1.., K)."""
    s, t = a.shape[1:4], b.shape[1:4]
    K = a.shape[-1]
    out = np.zeros((s[0] + t[0] - 1, s[1] + t[1] - 1, s[2] + t[2] - 1, K))
    for i in range(s[0]):
        for j in range(s[1]):
            for k in range(s[2]):
                out[i:i + t[0], j:j + t[1], k:k + t[2]] += np.einsum("cxyzK,cK->xyzK", b, a[:, i, j, k])
    return out


def _element_det(hp, widths, rational):
    """hp (K, p+1, q+1, r+1, 4) homogeneous Bezier points, widths (K, 3) -> det coefficients (K, a, b, c).

    Products are shifted adds in the scaled basis (exact up to ordinary rounding; an FFT version was no
    faster at these sizes and lost ~1e-10 relative accuracy at degree 15). Elements run along the last axis
    so every numpy operation works on contiguous runs.
    """
    degs = [n - 1 for n in hp.shape[1:4]]
    if rational:
        g = hp[..., [3, 0, 1, 2]]  # (W, P): the W column first makes det = +W^4 det J
        n = 4
    else:
        g = hp[..., :3] / hp[..., 3:4]
        n = 3
    # Partials in global parameters: p / width * forward differences (NURBS Book eq. 3.17 per direction).
    du = degs[0] / widths[:, 0, None, None, None, None] * np.diff(g, axis=1)
    dv = degs[1] / widths[:, 1, None, None, None, None] * np.diff(g, axis=2)
    dw = degs[2] / widths[:, 2, None, None, None, None] * np.diff(g, axis=3)
    def lay(f):  # -> (comp, i, j, k, K)
        return np.ascontiguousarray(np.moveaxis(_scaled(f), (0, 4), (4, 0)))

    su, sv, sw = lay(du), lay(dv), lay(dw)
    eps = _levi_civita(n)
    t = _shifted_products(sv, sw)                                  # T_cd = (G_v)_c (G_w)_d
    if rational:
        lam = np.einsum("abcd,cdxyzK->abxyzK", eps, t)             # L_ab = eps_abcd T_cd
        kk = np.stack([_shifted_dot(su, lam[a]) for a in range(n)])  # K_a = (G_u)_b L_ab
        det = _shifted_dot(lay(g), kk)                               # det = G_a K_a
    else:
        lam = np.einsum("abc,bcxyzK->axyzK", eps, t)               # the cross product M_v x M_w
        det = _shifted_dot(su, lam)
    det = np.moveaxis(det, 3, 0)
    return det / _binomials(det.shape[1:4])[None]


@dataclass(frozen=True, eq=False)
class JacobianSpline:
    """det J (times W^4 when rational) as Bernstein coefficients per Bezier element.

    breaks: three arrays of element boundaries (E_a + 1,); coefficients (E_u, E_v, E_w, a+1, b+1, c+1);
    min / max: extreme coefficients (bounds of the polynomial); argmin_uvw (3,): the Greville point of the min
    coefficient; rational: whether the polynomial is W^4 det J; lower / upper: bounds of det J itself
    (equal to min / max when polynomial; divided by bounds of W^4 per element when rational).
    """

    breaks: tuple
    coefficients: np.ndarray
    min: float
    max: float
    argmin_uvw: np.ndarray
    rational: bool = False
    lower: float = 0.0
    upper: float = 0.0

    @property
    def degrees(self):
        return tuple(n - 1 for n in self.coefficients.shape[3:6])

    @property
    def scale(self):
        """max |coefficient|: the scale against which tolerances are taken."""
        return float(max(abs(self.min), abs(self.max)))

    def greville(self, element, index):
        """Parameter point (3,) of coefficient `index` (i, j, k) in element (eu, ev, ew)."""
        out = np.empty(3)
        for a in range(3):
            b = self.breaks[a]
            e = element[a]
            out[a] = b[e] + (index[a] / max(self.degrees[a], 1)) * (b[e + 1] - b[e])
        return out

    def evaluate(self, uvw):
        """(n, 3) -> (n,) values of the polynomial (det J, or W^4 det J when rational)."""
        uvw = np.atleast_2d(np.asarray(uvw, dtype=float))
        out = np.empty(uvw.shape[0])
        for s in range(0, uvw.shape[0], 1024):
            x = uvw[s:s + 1024]
            idx, bern = [], []
            for a in range(3):
                b = self.breaks[a]
                t = np.clip(x[:, a], b[0], b[-1])
                e = np.clip(np.searchsorted(b, t, side="right") - 1, 0, len(b) - 2)
                idx.append(e)
                bern.append(_bernstein((t - b[e]) / (b[e + 1] - b[e]), self.degrees[a]))
            c = self.coefficients[idx[0], idx[1], idx[2]]
            out[s:s + 1024] = np.einsum("ni,nj,nk,nijk->n", bern[0], bern[1], bern[2], c, optimize=True)
        return out


def _bernstein(s, p):
    """(n,) local parameters in [0, 1] -> (n, p+1) Bernstein basis values."""
    s = np.asarray(s, dtype=float)
    j = np.arange(p + 1)
    binom = np.array([comb(p, i) for i in j], dtype=float)
    return binom * s[:, None] ** j * (1 - s[:, None]) ** (p - j)


_MEMO = weakref.WeakKeyDictionary()  # Volume (immutable, hashed by identity) -> its JacobianSpline


def jacobian_bezier(vol):
    """The exact det J of `vol` (a Volume) as a JacobianSpline, computed once per volume: a shell certifies its
    volume when it is built and verify certifies the same model again (1.2 s each for the duck's)."""
    spline = _MEMO.get(vol)
    if spline is None:
        spline = _MEMO[vol] = _jacobian_bezier(vol)
    return spline


def _jacobian_bezier(vol):
    breaks, hp = vol.bezier_elements()
    E = hp.shape[:3]
    widths = np.stack(np.meshgrid(*[np.diff(b) for b in breaks], indexing="ij"), axis=-1).reshape(-1, 3)
    flat = hp.reshape((-1,) + hp.shape[3:])
    parts = [_element_det(flat[s:s + _CHUNK], widths[s:s + _CHUNK], vol.is_rational)
             for s in range(0, flat.shape[0], _CHUNK)]
    coef = np.concatenate(parts, axis=0)
    coef = coef.reshape(E + coef.shape[1:])
    flat_i = int(np.argmin(coef))
    where = np.unravel_index(flat_i, coef.shape)
    lo, hi = float(coef.min()), float(coef.max())
    if vol.is_rational:
        # det J = N / W^4 with W between its element's min and max Bezier weight (convex hull property).
        w = hp[..., 3].reshape(E + (-1,))
        wmin4, wmax4 = w.min(axis=-1) ** 4, w.max(axis=-1) ** 4
        cmin = coef.reshape(E + (-1,)).min(axis=-1)
        cmax = coef.reshape(E + (-1,)).max(axis=-1)
        lower = float(np.min(np.where(cmin >= 0, cmin / wmax4, cmin / wmin4)))
        upper = float(np.max(np.where(cmax >= 0, cmax / wmin4, cmax / wmax4)))
    else:
        lower, upper = lo, hi
    det_spline = JacobianSpline(tuple(np.asarray(b, dtype=float) for b in breaks), coef, lo, hi, np.zeros(3),
                                vol.is_rational, lower, upper)
    object.__setattr__(det_spline, "argmin_uvw", det_spline.greville(where[:3], where[3:]))
    return det_spline


# --- certificates ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Certificate:
    """Result of certifying sign * det J > 0 over the domain.

    status: 'proved' (every coefficient > eps*scale after subdivision), 'disproved' (a point where
    sign * det J <= 0: where_uvw, value), 'unresolved' (max_depth reached), or 'degenerate' (see
    certify_positive). sign: +1 / -1. min_coefficient: the smallest coefficient of sign * det J (times W^4 when
    rational) over the final subdivision divided by `scale` (max |coefficient| at depth 0): a proved lower bound
    when status is proved/degenerate. where_uvw (3,): the place of that minimum, or of the failure. value: det J
    (true, unsigned, from the volume's derivatives) at where_uvw.
    """

    status: str
    sign: int
    min_coefficient: float
    where_uvw: np.ndarray
    value: float
    scale: float = 1.0
    depth: int = 0
    message: str = ""

    @property
    def ok(self):
        return self.status in ("proved", "degenerate")


def _true_det(vol, uvw):
    d = vol.derivatives(np.atleast_2d(uvw))
    return float(np.linalg.det(d)[0])


def _de_casteljau_half(c, axis):
    """Split Bernstein coefficients (K, a, b, c) at the midpoint of `axis` (1..3) -> (left, right)."""
    c = np.moveaxis(c, axis, 1)
    n = c.shape[1]
    left = np.empty_like(c)
    right = np.empty_like(c)
    work = c.copy()
    left[:, 0] = work[:, 0]
    right[:, n - 1] = work[:, n - 1]
    for r in range(1, n):
        work = 0.5 * (work[:, :-1] + work[:, 1:])
        left[:, r] = work[:, 0]
        right[:, n - 1 - r] = work[:, -1]
    return np.moveaxis(left, 1, axis), np.moveaxis(right, 1, axis)


def _eval_local(c, s):
    """c (K, a, b, c) Bernstein coefficients, s (K, 3) local parameters -> (K,) values."""
    degs = [n - 1 for n in c.shape[1:4]]
    b = [_bernstein(s[:, a], degs[a]) for a in range(3)]
    return np.einsum("ki,kj,kl,kijl->k", b[0], b[1], b[2], c)


def _null_faces_interior(c, tol, on_boundary):
    """For elements with all coefficients >= -tol: the local centre (3,) of a face/edge/corner (or the whole
    element) whose coefficients all vanish (<= tol) while it is not contained in the domain boundary;
    None per element when there is none. on_boundary (K, 2, 3) bool: element side (lo/hi, axis) on ∂D.

    The exact rule behind 'degenerate': a Bernstein polynomial with coefficients >= 0 is > 0 in the relative
    interior of every face (of any dimension, including the element itself) that has a positive coefficient,
    and 0 on the faces whose coefficients are all 0. So its zero set is exactly the union of the null faces.
    """
    K = c.shape[0]
    null = c <= tol
    result = [None] * K
    # choice per axis: 0 = lo side fixed, 1 = hi side fixed, 2 = free (whole range)
    for cu in range(3):
        for cv in range(3):
            for cw in range(3):
                choice = (cu, cv, cw)
                sl = tuple(slice(0, 1) if ch == 0 else slice(-1, None) if ch == 1 else slice(None) for ch in choice)
                allnull = null[(slice(None),) + sl].reshape(K, -1).all(axis=1)
                if not allnull.any():
                    continue
                inside = np.ones(K, dtype=bool)
                for a, ch in enumerate(choice):
                    if ch < 2:
                        inside &= ~on_boundary[:, ch, a]
                bad = allnull & inside
                for k in np.nonzero(bad)[0]:
                    if result[k] is None:
                        result[k] = np.array([0.0 if ch == 0 else 1.0 if ch == 1 else 0.5 for ch in choice])
    return result


def _certify(vol, det_spline, sign, max_depth, eps):
    scale = det_spline.scale
    if scale == 0.0:
        return Certificate("disproved", sign, 0.0, np.asarray(det_spline.argmin_uvw), 0.0, 0.0, 0,
                           "det J vanishes identically")
    tol = eps * scale
    E = det_spline.coefficients.shape[:3]
    degs = det_spline.degrees
    shape = det_spline.coefficients.shape[3:]
    coef = sign * det_spline.coefficients.reshape((-1,) + shape)
    eu, ev, ew = np.meshgrid(*[np.arange(n) for n in E], indexing="ij")
    eidx = np.stack([eu.ravel(), ev.ravel(), ew.ravel()], axis=1)
    boxes = np.stack([np.stack([det_spline.breaks[a][eidx[:, a]] for a in range(3)], axis=1),
                      np.stack([det_spline.breaks[a][eidx[:, a] + 1] for a in range(3)], axis=1)], axis=1)  # (K, 2, 3)
    dom = np.array([[b[0] for b in det_spline.breaks], [b[-1] for b in det_spline.breaks]])
    span = dom[1] - dom[0]

    best_min = np.inf          # smallest leaf coefficient among accepted leaves
    best_where = np.asarray(det_spline.argmin_uvw, dtype=float)
    degenerate = False
    unresolved = None          # (min coef, where) of the worst unresolved leaf

    def leaf_min(c, bx):
        nonlocal best_min, best_where
        flat = c.reshape(c.shape[0], -1)
        m = flat.min(axis=1)
        k = int(np.argmin(m))
        if m[k] < best_min:
            best_min = float(m[k])
            idx = np.unravel_index(int(np.argmin(flat[k])), shape)
            best_where = bx[k, 0] + np.array(idx) / np.maximum(degs, 1) * (bx[k, 1] - bx[k, 0])

    depth = 0
    while coef.shape[0]:
        flat = coef.reshape(coef.shape[0], -1)
        mins = flat.min(axis=1)
        good = mins > tol
        if good.any():
            leaf_min(coef[good], boxes[good])
        coef, boxes, mins, flat = coef[~good], boxes[~good], mins[~good], flat[~good]
        if not coef.shape[0]:
            break
        K = coef.shape[0]
        # Exact samples: corner coefficients are the values at the element corners.
        lo_b = np.isclose(boxes[:, 0], dom[0], rtol=0, atol=1e-12 * span)
        hi_b = np.isclose(boxes[:, 1], dom[1], rtol=0, atol=1e-12 * span)
        on_b = np.stack([lo_b, hi_b], axis=1)
        samples_s, samples_v = [], []
        for corner in np.ndindex(2, 2, 2):
            sl = tuple(0 if c_ == 0 else -1 for c_ in corner)
            samples_s.append(np.broadcast_to(np.array(corner, dtype=float), (K, 3)))
            samples_v.append(coef[(slice(None),) + sl])
        # ... and the polynomial at the Greville point of each element's min coefficient.
        imin = np.array(np.unravel_index(np.argmin(flat, axis=1), shape)).T
        s_min = imin / np.maximum(degs, 1)
        samples_s.append(s_min)
        samples_v.append(_eval_local(coef, s_min))
        S = np.stack(samples_s, axis=1)                    # (K, m, 3) local
        V = np.stack(samples_v, axis=1)                    # (K, m)
        X = boxes[:, None, 0] + S * (boxes[:, None, 1] - boxes[:, None, 0])
        strictly_inside = np.all((X > dom[0] + 1e-12 * span) & (X < dom[1] - 1e-12 * span), axis=2)
        fail = (V < -tol) | ((V <= tol) & strictly_inside)
        if fail.any():
            k, m = np.unravel_index(int(np.argmin(np.where(fail, V, np.inf))), V.shape)
            where = X[k, m]
            return Certificate("disproved", sign, float(mins.min() / scale), where, _true_det(vol, where),
                               scale, depth, f"sign*det J <= 0 at uvw={np.round(where, 6).tolist()}")
        # Elements whose coefficients are all >= -tol: zeros only on null faces; accept if those lie on ∂D.
        weak = mins >= -tol
        if weak.any():
            wk = np.nonzero(weak)[0]
            bad = _null_faces_interior(coef[wk], tol, on_b[wk])
            for k, b in zip(wk, bad, strict=True):
                if b is not None:
                    where = boxes[k, 0] + b * (boxes[k, 1] - boxes[k, 0])
                    return Certificate("disproved", sign, float(mins.min() / scale), where, _true_det(vol, where),
                                       scale, depth,
                                       f"det J vanishes inside the domain near uvw={np.round(where, 6).tolist()}")
            degenerate = True
            leaf_min(coef[weak], boxes[weak])
            coef, boxes, mins = coef[~weak], boxes[~weak], mins[~weak]
            if not coef.shape[0]:
                break
        if depth >= max_depth:
            k = int(np.argmin(mins))
            idx = np.unravel_index(int(np.argmin(coef[k])), shape)
            where = boxes[k, 0] + np.array(idx) / np.maximum(degs, 1) * (boxes[k, 1] - boxes[k, 0])
            unresolved = (float(mins[k]), where, coef.shape[0])
            break
        # Halve each remaining element along its widest side (relative to the domain).
        rel = (boxes[:, 1] - boxes[:, 0]) / span
        axis = np.argmax(rel, axis=1)
        new_c, new_b = [], []
        for a in range(3):
            sel = axis == a
            if not sel.any():
                continue
            left, right = _de_casteljau_half(coef[sel], a + 1)
            bl = boxes[sel].copy()
            br = boxes[sel].copy()
            mid = 0.5 * (bl[:, 0, a] + bl[:, 1, a])
            bl[:, 1, a] = mid
            br[:, 0, a] = mid
            new_c += [left, right]
            new_b += [bl, br]
        coef = np.concatenate(new_c)
        boxes = np.concatenate(new_b)
        depth += 1
    if unresolved is not None:
        m, where, n = unresolved
        return Certificate("unresolved", sign, m / scale, where, _true_det(vol, where), scale, depth,
                           f"{n} sub-element(s) still have a coefficient <= 0 after {max_depth} subdivisions")
    status = "degenerate" if degenerate else "proved"
    msg = ("det J >= 0 with zeros only on the domain boundary" if degenerate else "every coefficient is positive")
    return Certificate(status, sign, best_min / scale, best_where, _true_det(vol, best_where), scale, depth, msg)


def certify_positive(vol, max_depth=6, eps=1e-10, det_spline=None):
    """Certify det J > 0 on the whole domain -> Certificate.

    proved: every coefficient > eps*scale (scale = max |coefficient|), after subdividing (de Casteljau, halving the
    widest side) only the elements that need it, up to max_depth levels. disproved: a sampled value <= 0 — the
    element corners (exact: the corner coefficients) and the polynomial at the Greville point of each element's
    smallest coefficient — is found; where_uvw is that point. degenerate: every remaining coefficient is
    >= -eps*scale and each face/edge/corner of an element whose coefficients are all within eps*scale of zero lies
    on the domain boundary: then det J > 0 everywhere in the open domain and vanishes only on ∂D (collapsed faces
    such as a sphere's pole or a square-to-disk patch's corners). A null face inside the domain is 'disproved'.
    unresolved: max_depth reached.
    """
    det_spline = jacobian_bezier(vol) if det_spline is None else det_spline
    return _certify(vol, det_spline, +1, max_depth, eps)


def certify_negative(vol, max_depth=6, eps=1e-10, det_spline=None):
    """Certify det J < 0 on the whole domain (a left-handed model); see certify_positive."""
    det_spline = jacobian_bezier(vol) if det_spline is None else det_spline
    return _certify(vol, det_spline, -1, max_depth, eps)


@dataclass(frozen=True)
class Orientation:
    """handedness: 'right' (det J > 0), 'left' (det J < 0), 'folded' (both signs found; where_uvw holds a point
    of the minority sign, value det J there) or 'unresolved'. sign: +1 / -1 (0 when folded)."""

    handedness: str
    sign: int
    certificate: Certificate | None
    where_uvw: np.ndarray
    value: float
    lower: float = 0.0
    upper: float = 0.0


def orientation(vol, max_depth=6, eps=1e-10, samples=4096, seed=0):
    """Right- or left-handedness of `vol`, certified; 'folded' with a place when det J takes both signs."""
    det_spline = jacobian_bezier(vol)
    tol = eps * det_spline.scale
    if det_spline.min > tol:
        sign = 1
    elif det_spline.max < -tol:
        sign = -1
    else:
        rng = np.random.default_rng(seed)
        dom = vol.domain_array
        uvw = dom[0] + rng.random((samples, 3)) * (dom[1] - dom[0])
        det = np.linalg.det(vol.derivatives(uvw))
        big = np.abs(det).max() if det.size else 0.0
        pos, neg = det > eps * big, det < -eps * big
        if pos.any() and neg.any():
            minority = neg if neg.sum() <= pos.sum() else pos
            i = int(np.nonzero(minority)[0][np.argmax(np.abs(det[minority]))])
            return Orientation("folded", 0, None, uvw[i], float(det[i]), det_spline.lower, det_spline.upper)
        sign = 1 if pos.sum() >= neg.sum() else -1
    cert = _certify(vol, det_spline, sign, max_depth, eps)
    if cert.ok:
        return Orientation("right" if sign > 0 else "left", sign, cert, cert.where_uvw, cert.value, det_spline.lower,
                           det_spline.upper)
    if cert.status == "disproved":
        return Orientation("folded", 0, cert, cert.where_uvw, cert.value, det_spline.lower, det_spline.upper)
    return Orientation("unresolved", sign, cert, cert.where_uvw, cert.value, det_spline.lower, det_spline.upper)
