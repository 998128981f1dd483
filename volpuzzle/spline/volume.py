"""The Volume type: a trivariate (rational) B-spline M: D -> R^3 with clamped knot vectors.

Control points are Cartesian, shape (n_u, n_v, n_w, 3); weights, when present, (n_u, n_v, n_w).
"""

from dataclasses import dataclass

import numpy as np

from ..errors import ModelError
from . import basis

AXES = "uvw"


def _readonly(a):
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Volume:
    """degrees (3,), knots: three clamped knot vectors, control_points (n_u, n_v, n_w, 3), weights or None."""

    degrees: tuple
    knots: tuple
    control_points: np.ndarray
    weights: np.ndarray | None = None

    def __post_init__(self):
        problems = []
        try:
            degrees = tuple(int(d) for d in self.degrees)
        except (TypeError, ValueError):
            raise ModelError(f"degrees: expected three integers, got {self.degrees!r}") from None
        if len(degrees) != 3 or any(d < 1 or d > 7 for d in degrees):
            raise ModelError(f"degrees: expected three integers from 1 to 7, got {list(degrees)}")
        try:
            cps = np.array(self.control_points, dtype=float)
        except (TypeError, ValueError):
            raise ModelError("control_points: expected numbers in an array of shape (n_u, n_v, n_w, 3)") from None
        if cps.ndim != 4 or cps.shape[3] != 3:
            raise ModelError(f"control_points: expected an array of shape (n_u, n_v, n_w, 3), got shape {cps.shape}")
        if not np.all(np.isfinite(cps)):
            bad = np.argwhere(~np.isfinite(cps))[0]
            raise ModelError(f"control_points: non-finite coordinate (NaN or infinity) at index {bad[:3].tolist()}")
        if len(self.knots) != 3:
            raise ModelError(f"knots: expected three knot vectors, got {len(self.knots)}")
        knots = []
        for a in range(3):
            try:
                k = np.asarray(self.knots[a], dtype=float).ravel()
            except (TypeError, ValueError):
                raise ModelError(f"knots[{a}] ({AXES[a]}): expected a list of numbers") from None
            p, n = degrees[a], cps.shape[a]
            if n < p + 1:
                problems.append(f"control_points: {n} along {AXES[a]} is too few for degree {p} (need at least {p + 1})")
            if len(k) != n + p + 1:
                problems.append(
                    f"knots[{a}] ({AXES[a]}): length {len(k)} does not fit {n} control points of degree {p} "
                    f"(expected {n + p + 1})")
            elif not np.all(np.isfinite(k)):
                problems.append(f"knots[{a}] ({AXES[a]}): non-finite value")
            elif np.any(np.diff(k) < 0):
                i = int(np.argmax(np.diff(k) < 0))
                problems.append(f"knots[{a}] ({AXES[a]}): not non-decreasing (knot {i} = {k[i]:g} > knot {i + 1} = {k[i + 1]:g})")
            elif k[p] >= k[n]:
                problems.append(f"knots[{a}] ({AXES[a]}): empty domain [{k[p]:g}, {k[n]:g}]")
            else:
                inner = k[p + 1:n]
                mult = np.max(np.unique(inner, return_counts=True)[1]) if inner.size else 0
                if mult > p:
                    problems.append(f"knots[{a}] ({AXES[a]}): an interior knot repeats {mult} times, more than the degree {p}")
            knots.append(k)
        w = None
        if self.weights is not None:
            try:
                w = np.array(self.weights, dtype=float)
            except (TypeError, ValueError):
                raise ModelError("weights: expected numbers") from None
            if w.shape != cps.shape[:3]:
                problems.append(f"weights: shape {w.shape} does not match the control points {cps.shape[:3]}")
            elif not np.all(np.isfinite(w)) or np.any(w <= 0):
                bad = np.argwhere(~(np.isfinite(w) & (w > 0)))[0]
                problems.append(f"weights: every weight must be > 0, got {w[tuple(bad)]:g} at index {bad.tolist()}")
        if problems:
            raise ModelError("; ".join(problems))
        object.__setattr__(self, "degrees", degrees)
        object.__setattr__(self, "knots", tuple(_readonly(self._clamped(k, p)) for k, p in zip(knots, degrees)))
        object.__setattr__(self, "control_points", _readonly(cps))
        object.__setattr__(self, "weights", None if w is None else _readonly(w))

    @staticmethod
    def _clamped(k, p):
        # Unclamped end knots do not change the curve on [k[p], k[-p-1]] but would break Bezier extraction;
        # only the clamped case is supported, so check here rather than deep in an algorithm.
        if not (np.all(k[:p + 1] == k[0]) and np.all(k[-p - 1:] == k[-1])):
            raise ModelError(
                f"knots: only clamped (open) knot vectors are supported; the first and last knots must repeat "
                f"degree+1 = {p + 1} times, got {k[:p + 1].tolist()} ... {k[-p - 1:].tolist()}")
        return k

    # --- shape -------------------------------------------------------------------------------------------
    @property
    def shape(self):
        """(n_u, n_v, n_w): control points per axis."""
        return self.control_points.shape[:3]

    @property
    def is_rational(self):
        return self.weights is not None

    @property
    def domain(self):
        """((u0, u1), (v0, v1), (w0, w1))."""
        return tuple((float(k[p]), float(k[-p - 1])) for k, p in zip(self.knots, self.degrees))

    @property
    def domain_array(self):
        """(2, 3): row 0 the minimum parameters, row 1 the maximum."""
        return np.array(self.domain, dtype=float).T

    def homogeneous(self):
        """(n_u, n_v, n_w, 4): weighted points (w*x, w*y, w*z, w)."""
        w = np.ones(self.shape) if self.weights is None else self.weights
        return np.concatenate([self.control_points * w[..., None], w[..., None]], axis=-1)

    @classmethod
    def from_homogeneous(cls, degrees, knots, hpoints):
        """Inverse of homogeneous(): drops the weights when they are all one."""
        hpoints = np.asarray(hpoints, dtype=float)
        w = hpoints[..., 3]
        pts = hpoints[..., :3] / w[..., None]
        return cls(degrees, knots, pts, None if np.allclose(w, 1.0, rtol=0, atol=1e-14) else w)

    # --- evaluation ---------------------------------------------------------------------------------------
    def _check_uvw(self, uvw):
        uvw = np.asarray(uvw, dtype=float)
        if uvw.ndim != 2 or uvw.shape[1] != 3:
            raise ValueError(f"uvw must have shape (n, 3), got {uvw.shape}")
        return uvw

    def _local(self, uvw, order):
        """Basis values (and derivatives) per axis plus the span indices."""
        out = []
        for a in range(3):
            p, k = self.degrees[a], self.knots[a]
            t = np.clip(uvw[:, a], k[p], k[-p - 1])
            span = basis.find_span(k, p, t)
            out.append((span, basis.basis_derivatives(k, p, t, order, span)))
        return out

    def _sum(self, loc, du, dv, dw, hp):
        (su, bu), (sv, bv), (sw, bw) = loc
        pu, pv, pw = self.degrees
        iu = su[:, None] - pu + np.arange(pu + 1)
        iv = sv[:, None] - pv + np.arange(pv + 1)
        iw = sw[:, None] - pw + np.arange(pw + 1)
        local = hp[iu[:, :, None, None], iv[:, None, :, None], iw[:, None, None, :]]  # (n, pu+1, pv+1, pw+1, 4)
        return np.einsum("ni,nj,nk,nijkd->nd", bu[:, du], bv[:, dv], bw[:, dw], local, optimize=True)

    def evaluate(self, uvw):
        """(n, 3) parameters -> (n, 3) points."""
        uvw = self._check_uvw(uvw)
        loc = self._local(uvw, 0)
        h = self._sum(loc, 0, 0, 0, self.homogeneous())
        return h[:, :3] / h[:, 3:4]

    def evaluate_with_derivatives(self, uvw):
        """(n, 3) -> points (n, 3) and partials (n, 3, 3) with [i, :, k] = d point / d param k."""
        uvw = self._check_uvw(uvw)
        loc = self._local(uvw, 1)
        hp = self.homogeneous()
        h = self._sum(loc, 0, 0, 0, hp)
        w = h[:, 3:4]
        pts = h[:, :3] / w
        der = np.empty((uvw.shape[0], 3, 3))
        for k, (du, dv, dw) in enumerate(((1, 0, 0), (0, 1, 0), (0, 0, 1))):
            hd = self._sum(loc, du, dv, dw, hp)
            der[:, :, k] = (hd[:, :3] - pts * hd[:, 3:4]) / w
        return pts, der

    def derivatives(self, uvw):
        """(n, 3) -> (n, 3, 3): [i, :, k] = d point / d param k."""
        return self.evaluate_with_derivatives(uvw)[1]

    def evaluate_grid(self, u, v, w):
        """Tensor grid: parameter lists (a,), (b,), (c,) -> points (a, b, c, 3)."""
        u, v, w = (np.atleast_1d(np.asarray(x, dtype=float)) for x in (u, v, w))
        uu, vv, ww = np.meshgrid(u, v, w, indexing="ij")
        uvw = np.stack([uu.ravel(), vv.ravel(), ww.ravel()], axis=1)
        return self.evaluate(uvw).reshape(len(u), len(v), len(w), 3)

    def __repr__(self):
        kind = "rational" if self.is_rational else "polynomial"
        return f"Volume({kind}, degrees={self.degrees}, control_points={self.shape}, domain={self.domain})"
