"""`model.shell`: the trivariate between a NURBS surface and its inward offset (the paper's duck and Earth).

The surface S is scaled to mm first (units, then `size` on its bounding box), so the thickness t is millimetres of
the printed object. The shell is ruled along w: w = 0 the inner surface, w = 1 the outer surface S, so w_max is
the outside (where a texture goes).

The true offset S - t n is not a NURBS in general. It is represented on S's own rational basis (same weights, same
knots, refined): the inner control points are a least-squares fit to samples of the true offset, the knots halved
until the largest deviation on a denser check grid is at most a quarter of output.tolerance (or four rounds are
done). When the offset lies in that space (a sphere: the offset is S scaled about its centre) the fit is exact to
round-off. Shifting S's control points along the normal, the simpler construction, is measured alongside and
reported, and is orders of magnitude worse on a freeform surface.

A closed direction (first and last rows of control points equal) keeps its first and last inner rows tied, so the
shell closes exactly; a collapsed row (a pole: every control point the same) stays collapsed on the inner surface.
Where one direction is closed it becomes v and the other u, as in the sphere shell (u polar, v azimuth), and u is
reversed when needed so that the shell is right-handed.

An inward offset folds where t exceeds the radius of curvature of a part of S that bends round the inside (1 / the
largest positive principal curvature with the outward normal): the Jacobian certificate of the shell refuses it, and
the message names the place and the thickest shell that certifies.
"""

from dataclasses import dataclass

import numpy as np

from .errors import ModelError
from .spline import basis
from .spline.knots import breaks as knot_breaks
from .spline.surface import Surface
from .spline.volume import Volume

_W = np.array([0.0, 0.0, 1.0, 1.0])
_FIT_PER_SPAN = 4  # samples per knot span and direction for the fit
_CHECK_PER_SPAN = 7  # and for measuring it, placed apart from the fit's samples
_MAX_ROUNDS = 4


@dataclass(frozen=True)
class Shell:
    """volume: the shell in mm (w = 0 inner, w = 1 outer); surface: the outer surface as used (mm, axes arranged);
    info: what report.json says of it."""

    volume: Volume
    surface: Surface
    info: dict


# --- the surface's structure ---------------------------------------------------------------------------------
def _size(surf):
    cps = surf.control_points.reshape(-1, 3)
    return float(np.linalg.norm(cps.max(0) - cps.min(0))) or 1.0


def _samples(surf, axis, per_span, shift=0.0):
    """Parameters along one axis: per_span points in each knot span (shift in (0, 1) moves them off the knots),
    plus the ends and the knots themselves."""
    br = knot_breaks(surf.knots[axis], surf.degrees[axis])
    s = (np.arange(per_span) + 0.5 + shift) / (per_span + 1) if shift else np.arange(per_span) / per_span
    t = (br[:-1, None] + s[None] * np.diff(br)[:, None]).ravel()
    return np.unique(np.concatenate([t, br]))


def grid_points(surf, per_span=8):
    """Points of S on a grid of per_span points per span -> (a, b, 3), and the parameters (a,), (b,)."""
    u, v = _samples(surf, 0, per_span), _samples(surf, 1, per_span)
    return surf.evaluate_grid(u, v), u, v


def closed_axes(surf, rel_tol=1e-6):
    """Axes (0 u, 1 v) whose first and last boundary curves coincide in space."""
    out = []
    tol = rel_tol * _size(surf)
    for a in range(2):
        t = _samples(surf, 1 - a, 5, shift=0.13)
        dom = surf.domain[a]
        lo = np.empty((len(t), 2))
        lo[:, a], lo[:, 1 - a] = dom[0], t
        hi = lo.copy()
        hi[:, a] = dom[1]
        if np.max(np.linalg.norm(surf.evaluate(lo) - surf.evaluate(hi), axis=1)) <= tol:
            out.append(a)
    return out


