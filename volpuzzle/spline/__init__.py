"""Trivariate B-spline and NURBS mathematics: basis, knots, the Volume type and its exact Jacobian."""

from .volume import Volume

__all__ = ["Volume"]
