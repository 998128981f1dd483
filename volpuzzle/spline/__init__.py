"""Trivariate B-spline and NURBS mathematics: basis, knots, the Volume type and its exact Jacobian.

volpuzzle.spline.jacobian (jacobian_bezier, certify_positive, certify_negative, orientation) and
volpuzzle.spline.measure (volume, bbox, control_net_bbox) are imported on demand: they need scipy.
"""

from .volume import Volume

__all__ = ["Volume"]