def collapsed_rows(surf, rel_tol=1e-9):
    """Boundary rows whose control points all coincide (poles) -> list of (axis, side 0 | -1): the row at the min
    (0) or max (-1) end of `axis`."""
    out = []
    tol = rel_tol * _size(surf)
    cps = surf.control_points
    for a in range(2):
        for side in (0, -1):
            row = cps[side] if a == 0 else cps[:, side]
            if np.max(np.linalg.norm(row - row[0], axis=1)) <= tol:
                out.append((a, side))
    return out


def _enclosed(surf, per_span=6):
    """(1/3) * the flux of x through S along S_u x S_v: the enclosed volume, positive when S_u x S_v points out
    of a closed surface. Midpoint rule on a fine grid: only its sign and rough size are used."""
    u, v = _samples(surf, 0, per_span, 0.5), _samples(surf, 1, per_span, 0.5)
    uu, vv = np.meshgrid(0.5 * (u[1:] + u[:-1]), 0.5 * (v[1:] + v[:-1]), indexing="ij")
    du = np.diff(u)[:, None] * np.diff(v)[None, :]
    x, d = surf.evaluate_with_derivatives(np.stack([uu.ravel(), vv.ravel()], 1))
    flux = np.einsum("ni,ni->n", x, np.cross(d[:, :, 0], d[:, :, 1]))
    return float(np.sum(flux * du.ravel()) / 3.0)


def _outward_sign(surf, closed):
    """+1 when S_u x S_v points out of the solid the shell wraps, -1 when it points in."""
    if closed:
        vol = _enclosed(surf)
        return 1 if vol > 0 else -1
    # an open surface: 'inward' is toward the middle of its control net, on average
    pts, u, v = grid_points(surf, 3)
    uv = np.stack(np.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)
    n = surf.normals(uv)
    c = surf.control_points.reshape(-1, 3).mean(0)
    return 1 if np.mean(np.einsum("ni,ni->n", pts.reshape(-1, 3) - c, n)) >= 0 else -1


def arrange(surf):
    """Put a lone closed direction on v and orient S_u x S_v outward -> (surface, {closed, poles, swapped,
    reversed_u})."""
    closed = closed_axes(surf)
    swapped = closed == [0]
    if swapped:
        surf = surf.swapped()
        closed = [1]
    flip = _outward_sign(surf, bool(closed) or len(collapsed_rows(surf)) == 2) < 0
    if flip:
        surf = surf.reversed(0)
    return surf, {"closed_axes": ["uv"[a] for a in closed_axes(surf)],
                  "poles": [f"{'uv'[a]}_{'min' if s == 0 else 'max'}" for a, s in collapsed_rows(surf)],
                  "axes_swapped": bool(swapped), "u_reversed": bool(flip)}


# --- the offset ----------------------------------------------------------------------------------------------
def true_offset(surf, uv, thickness):
    """(n, 2) -> (n, 3): S - t n, n the unit normal along S_u x S_v (outward after arrange)."""
    return surf.evaluate(uv) - thickness * surf.normals(uv)


def _unknowns(surf):
    """Index of the unknown inner control point for each (i, j) -> (n_u, n_v) int, count: poles share one unknown,
    a closed direction's last row is its first."""
    n_u, n_v = surf.shape
    var = np.arange(n_u * n_v).reshape(n_u, n_v)
    for a, side in collapsed_rows(surf):
        if a == 0:
            var[side] = var[side, 0]
        else:
            var[:, side] = var[0, side]
    for a in closed_axes(surf):
        if a == 0:
            var[-1] = var[0]
        else:
            var[:, -1] = var[:, 0]
    ids, var = np.unique(var, return_inverse=True)
    return var.reshape(n_u, n_v), len(ids)


