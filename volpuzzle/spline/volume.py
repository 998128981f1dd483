"""The Volume type: a trivariate (rational) B-spline M: D -> R^3 with clamped knot vectors.

Control points are Cartesian, shape (n_u, n_v, n_w, 3); weights, when present, (n_u, n_v, n_w).
"""

import os
import threading
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..errors import ModelError
from ..grid import AXES
from . import basis
from . import knots as knots_mod

_PARALLEL_MIN = 4096  # points; below this one thread is faster than waking others
_POOL = {}
_MODE = {3: np.empty(0), 4: np.empty((0, 0))}
_FAST = []


def _fast_module():
    """The numba kernels, imported lazily (None when numba is unavailable: the numpy path is used)."""
    if not _FAST:
        try:
            from . import _fast
        except ImportError:  # pragma: no cover - numba is a dependency, but degrade rather than fail
            _fast = None
        _FAST.append(_fast)
    return _FAST[0]


def _threads():
    """This process's thread pool for large batches, or None off the main thread (callers that already run on
    threads keep to theirs) or on one core. A forked child makes its own: threads do not survive a fork."""
    if threading.current_thread() is not threading.main_thread():
        return None
    from ..workers import usable_cores

    workers = usable_cores()
    if workers < 2:
        return None
    pid = os.getpid()
    if _POOL.get("pid") != pid:
        from concurrent.futures import ThreadPoolExecutor

        workers = min(workers, 8)
        _POOL.update(pid=pid, workers=workers, pool=ThreadPoolExecutor(workers, thread_name_prefix="volpuzzle-spline"))
    return _POOL["pool"]


def _axis_index(axis):
    if axis in (0, 1, 2):
        return int(axis)
    if isinstance(axis, str) and axis in AXES:
        return AXES.index(axis)
    raise ModelError(f"axis: expected 0, 1, 2 or 'u', 'v', 'w', got {axis!r}")



def _readonly(a):
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


class TensorSpline:
    """What a tensor-product NURBS (Volume, Surface) derives alike from its degrees, knots and weights."""

    @property
    def shape(self):
        """Control points per axis: (n_u, n_v, n_w) or (n_u, n_v)."""
        return self.control_points.shape[:len(self.degrees)]

    @property
    def is_rational(self):
        return self.weights is not None

    @property
    def domain(self):
        """((u0, u1), (v0, v1)[, (w0, w1)])."""
        return tuple((float(k[p]), float(k[-p - 1])) for k, p in zip(self.knots, self.degrees, strict=True))


