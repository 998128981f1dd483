"""The piece map F = M o R: parameter points of D to millimetres of the printed object."""

from dataclasses import dataclass

import numpy as np

from .spline import Volume


@dataclass(frozen=True, eq=False)
class Map:
    """model: M with control points already in mm; warp: R: D -> D or None (identity).

    orientation is +1 when det dF > 0 (right-handed) and -1 when M is left-handed; R is always right-handed.
    """

    model: Volume
    warp: Volume | None = None
    orientation: int = 1

    @property
    def domain(self):
        return self.model.domain

    def evaluate(self, uvw):
        """(n, 3) -> (n, 3) mm."""
        uvw = np.asarray(uvw, dtype=float)
        if self.warp is not None:
            uvw = self.warp.evaluate(uvw)
        return self.model.evaluate(uvw)

    def evaluate_with_jacobian(self, uvw):
        """(n, 3) -> points (n, 3) mm and dF/duvw (n, 3, 3) by the chain rule."""
        uvw = np.asarray(uvw, dtype=float)
        if self.warp is None:
            return self.model.evaluate_with_derivatives(uvw)
        r, dr = self.warp.evaluate_with_derivatives(uvw)
        x, dm = self.model.evaluate_with_derivatives(r)
        return x, np.einsum("nij,njk->nik", dm, dr)