def _rational_rows(surf, u, v):
    """Sparse (len(u)*len(v), n_u*n_v) matrix of the rational basis R_kl(u_i, v_j) on the grid u x v."""
    from scipy import sparse

    loc = []
    for a, t in enumerate((u, v)):
        p, k = surf.degrees[a], surf.knots[a]
        span = basis.find_span(k, p, t)
        loc.append((span[:, None] - p + np.arange(p + 1), basis.basis_functions(k, p, t, span)))
    (iu, bu), (iv, bv) = loc
    w = np.ones(surf.shape) if surf.weights is None else surf.weights
    n_v = surf.shape[1]
    # (a, b, pu+1, pv+1) products and column indices
    val = bu[:, None, :, None] * bv[None, :, None, :] * w[iu[:, None, :, None], iv[None, :, None, :]]
    val /= val.sum(axis=(2, 3), keepdims=True)
    col = iu[:, None, :, None] * n_v + iv[None, :, None, :]
    rows = np.broadcast_to(np.arange(len(u) * len(v)).reshape(len(u), len(v), 1, 1), val.shape)
    return sparse.csr_matrix((val.ravel(), (rows.ravel(), col.ravel())), shape=(len(u) * len(v), surf.shape[0] * n_v))


def fit_offset(surf, thickness):
    """Least-squares inner surface on surf's rational basis -> Surface (same knots and weights)."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    u, v = _samples(surf, 0, _FIT_PER_SPAN), _samples(surf, 1, _FIT_PER_SPAN)
    uv = np.stack(np.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)
    target = true_offset(surf, uv, thickness)
    var, n = _unknowns(surf)
    tie = sparse.csr_matrix((np.ones(var.size), (np.arange(var.size), var.ravel())), shape=(var.size, n))
    a = _rational_rows(surf, u, v) @ tie
    ata = (a.T @ a).tocsc()
    x = spsolve(ata, a.T @ target)
    x = np.asarray(x).reshape(n, 3)
    return Surface(surf.degrees, surf.knots, x[var], surf.weights)


def distance_to(surf, x, uv, iterations=12):
    """Distance from points x (n, 3) to surf, by Gauss-Newton from the parameters uv (n, 2) of a nearby foot point
    (clamped to the domain) -> (n,)."""
    dom = np.array(surf.domain)
    uv = np.array(uv, dtype=float)
    active = np.arange(len(uv))
    tiny = 1e-9 * np.max(dom[:, 1] - dom[:, 0])  # about 1e-7 mm on the surface
    for _ in range(iterations):
        p, d = surf.evaluate_with_derivatives(uv[active])
        r = p - x[active]
        su, sv = d[:, :, 0], d[:, :, 1]
        a, b, c = (su * su).sum(1), (su * sv).sum(1), (sv * sv).sum(1)
        ru, rv = (su * r).sum(1), (sv * r).sum(1)
        reg = 1e-12 * (a + c)  # a pole: S_v = 0
        a, c = a + reg, c + reg
        det = a * c - b * b
        step = np.stack([(c * ru - b * rv) / det, (a * rv - b * ru) / det], 1)
        uv[active] = np.clip(uv[active] - step, dom[:, 0], dom[:, 1])
        active = active[np.max(np.abs(step), axis=1) > tiny]  # converged points stop
        if not len(active):
            break
    return np.linalg.norm(surf.evaluate(uv) - x, axis=1)


def offset_error(surf, inner, thickness):
    """Largest deviation of the inner surface from the true offset, | distance(inner(u, v), S) - t | in mm, on a
    check grid off the fit's samples -> (error, uv of it). Measured as a distance, not at equal parameters: at a
    cone-like pole the normals fan out and the offset there is a piece of sphere, not one point per (u, v)."""
    u, v = _samples(surf, 0, _CHECK_PER_SPAN, 0.37), _samples(surf, 1, _CHECK_PER_SPAN, 0.37)
    uv = np.stack(np.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)
    d = np.abs(distance_to(surf, inner.evaluate(uv), uv) - thickness)
    k = int(np.argmax(d))
    return float(d[k]), uv[k]


_SPLIT_AT = 0.5 + 0.0137  # a little off the middle: a midpoint knot often lands a hair beside a uniform split


def _refined(surf):
    """surf with a knot inserted in (about) the middle of every span, both directions (exact). A knot 1e-6 beside a
    cut leaves sliver faces in the tessellation, and midpoints of rounded knots (0.523599, 1.0472) do that."""
    for a in range(2):
        br = knot_breaks(surf.knots[a], surf.degrees[a])
        for t in br[:-1] + _SPLIT_AT * np.diff(br):
            surf = surf.insert_knot(a, t)
    return surf


def _normal_shift(surf, thickness):
    """The simple construction, for comparison: control points moved by t along the normal at their Greville
    points."""
    g = []
    for a in range(2):
        p, k = surf.degrees[a], surf.knots[a]
        g.append(np.array([np.mean(k[i + 1:i + p + 1]) for i in range(surf.shape[a])]))
    uv = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 2)
    n = surf.normals(uv).reshape(surf.shape + (3,))
    return Surface(surf.degrees, surf.knots, surf.control_points - thickness * n, surf.weights)


def inner_surface(surf, thickness, target, max_rounds=_MAX_ROUNDS):
    """The fitted inner surface, refining until its error is at most target mm (or stops improving by a tenth).
    -> (outer on the inner's knots, inner, {method, offset_max_error_mm, ...})."""
    rounds, best = [], None
    for r in range(max_rounds):
        inner = fit_offset(surf, thickness)
        err, where = offset_error(surf, inner, thickness)
        rounds.append({"control_points": list(surf.shape), "max_error_mm": err})
        if best is None or err < best[0]:
            best = (err, where, surf, inner)
        stalled = len(rounds) > 1 and err > 0.9 * rounds[-2]["max_error_mm"]
        if err <= target or r == max_rounds - 1 or stalled:
            break
        surf = _refined(surf)
    err, where, surf, inner = best  # refining past a feature the fit cannot follow can make it worse
    naive, _ = offset_error(surf, _normal_shift(surf, thickness), thickness)
    exact = err <= 1e-6 * _size(surf)  # round-off, and the normals taken a hair off the poles
    info = {"method": "exact (the offset lies in the surface's rational space)" if exact else
            "least-squares fit on the surface's rational basis, knots halved until within the target",
            "offset_max_error_mm": err, "offset_error_uv": [float(x) for x in where],
            "offset_error_xyz_mm": [float(x) for x in surf.evaluate(np.reshape(where, (1, 2)))[0]],
            "offset_target_mm": target, "fit_rounds": rounds,
            "normal_shift_max_error_mm": naive}
    return surf, inner, info


def shell_volume(outer, inner):
    """The ruled trivariate: w = 0 the inner surface, w = 1 the outer one (same knots and weights)."""
    cps = np.stack([inner.control_points, outer.control_points], axis=2)
    w = None if outer.weights is None else np.stack([outer.weights] * 2, axis=2)
    return Volume(outer.degrees + (1,), outer.knots + (_W,), cps, w)


# --- curvature and folds ------------------------------------------------------------------------------------
def tightest_inner_bend(surf, per_span=8):
    """Where S bends most tightly round its inside: the largest positive principal curvature (outward normal)
    -> (radius mm, uv (2,), xyz (3,)). Radius inf when S bends nowhere round the inside (a plane)."""
    u, v = _samples(surf, 0, per_span, 0.21), _samples(surf, 1, per_span, 0.21)
    uv = np.stack(np.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)
    d = surf.derivatives(uv, 2)
    su, sv, suu, suv, svv = d[:, 1, 0], d[:, 0, 1], d[:, 2, 0], d[:, 1, 1], d[:, 0, 2]
    n = np.cross(su, sv)
    ln = np.linalg.norm(n, axis=1)
    ok = ln > 1e-6 * np.maximum(np.linalg.norm(su, axis=1), np.linalg.norm(sv, axis=1)) ** 2
    n = n / np.maximum(ln, 1e-300)[:, None]
    E, F, G = (np.einsum("ni,ni->n", a, b) for a, b in ((su, su), (su, sv), (sv, sv)))
    # second fundamental form with the inward normal -n: positive where S bends round its inside
    L, M, N = (-np.einsum("ni,ni->n", a, n) for a in (suu, suv, svv))
    den = np.maximum(E * G - F * F, 1e-300)
    H = (E * N - 2 * F * M + G * L) / (2 * den)
    K = (L * N - M * M) / den
    kmax = H + np.sqrt(np.maximum(H * H - K, 0.0))
    kmax[~ok] = -np.inf
    k = int(np.argmax(kmax))
    radius = float(1.0 / kmax[k]) if kmax[k] > 0 else float("inf")
    return radius, uv[k], surf.evaluate(uv[k:k + 1])[0]


def _certify(vol):
    from .spline.jacobian import certify_positive

    return certify_positive(vol)


def _fmt(x):
    return f"{float(x):.3g}"


def _thickest(surf, hi, target):
    """The largest thickness below hi (within ~3%) whose shell certifies, by bisection from 0."""
    lo = 0.0
    for _ in range(6):
        mid = 0.5 * (lo + hi)
        o, inner, _ = inner_surface(surf, mid, target, max_rounds=2)
        if _certify(shell_volume(o, inner)).ok:
            lo = mid
        else:
            hi = mid
        if hi - lo < 0.03 * hi:
            break
    return lo


def make_shell(surf, thickness, target, key="model.shell.thickness"):
    """The shell of thickness mm inside surf (already in mm) -> Shell. Raises ModelError where it folds."""
    surf, layout = arrange(surf)
    outer, inner, fit = inner_surface(surf, thickness, target)
    vol = shell_volume(outer, inner)
    cert = _certify(vol)
    if not cert.ok:
        radius, uv, xyz = tightest_inner_bend(surf)
        where_uvw = np.asarray(cert.where_uvw, float)
        at = vol.evaluate(where_uvw.reshape(1, 3))[0]
        fits = _thickest(surf, min(thickness, radius), target)
        advice = f"at most {_fmt(np.floor(fits * 10) / 10)}" if fits > 0 else "a smaller thickness"
        raise ModelError(
            f"{key}: a {_fmt(thickness)} mm shell folds: its Jacobian changes sign near xyz "
            f"({', '.join(_fmt(c) for c in at)}) mm; the surface bends round its inside with a radius of "
            f"{_fmt(radius)} mm at xyz ({', '.join(_fmt(c) for c in xyz)}) mm, uv ({_fmt(uv[0])}, {_fmt(uv[1])}) "
            f"(got {_fmt(thickness)}, expected {advice} mm, the thickest shell that certifies)")
    radius, uv, xyz = tightest_inner_bend(surf)
    info = {"thickness_mm": float(thickness), **layout, **fit,
            "smallest_inner_radius_mm": radius if np.isfinite(radius) else None,
            "control_points": list(vol.shape)}
    return Shell(vol, outer, info)


def scale_to_mm(surf, unit_scale, size):
    """surf in model units -> (surf in mm, mm per model unit): units first, then `size` on the largest side of
    its bounding box (sampled densely: the shell lies inside the outer surface, so this is the shell's box)."""
    surf = surf.scaled(unit_scale) if unit_scale != 1.0 else surf
    scale = unit_scale
    if size is not None:
        pts, _, _ = grid_points(surf, 16)
        pts = pts.reshape(-1, 3)
        factor = size / float(np.max(pts.max(0) - pts.min(0)))
        surf, scale = surf.scaled(factor), scale * factor
    return surf, scale


def load_shell(shell_spec, unit_scale, size, tolerance):
    """model.shell from the spec -> (Shell, mm per model unit, meta of the surface file)."""
    from .io import load_surface_with_meta

    surf, meta = load_surface_with_meta(shell_spec.surface, patch=shell_spec.patch)
    surf, scale = scale_to_mm(surf, unit_scale, size)
    shell = make_shell(surf, shell_spec.thickness, target=0.25 * tolerance)
    return shell, scale, meta