@dataclass(frozen=True, eq=False)
class Volume(TensorSpline):
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
                problems.append(f"control_points: {n} along {AXES[a]} is too few for degree {p} "
                                f"(need at least {p + 1})")
            if len(k) != n + p + 1:
                problems.append(
                    f"knots[{a}] ({AXES[a]}): length {len(k)} does not fit {n} control points of degree {p} "
                    f"(expected {n + p + 1})")
            elif not np.all(np.isfinite(k)):
                problems.append(f"knots[{a}] ({AXES[a]}): non-finite value")
            elif np.any(np.diff(k) < 0):
                i = int(np.argmax(np.diff(k) < 0))
                problems.append(f"knots[{a}] ({AXES[a]}): not non-decreasing "
                                f"(knot {i} = {k[i]:g} > knot {i + 1} = {k[i + 1]:g})")
            elif k[p] >= k[n]:
                problems.append(f"knots[{a}] ({AXES[a]}): empty domain [{k[p]:g}, {k[n]:g}]")
            else:
                inner = k[p + 1:n]
                mult = np.max(np.unique(inner, return_counts=True)[1]) if inner.size else 0
                if mult > p:
                    problems.append(f"knots[{a}] ({AXES[a]}): an interior knot repeats {mult} times, "
                                    f"more than the degree {p}")
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
        object.__setattr__(self, "knots", tuple(_readonly(self._clamped(k, p))
                                                for k, p in zip(knots, degrees, strict=True)))
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
    @cached_property
    def _net(self):
        # Contiguous control net for the kernels: Cartesian (d=3) when polynomial, homogeneous (d=4) when
        # rational, so polynomial volumes skip a quarter of the work and the division.
        net = self.homogeneous() if self.is_rational else self.control_points
        return np.ascontiguousarray(net, dtype=float)

    @cached_property
    def _knet(self):
        # The compiled kernels' copy: zero-padded along v and w for their unrolled loops.
        fast = _fast_module()
        net = self._net if fast is None else fast.padded_net(self._net, self.degrees)
        return np.require(net, np.float64, ["C", "W"])  # a read-only net would be another type, another compilation

    @cached_property
    def _tables(self):
        fast = _fast_module()
        return fast.KernelTables(*(fast.axis_tables(k, p) for k, p in zip(self.knots, self.degrees, strict=True)))

    def _check_uvw(self, uvw):
        uvw = np.asarray(uvw, dtype=float)
        if uvw.ndim != 2 or uvw.shape[1] != 3:
            raise ValueError(f"uvw must have shape (n, 3), got {uvw.shape}")
        return uvw

    def _kernel(self, uvw, want_der):
        """Homogeneous (or Cartesian) sums at scattered points: (n, d) and, if asked, (n, d, 3)."""
        n = uvw.shape[0]
        d = self._net.shape[3]
        # Every call takes the compiled path, however few its points: a numpy path for tiny calls until the kernels
        # were loaded made the last bits (of bbox, say) depend on what the process had evaluated before.
        fast = _fast_module()
        if fast is None:
            return self._numpy_sums(uvw, want_der)
        # One array type per argument (C-contiguous, writable float64), so numba compiles one version per kernel.
        uvw = np.require(uvw, np.float64, ["C", "W"])
        out = np.empty((n, d))
        der = np.empty((n, d, 3)) if want_der else np.empty((1, 1, 3))
        fn = fast.kernel(self.degrees, want_der)
        args = (*self._tables.as_args(), *(int(p) for p in self.degrees), self._knet, out, der, _MODE[d])
        pool = _threads() if n >= _PARALLEL_MIN else None
        if pool is None:
            fn(uvw, 0, n, *args)
        else:
            # The kernels release the GIL: ranges of the points on threads, each point computed alone, so the bits
            # do not depend on the split.
            step = max(1024, -(-n // (4 * _POOL["workers"])))
            list(pool.map(lambda s: fn(uvw, s, min(n, s + step), *args), range(0, n, step)))
        return out, (der if want_der else None)

    def _numpy_sums(self, uvw, want_der):
        """The plain numpy path (reference and fallback when numba is missing)."""
        order = 1 if want_der else 0
        loc = []
        for a in range(3):
            p, k = self.degrees[a], self.knots[a]
            t = np.clip(uvw[:, a], k[p], k[-p - 1])
            span = basis.find_span(k, p, t)
            loc.append((span, basis.basis_derivatives(k, p, t, order, span)))
        (su, bu), (sv, bv), (sw, bw) = loc
        pu, pv, pw = self.degrees
        iu = su[:, None] - pu + np.arange(pu + 1)
        iv = sv[:, None] - pv + np.arange(pv + 1)
        iw = sw[:, None] - pw + np.arange(pw + 1)
        local = self._net[iu[:, :, None, None], iv[:, None, :, None], iw[:, None, None, :]]
        def s(du, dv, dw):
            return np.einsum("ni,nj,nk,nijkd->nd", bu[:, du], bv[:, dv], bw[:, dw], local, optimize=True)

        h = s(0, 0, 0)
        if not want_der:
            return h, None
        return h, np.stack([s(1, 0, 0), s(0, 1, 0), s(0, 0, 1)], axis=-1)

    def _project(self, h, hd):
        """Homogeneous sums -> points and (quotient rule) partials."""
        if not self.is_rational:
            return h, hd
        w = h[:, 3:4]
        pts = h[:, :3] / w
        if hd is None:
            return pts, None
        der = (hd[:, :3, :] - pts[:, :, None] * hd[:, 3:4, :]) / w[:, :, None]
        return pts, der

    def evaluate(self, uvw):
        """(n, 3) parameters -> (n, 3) points. Parameters outside the domain are clamped to it."""
        uvw = self._check_uvw(uvw)
        return self._project(*self._kernel(uvw, False))[0]

    def evaluate_with_derivatives(self, uvw):
        """(n, 3) -> points (n, 3) and partials (n, 3, 3) with [i, :, k] = d point / d param k."""
        uvw = self._check_uvw(uvw)
        return self._project(*self._kernel(uvw, True))

    def derivatives(self, uvw):
        """(n, 3) -> (n, 3, 3): [i, :, k] = d point / d param k."""
        return self.evaluate_with_derivatives(uvw)[1]

    def _grid_sums(self, u, v, w, want_der):
        # Basis once per axis, then contract w, v, u in turn (cost ~ a*b*c*n_u*d for the last step).
        u, v, w = (np.atleast_1d(np.asarray(x, dtype=float)).ravel() for x in (u, v, w))
        order = 1 if want_der else 0
        Bu, Bv, Bw = (basis.basis_matrix(k, p, t, order)
                      for k, p, t in zip(self.knots, self.degrees, (u, v, w), strict=True))
        net = self._net
        cw = [np.einsum("ck,ijkd->ijcd", Bw[o], net, optimize=True) for o in range(order + 1)]
        bv = [np.einsum("bj,ijcd->ibcd", Bv[0], cw[0], optimize=True)]
        if want_der:
            bv.append(np.einsum("bj,ijcd->ibcd", Bv[1], cw[0], optimize=True))  # d/dv
            bv.append(np.einsum("bj,ijcd->ibcd", Bv[0], cw[1], optimize=True))  # d/dw
        h = np.einsum("ai,ibcd->abcd", Bu[0], bv[0], optimize=True)
        if not want_der:
            return h, None
        hd = np.stack([np.einsum("ai,ibcd->abcd", Bu[1], bv[0], optimize=True),
                       np.einsum("ai,ibcd->abcd", Bu[0], bv[1], optimize=True),
                       np.einsum("ai,ibcd->abcd", Bu[0], bv[2], optimize=True)], axis=-1)
        return h, hd

    def evaluate_grid(self, u, v, w):
        """Tensor grid: parameter lists (a,), (b,), (c,) -> points (a, b, c, 3)."""
        h, _ = self._grid_sums(u, v, w, False)
        if self.is_rational:
            return h[..., :3] / h[..., 3:4]
        return h

    def derivatives_grid(self, u, v, w):
        """Tensor grid: (a,), (b,), (c,)
        -> points (a, b, c, 3) and partials (a, b, c, 3, 3), [.., :, k] = d/d param k."""
        h, hd = self._grid_sums(u, v, w, True)
        if not self.is_rational:
            return h, hd
        wt = h[..., 3:4]
        pts = h[..., :3] / wt
        der = (hd[..., :3, :] - pts[..., :, None] * hd[..., 3:4, :]) / wt[..., None]
        return pts, der

    # --- refinement and maps ------------------------------------------------------------------------------
    def insert_knot(self, axis, t, times=1):
        """The same volume with knot t inserted `times` times along axis 0/1/2 (Boehm, in homogeneous space)."""
        axis = _axis_index(axis)
        k, hp = knots_mod.insert_knot(self.knots[axis], self.degrees[axis], self.homogeneous(), float(t), times, axis)
        new_knots = list(self.knots)
        new_knots[axis] = k
        return self._from_h(new_knots, hp)

    def _from_h(self, knots, hp):
        # Keep the rational/polynomial kind of self (from_homogeneous would drop all-one weights anyway).
        if not self.is_rational:
            return Volume(self.degrees, tuple(knots), hp[..., :3] / hp[..., 3:4], None)
        return Volume(self.degrees, tuple(knots), hp[..., :3] / hp[..., 3:4], hp[..., 3])

    def bezier_elements(self):
        """Bezier extraction (every interior knot raised to multiplicity p; NURBS Book 5.3).

        Returns (breaks: three arrays of distinct knots (E_a + 1,), hpoints (E_u, E_v, E_w, p_u+1, p_v+1, p_w+1, 4)):
        homogeneous Bezier control points of each element.
        """
        hp = self.homogeneous()
        brs = []
        for a in range(3):
            br, hp = knots_mod.bezier_extract_axis(self.knots[a], self.degrees[a], hp, axis=2 * a)
            brs.append(br)
        # hp is now (E_u, p_u+1, E_v, p_v+1, E_w, p_w+1, 4)
        return tuple(brs), np.ascontiguousarray(hp.transpose(0, 2, 4, 1, 3, 5, 6))

    def subvolume(self, box):
        """The volume restricted to the parameter box (2, 3) (row 0 minimum, row 1 maximum), exactly."""
        box = np.asarray(box, dtype=float)
        if box.shape != (2, 3):
            raise ModelError(f"subvolume: box must have shape (2, 3), got {box.shape}")
        dom = self.domain_array
        for a in range(3):
            lo, hi = box[:, a]
            if not (dom[0, a] <= lo < hi <= dom[1, a]):
                raise ModelError(
                    f"subvolume: box along {AXES[a]} is [{lo:g}, {hi:g}]; expected lo < hi inside the domain "
                    f"[{dom[0, a]:g}, {dom[1, a]:g}]")
        hp = self.homogeneous()
        new_knots = []
        for a in range(3):
            k, hp = knots_mod.sub_range(self.knots[a], self.degrees[a], hp, box[0, a], box[1, a], axis=a)
            new_knots.append(k)
        return self._from_h(new_knots, hp)

    def transformed(self, matrix, offset=(0.0, 0.0, 0.0)):
        """x -> matrix @ x + offset applied to the control points (exact for NURBS: affine maps commute)."""
        m = np.asarray(matrix, dtype=float)
        o = np.asarray(offset, dtype=float)
        if m.shape != (3, 3) or o.shape != (3,):
            raise ModelError(f"transformed: expected a (3, 3) matrix and a (3,) offset, got {m.shape} and {o.shape}")
        return Volume(self.degrees, self.knots, self.control_points @ m.T + o, self.weights)

    def scaled(self, factor):
        """Uniform scale about the origin."""
        return self.transformed(np.eye(3) * float(factor))

    def __repr__(self):
        kind = "rational" if self.is_rational else "polynomial"
        return f"Volume({kind}, degrees={self.degrees}, control_points={self.shape}, domain={self.domain})"
