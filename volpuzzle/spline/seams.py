"""Periodic (closed) axes: where a volume's min and max faces along an axis meet in space.

A seam along axis a identifies the max face with the min face through one of the eight symmetries of the
unit square, acting on the normalised face coordinates (s, t) of the other two axes (b, c), b < c.
A torus closes with the identity; a square bar twisted by 90 degrees closes with a swap and a flip.
"""

from dataclasses import dataclass, field
from itertools import product

import numpy as np

from ..grid import other_axes

_UNIT = ((0.0, 1.0), (0.0, 1.0), (0.0, 1.0))


@dataclass(frozen=True)
class Seam:
    """Max face point at (s, t) == min face point at g(s, t); g swaps (if swap) and then flips.

    (s, t) are the normalised [0, 1] coordinates of the two other axes in increasing order. `domain` is the
    volume's parameter domain, used to convert to and from parameters; it takes no part in equality.
    """

    axis: int
    swap: bool = False
    flip: tuple = (False, False)
    domain: tuple = field(default=_UNIT, compare=False, repr=False)

    @property
    def is_identity(self):
        return not self.swap and not any(self.flip)

    def _g(self, st):
        st = st[:, ::-1] if self.swap else st.copy()
        for k in range(2):
            if self.flip[k]:
                st[:, k] = 1.0 - st[:, k]
        return st

    def _g_inverse(self, st):
        st = st.copy()
        for k in range(2):
            if self.flip[k]:
                st[:, k] = 1.0 - st[:, k]
        return st[:, ::-1] if self.swap else st

    def _apply(self, uvw, fn, to_max):
        uvw = np.asarray(uvw, dtype=float)
        b, c = other_axes(self.axis)
        lo = np.array([self.domain[b][0], self.domain[c][0]])
        hi = np.array([self.domain[b][1], self.domain[c][1]])
        st = (uvw[:, [b, c]] - lo) / (hi - lo)
        st = fn(st)
        out = uvw.copy()
        out[:, [b, c]] = lo + st * (hi - lo)
        out[:, self.axis] = self.domain[self.axis][1 if to_max else 0]
        return out

    def map_max_to_min(self, uvw):
        """(n, 3) parameters on (or projected onto) the max face
        -> (n, 3) parameters of the same points on the min face."""
        return self._apply(uvw, self._g, to_max=False)

    def map_min_to_max(self, uvw):
        """Inverse of map_max_to_min: (n, 3) on the min face -> (n, 3) on the max face."""
        return self._apply(uvw, self._g_inverse, to_max=True)


def _symmetries():
    # identity first, so that a degenerate face that matches several ways reports the simplest seam
    for swap, f0, f1 in product((False, True), (False, True), (False, True)):
        yield swap, (f0, f1)


def _model_size(vol):
    cps = vol.control_points.reshape(-1, 3)
    return float(np.linalg.norm(cps.max(axis=0) - cps.min(axis=0))) or 1.0


def find_seams(vol, rel_tol=1e-6, samples=9):
    """Axes whose min and max faces coincide in space -> {axis: Seam}.

    Compares evaluated points of the two faces on a (samples x samples) grid, off the knots, within
    rel_tol times the diagonal of the control net's bounding box.
    """
    dom = vol.domain
    size = _model_size(vol)
    # a grid that includes the face corners and edges plus irregular interior points (avoids knot symmetries)
    s = np.unique(np.concatenate([[0.0, 1.0], (np.arange(samples) + 0.5) / samples + 0.013]))
    s = s[(s >= 0) & (s <= 1)]
    ss, tt = np.meshgrid(s, s, indexing="ij")
    st = np.stack([ss.ravel(), tt.ravel()], axis=1)
    seams = {}
    for a in range(3):
        b, c = other_axes(a)
        uvw = np.empty((len(st), 3))
        uvw[:, a] = dom[a][1]
        uvw[:, b] = dom[b][0] + st[:, 0] * (dom[b][1] - dom[b][0])
        uvw[:, c] = dom[c][0] + st[:, 1] * (dom[c][1] - dom[c][0])
        xyz_max = vol.evaluate(uvw)
        for swap, flip in _symmetries():
            seam = Seam(a, swap, flip, tuple(tuple(d) for d in dom))
            xyz_min = vol.evaluate(seam.map_max_to_min(uvw))
            if np.max(np.linalg.norm(xyz_max - xyz_min, axis=1)) <= rel_tol * size:
                seams[a] = seam
                break
    return seams


def periodic_axes(vol, rel_tol=1e-6):
    """Sorted list of the axes along which the volume closes on itself."""
    return sorted(find_seams(vol, rel_tol=rel_tol))
