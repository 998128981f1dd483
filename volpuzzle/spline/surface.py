"""The Surface type: a bivariate (rational) B-spline S: [u0, u1] x [v0, v1] -> R^3 with clamped knot vectors.

Control points are Cartesian, shape (n_u, n_v, 3); weights, when present, (n_u, n_v). Derivatives of a rational
surface follow The NURBS Book A4.4 (derivatives of the homogeneous sums, then the quotient rule).
"""

from dataclasses import dataclass
from functools import cached_property
from math import comb

import numpy as np

from ..errors import ModelError
from . import basis
from . import knots as knots_mod
from .volume import _PARALLEL_MIN, _POOL, TensorSpline, Volume, _fast_module, _readonly, _threads

_W_KNOTS = np.array([0.0, 0.0, 1.0, 1.0])


@dataclass(frozen=True, eq=False)
class Surface(TensorSpline):
    """degrees (2,), knots: two clamped knot vectors, control_points (n_u, n_v, 3), weights (n_u, n_v) or None."""

    degrees: tuple
    knots: tuple
    control_points: np.ndarray
    weights: np.ndarray | None = None

    def __post_init__(self):
        cps = np.asarray(self.control_points, dtype=float) if _numeric(self.control_points) else None
        if cps is None or cps.ndim != 3 or cps.shape[2] != 3:
            shape = None if cps is None else cps.shape
            raise ModelError(f"control_points: expected an array of shape (n_u, n_v, 3), got shape {shape}")
        if len(self.degrees) != 2 or len(self.knots) != 2:
            raise ModelError(f"degrees and knots: expected two of each (u, v), got {len(self.degrees)} and "
                             f"{len(self.knots)}")
        # The volume type already checks degrees, knots, weights and clamping: the surface is its w = 0 slab.
        w = None if self.weights is None else np.stack([self.weights] * 2, axis=2)
        vol = Volume(tuple(self.degrees) + (1,), tuple(self.knots) + (_W_KNOTS,), np.stack([cps, cps], axis=2), w)
        object.__setattr__(self, "degrees", vol.degrees[:2])
        object.__setattr__(self, "knots", vol.knots[:2])
        object.__setattr__(self, "control_points", _readonly(cps))
        object.__setattr__(self, "weights", None if vol.weights is None else _readonly(vol.weights[:, :, 0]))

    @classmethod
    def from_volume_slab(cls, vol, k=0):
        """The surface of control slab k along w of a volume (exact when that slab is a face: k = 0 or -1)."""
        w = None if vol.weights is None else vol.weights[:, :, k]
        return cls(vol.degrees[:2], vol.knots[:2], vol.control_points[:, :, k], w)

    @classmethod
    def from_homogeneous(cls, degrees, knots, hpoints):
        hpoints = np.asarray(hpoints, dtype=float)
        w = hpoints[..., 3]
        rational = not np.allclose(w, 1.0, rtol=0, atol=1e-14)
        return cls(degrees, knots, hpoints[..., :3] / w[..., None], w if rational else None)

    # --- shape -------------------------------------------------------------------------------------------
    def homogeneous(self):
        """(n_u, n_v, 4): weighted points (w*x, w*y, w*z, w)."""
        w = np.ones(self.shape) if self.weights is None else self.weights
        return np.concatenate([self.control_points * w[..., None], w[..., None]], axis=-1)

    @cached_property
    def as_volume(self):
        """The surface as a volume of degree 1 along w with two equal slabs: evaluates with the compiled kernels."""
        w = None if self.weights is None else np.stack([self.weights] * 2, axis=2)
        return Volume(self.degrees + (1,), self.knots + (_W_KNOTS,), np.stack([self.control_points] * 2, 2), w)

    # --- evaluation ---------------------------------------------------------------------------------------
    def _uvw(self, uv):
        uv = np.asarray(uv, dtype=float)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"uv must have shape (n, 2), got {uv.shape}")
        return np.concatenate([uv, np.zeros((len(uv), 1))], axis=1)

    def evaluate(self, uv):
        """(n, 2) parameters -> (n, 3) points; parameters outside the domain are clamped to it."""
        return self.as_volume.evaluate(self._uvw(uv))

    def evaluate_with_derivatives(self, uv):
        """(n, 2) -> points (n, 3) and partials (n, 3, 2), [i, :, k] = d point / d param k."""
        x, d = self.as_volume.evaluate_with_derivatives(self._uvw(uv))
        return x, d[:, :, :2]

    def derivatives(self, uv, order=2):
        """(n, 2) -> (n, order+1, order+1, 3): [i, k, l] = d^(k+l) S / du^k dv^l (NURBS Book A3.6 and A4.4)."""
        uv = np.asarray(uv, dtype=float)
        n = len(uv)
        h = self._compiled_sums(uv, order) if order <= 2 else None
        if h is None:
            h = self._numpy_sums(uv, order)
        a, w = h[..., :3], h[..., 3]
        out = np.zeros((n, order + 1, order + 1, 3))
        for k in range(order + 1):
            for m in range(order + 1 - k):
                v = a[:, k, m].copy()
                for j in range(1, m + 1):
                    v -= comb(m, j) * w[:, 0, j, None] * out[:, k, m - j]
                for i in range(1, k + 1):
                    v -= comb(k, i) * w[:, i, 0, None] * out[:, k - i, m]
                    for j in range(1, m + 1):
                        v -= comb(k, i) * comb(m, j) * w[:, i, j, None] * out[:, k - i, m - j]
                out[:, k, m] = v / w[:, 0, 0, None]
        return out

    @cached_property
    def _hnet(self):
        # the compiled surface kernel's net: homogeneous even when polynomial (weights 1), one array type
        return np.require(self.homogeneous(), np.float64, ["C", "W"])

    def _compiled_sums(self, uv, order):
        """Homogeneous sums and partials up to order <= 2 by the compiled kernel -> (n, order+1, order+1, 4), or
        None without numba. ~50x the numpy path: the shell's offset fit measures its distance to S with Newton
        steps at up to ~10^5-10^6 points per round."""
        n = len(uv)
        out = np.empty((n, 6, 4))
        if not self._run_compiled("surface_sums2", n, (np.require(uv, np.float64, ["C", "W"]),), (out,)):
            return None
        h = np.zeros((n, order + 1, order + 1, 4))
        for slot, (k, m) in enumerate(((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))):
            if k + m <= order:
                h[:, k, m] = out[:, slot]
        return h

    def _run_compiled(self, name, n, before, after):
        """Run the compiled surface kernel `name`(*before, start, stop, *tables of u and v, pu, pv, net, *after) over
        n points, split over the spline thread pool when large -> False without numba."""
        fast = _fast_module()
        if fast is None:
            return False
        fn, tables = getattr(fast, name), self.as_volume._tables
        tail = (*tables.u, *tables.v, int(self.degrees[0]), int(self.degrees[1]), self._hnet, *after)
        pool = _threads() if n >= _PARALLEL_MIN else None
        if pool is None:
            fn(*before, 0, n, *tail)
        else:  # each point computed alone: the bits do not depend on the split
            step = max(1024, -(-n // (4 * _POOL["workers"])))
            list(pool.map(lambda s: fn(*before, s, min(n, s + step), *tail), range(0, n, step)))
        return True

    def _numpy_sums(self, uv, order):
        """The numpy path of the homogeneous sums (reference, and any order) -> (n, order+1, order+1, 4)."""
        loc = []
        for a in range(2):
            p, k = self.degrees[a], self.knots[a]
            t = np.clip(uv[:, a], k[p], k[-p - 1])
            span = basis.find_span(k, p, t)
            loc.append((span, basis.basis_derivatives(k, p, t, min(order, p), span)))
        (su, bu), (sv, bv) = loc
        pu, pv = self.degrees
        iu = su[:, None] - pu + np.arange(pu + 1)
        iv = sv[:, None] - pv + np.arange(pv + 1)
        local = self.homogeneous()[iu[:, :, None], iv[:, None, :]]  # (n, pu+1, pv+1, 4)
        h = np.zeros((len(uv), order + 1, order + 1, 4))
        for k in range(min(order, pu) + 1):
            for m in range(min(order - k, pv) + 1):
                h[:, k, m] = np.einsum("ni,nj,nijd->nd", bu[:, k], bv[:, m], local)
        return h

    def distance_compiled(self, x, uv, iterations):
        """shell.distance_to by the compiled kernel: x (n, 3), uv (n, 2) -> (n,), or None without numba."""
        n = len(x)
        dist = np.empty(n)
        before = tuple(np.require(a, np.float64, ["C", "W"]) for a in (x, uv))
        dom = np.require(np.array(self.domain, dtype=float), np.float64, ["C", "W"])
        return dist if self._run_compiled("surface_distance", n, before, (dom, int(iterations), dist)) else None

    def normals(self, uv, nudge=1e-4):
        """(n, 2) -> (n, 3) unit normals along S_u x S_v. Where that product vanishes (a collapsed row, a pole) the
        normal is the limit, taken a little (nudge of the domain) inside the domain."""
        uv = np.array(uv, dtype=float)
        _, d = self.evaluate_with_derivatives(uv)
        nrm = np.cross(d[:, :, 0], d[:, :, 1])
        length = np.linalg.norm(nrm, axis=1)
        # a vanishing partial (a pole) makes the product vanish too: compare with the larger partial squared
        scale = np.maximum(np.linalg.norm(d[:, :, 0], axis=1), np.linalg.norm(d[:, :, 1], axis=1)) ** 2
        bad = length <= 1e-8 * np.maximum(scale, 1e-300)
        if np.any(bad):
            dom = np.array(self.domain)
            mid = dom.mean(axis=1)
            step = nudge * (dom[:, 1] - dom[:, 0])
            # off the degenerate boundary only: a pole's normals are the limits along each meridian
            moved = uv[bad].copy()
            for k in range(2):
                edge = np.isclose(moved[:, k], dom[k, 0]) | np.isclose(moved[:, k], dom[k, 1])
                moved[edge, k] += np.sign(mid[k] - moved[edge, k]) * step[k]
            if np.array_equal(moved, uv[bad]):
                moved += np.sign(mid - moved) * step
            nrm[bad] = self.normals(moved, nudge * 4) if nudge < 0.05 else nrm[bad]
            length[bad] = np.linalg.norm(nrm[bad], axis=1)
        return nrm / np.maximum(length, 1e-300)[:, None]

    def evaluate_grid(self, u, v):
        """(a,), (b,) -> points (a, b, 3)."""
        return self.as_volume.evaluate_grid(u, v, [0.0])[:, :, 0]

    # --- refinement and maps ------------------------------------------------------------------------------
    def insert_knot(self, axis, t, times=1):
        """The same surface with knot t inserted `times` times along axis 0 (u) or 1 (v)."""
        k, hp = knots_mod.insert_knot(self.knots[axis], self.degrees[axis], self.homogeneous(), float(t), times, axis)
        new = list(self.knots)
        new[axis] = k
        w = None if not self.is_rational else hp[..., 3]
        return Surface(self.degrees, tuple(new), hp[..., :3] / hp[..., 3:4], w)

    def transformed(self, matrix, offset=(0.0, 0.0, 0.0)):
        """x -> matrix @ x + offset on the control points (exact for NURBS)."""
        m, o = np.asarray(matrix, dtype=float), np.asarray(offset, dtype=float)
        return Surface(self.degrees, self.knots, self.control_points @ m.T + o, self.weights)

    def scaled(self, factor):
        return self.transformed(np.eye(3) * float(factor))

    def swapped(self):
        """The same surface with u and v exchanged (flips the normal)."""
        w = None if self.weights is None else self.weights.T
        return Surface(self.degrees[::-1], self.knots[::-1], self.control_points.transpose(1, 0, 2), w)

    def reversed(self, axis):
        """The same surface with one parameter running the other way (flips the normal)."""
        k = self.knots[axis]
        new = list(self.knots)
        new[axis] = (k[0] + k[-1]) - k[::-1]
        w = None if self.weights is None else np.flip(self.weights, axis)
        return Surface(self.degrees, tuple(new), np.flip(self.control_points, axis), w)

    def __repr__(self):
        kind = "rational" if self.is_rational else "polynomial"
        return f"Surface({kind}, degrees={self.degrees}, control_points={self.shape}, domain={self.domain})"


def _numeric(x):
    try:
        np.asarray(x, dtype=float)
        return True
    except (TypeError, ValueError):
        return False

