"""randomize: R: D -> D, a random cubic B-spline map of the parameter box onto itself that keeps its boundary.

The pieces are the images of the cells under F = M o R; R bends the straight cuts between cells into freeform
surfaces while D's boundary (and so the model's outer surface) stays where it is.

Construction (all in normalised unit-cube coordinates, then scaled onto D):

- Each axis has n >= 4 control points, degree 3, uniform clamped knots. With control points at the Greville
  abscissae the spline is the identity (linear precision of B-splines, The NURBS Book, eq. 2.10 / section 9.2.3).
- One direction field delta, shape (n, n, n, 3), is drawn once, uniformly in [-1, 1], from the generator. The
  control point (i, j, k) moves by   displacement_a = amplitude * spacing_a * delta_a   along axis a, where
  spacing_a = (hi_a - lo_a) / (n - 1) is R's mean control-point spacing along a. So `amplitude` is a fraction of
  that spacing: 0.25 moves a control point by at most a quarter of the distance to its neighbour.
- Corner and edge control points do not move; a face-internal control point moves only within its face plane
  (its normal component is zero); interior control points move freely. A clamped spline's boundary face is the
  bivariate spline of its face control points, so D's corners and edges are fixed and each face maps into itself.
- On a periodic axis with seam g (swap then flip of the face coordinates), the max-face control points are set from
  the min-face ones: P_max[i, j] = g^-1(P_min[g(i, j)]), g acting on indices (flip: i -> n-1-i) and on the in-face
  displacement (flip negates, swap exchanges). Since the knots are uniform, symmetric and equal on both face axes,
  this makes g o R = R o g on the max face, so cells still meet across the seam after warping.
- Control points are clamped into D (clamping commutes with the seam symmetries), so by the convex-hull property
  R(D) is inside D; with the boundary kept and det J > 0 (verify.verify_warp), R maps D onto D one-to-one.
"""

from dataclasses import dataclass

import numpy as np

from .errors import SpecError
from .spline import Volume
from .spline.knots import greville, uniform_knots

DEGREE = 3


def _domain_array(domain):
    """Accept (2, 3) [min row, max row] or ((u0, u1), (v0, v1), (w0, w1)); return (2, 3)."""
    d = np.asarray(domain, dtype=float)
    if d.shape == (3, 2):
        d = d.T
    if d.shape != (2, 3) or not np.all(np.isfinite(d)) or np.any(d[1] <= d[0]):
        raise ValueError(f"domain must be (2, 3) with min < max on every axis, got {np.asarray(domain).tolist()}")
    return d


def _boundary_mask(n):
    """(n, n, n, 3) of 0/1: which displacement components may be non-zero.

    Interior points move in 3D; a face point (one index at 0 or n-1) keeps that axis's coordinate; an edge or corner
    point (two or more such indices) stays fixed.
    """
    idx = np.indices((n, n, n))
    on = (idx == 0) | (idx == n - 1)  # (3, n, n, n)
    count = on.sum(axis=0)
    mask = np.ones((n, n, n, 3))
    for a in range(3):
        mask[..., a] = np.where(on[a], 0.0, 1.0)
    mask[count >= 2] = 0.0
    return mask


def _apply_seam(delta, axis, seam, n):
    """Set the max-face displacements from the min-face ones so that g o R = R o g on the max face (in place)."""
    b, c = (x for x in range(3) if x != axis)
    swap = bool(seam.swap)
    flip = tuple(bool(f) for f in seam.flip)
    # Move axes so the array is (a, b, c, 3).
    d = np.moveaxis(delta, (axis, b, c), (0, 1, 2))
    face_min = d[0]  # (n, n, 3), indexed [i_b, i_c]
    i_b, i_c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    # g on indices: swap first, then flip (i -> n-1-i).
    g0, g1 = (i_c, i_b) if swap else (i_b, i_c)
    if flip[0]:
        g0 = n - 1 - g0
    if flip[1]:
        g1 = n - 1 - g1
    src = face_min[g0, g1]  # (n, n, 3): displacement of P_min[g(i, j)]
    # g^-1 = swap o flip on vectors: negate flipped components (in the post-swap frame), then swap.
    st = src[..., [b, c]].copy()
    for k in range(2):
        if flip[k]:
            st[..., k] = -st[..., k]
    if swap:
        st = st[..., ::-1]
    face_max = np.zeros_like(src)
    face_max[..., b] = st[..., 0]
    face_max[..., c] = st[..., 1]
    d[n - 1] = face_max
    return delta


@dataclass(frozen=True, eq=False)
class WarpFamily:
    """R_amplitude for amplitude >= 0: one drawn direction field, scaled. Call it with an amplitude to get a Volume.

    domain (2, 3); control_points n per axis; delta (n, n, n, 3) in [-1, 1], already masked for the boundary and made
    seam-symmetric; knots: three clamped uniform knot vectors on D; identity (n, n, n, 3) in unit-cube coordinates.
    """

    domain: np.ndarray
    control_points: int
    delta: np.ndarray
    knots: tuple
    identity: np.ndarray
    periodic: tuple = ()

    def control_net(self, amplitude):
        """(n, n, n, 3) control points of R in D's coordinates."""
        amplitude = float(amplitude)
        if not np.isfinite(amplitude) or amplitude < 0:
            raise ValueError(f"amplitude must be a finite number >= 0, got {amplitude!r}")
        n = self.control_points
        q = self.identity + (amplitude / (n - 1)) * self.delta  # spacing in the unit cube is 1 / (n - 1)
        q = np.clip(q, 0.0, 1.0)
        lo, hi = self.domain
        return lo * (1.0 - q) + hi * q  # exact lo at q = 0 and hi at q = 1, so boundary points stay on D's faces

    def __call__(self, amplitude):
        return Volume((DEGREE,) * 3, self.knots, self.control_net(amplitude))


def warp_family(domain, control_points, rng, seams=None):
    """A family amplitude -> R (cubic Volume on D) with one random direction field drawn from rng.

    domain (2, 3) or ((u0, u1), (v0, v1), (w0, w1)); control_points n >= 4 per axis; rng np.random.Generator;
    seams {axis: Seam} (any object with .swap and .flip) for the periodic axes.
    """
    d = _domain_array(domain)
    n = int(control_points)
    if n < 4:
        raise SpecError(f"randomize.control_points: too few for a cubic map (got {control_points}, expected >= 4)")
    unit = uniform_knots(n)
    g = greville(unit)
    g[0], g[-1] = 0.0, 1.0  # exact ends, so fixed boundary points sit exactly on D's faces
    identity = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1)
    delta = rng.uniform(-1.0, 1.0, size=(n, n, n, 3))  # drawn once, whole, so the stream does not depend on seams
    delta = delta * _boundary_mask(n)
    seams = dict(seams or {})
    for axis in sorted(seams):
        _apply_seam(delta, int(axis), seams[axis], n)
    delta.setflags(write=False)
    identity.setflags(write=False)
    knots = tuple(uniform_knots(n, d[0, a], d[1, a]) for a in range(3))
    # The same knot values at the ends as D itself, so the Volume's domain equals D bit for bit.
    return WarpFamily(d, n, delta, knots, identity, tuple(sorted(int(a) for a in seams)))


def family_from_spec(domain, rand_spec, rng, seams=None):
    """WarpFamily for the spec's randomize section, or None when there is none or its amplitude is 0.

    rand_spec: spec.RandomizeSpec or None. rng: the pipeline's generator, made from rand_spec.seed.
    """
    if rand_spec is None or rand_spec.amplitude == 0:
        return None
    if rand_spec.amplitude < 0 or not np.isfinite(rand_spec.amplitude):
        raise SpecError(f"randomize.amplitude: must be a finite number >= 0 (got {rand_spec.amplitude}, "
                        f"expected e.g. 0.25)")
    return warp_family(domain, rand_spec.control_points, rng, seams)
