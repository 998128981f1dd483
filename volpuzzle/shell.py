"""`model.shell`: the trivariate between a NURBS surface and its offsets (the paper's duck and Earth).

The surface S is scaled to mm first (units, then `size` on its bounding box, less a wall outside it), so the thickness
t is millimetres of the printed object. `side` puts the wall inside S (inward, the default: S is the outside), outside
it (outward: S is the inside), half each way (both), or a share s in [0, 1] of it outside: the walls are S - (1 - s) t n
and S + s t n. The shell is ruled along w: w = 0 the inner wall, w = 1 the outer one, so w_max is the outside (where
a texture goes).

A true offset S + d n is not a NURBS in general. It is represented on S's own rational basis (same weights, same
knots, refined): its control points are a least-squares fit to samples of the true offset, the knots halved (for
both walls together) until the largest deviation on a denser check grid is at most a quarter of output.tolerance (or
four rounds are done). When the offset lies in that space (a sphere: the offset is S scaled about its centre) the fit
is exact to round-off. Shifting S's control points along the normal, the simpler construction, is measured alongside
and reported, and is orders of magnitude worse on a freeform surface.

A closed direction (first and last rows of control points equal) keeps its first and last rows tied, so the shell
closes exactly; a collapsed row (a pole: every control point the same) stays collapsed on both walls. Where one
direction is closed it becomes v and the other u, as in the sphere shell (u polar, v azimuth), and u is reversed when
needed so that the shell is right-handed.

An inward wall folds where it is thicker than the radius of curvature of a part of S that bends round the inside (1 /
the largest positive principal curvature with the outward normal: a ridge), an outward wall where it is thicker than
the radius of a part that bends round the outside (a hollow, a crease): the Jacobian certificate of the shell refuses
either, and the message names the place, the bend that limits it and the thickest shell with the same side that
certifies.
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
    """(n, 2) -> (n, 3): S - t n, n the unit normal along S_u x S_v (outward after arrange); a negative t is an
    outward offset."""
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
    x = spsolve(ata, a.T @ target, permc_spec="MMD_AT_PLUS_A")  # ata is symmetric: ~4x COLAMD's time here
    x = np.asarray(x).reshape(n, 3)
    return Surface(surf.degrees, surf.knots, x[var], surf.weights)


def distance_to(surf, x, uv, iterations=20):
    """Distance from points x (n, 3) to surf, by Newton from the parameters uv (n, 2) of a nearby foot point
    (clamped to the domain) -> (n,). Newton, not Gauss-Newton: from a point t beyond a hollow of radius R < t (an
    inward offset in a crease, an outward one round a tight ridge) Gauss-Newton's step is 1 + t / R times too long
    and diverges; a step that does not bring the surface nearer is halved. Compiled (each point alone, the same
    steps: ~100x) when numba is there; the numpy loop below is the reference."""
    dist = surf.distance_compiled(x, uv, iterations)
    return dist if dist is not None else _distance_numpy(surf, x, uv, iterations)


def _distance_numpy(surf, x, uv, iterations=20):
    dom = np.array(surf.domain)
    uv = np.array(uv, dtype=float)
    dist = np.linalg.norm(surf.evaluate(uv) - x, axis=1)
    active = np.arange(len(uv))
    for _ in range(iterations):
        d = surf.derivatives(uv[active], 2)
        r = d[:, 0, 0] - x[active]
        su, sv = d[:, 1, 0], d[:, 0, 1]
        a, b, c = (su * su).sum(1), (su * sv).sum(1), (sv * sv).sum(1)
        ha, hb, hc = a + (r * d[:, 2, 0]).sum(1), b + (r * d[:, 1, 1]).sum(1), c + (r * d[:, 0, 2]).sum(1)
        convex = (ha > 0) & (ha * hc - hb * hb > 0)  # else Gauss-Newton's matrix, positive but for poles
        a, b, c = np.where(convex, ha, a), np.where(convex, hb, b), np.where(convex, hc, c)
        ru, rv = (su * r).sum(1), (sv * r).sum(1)
        reg = 1e-12 * (np.abs(a) + np.abs(c))  # a pole: S_v = 0
        a, c = a + reg, c + reg
        det = a * c - b * b
        step = np.stack([(c * ru - b * rv) / det, (a * rv - b * ru) / det], 1)
        new, nd = uv[active].copy(), dist[active].copy()
        todo = np.arange(len(active))
        for _halve in range(8):
            trial = np.clip(uv[active[todo]] - step[todo], dom[:, 0], dom[:, 1])
            td = np.linalg.norm(surf.evaluate(trial) - x[active[todo]], axis=1)
            take = td <= nd[todo]
            new[todo[take]], nd[todo[take]] = trial[take], td[take]
            todo = todo[~take]
            if not len(todo):
                break
            step[todo] *= 0.5
        gain = dist[active] - nd
        uv[active], dist[active] = new, nd
        active = active[gain > 1e-9]  # converged points stop (at a pole v may still wander: it moves nothing)
        if not len(active):
            break
    return dist


def offset_error(surf, inner, thickness):
    """Largest deviation of a fitted offset (inner, or outer for a negative thickness) from the true offset,
    | distance(offset(u, v), S) - |t| | in mm, on a check grid off the fit's samples -> (error, uv of it). Measured
    as a distance, not at equal parameters: at a cone-like pole the normals fan out and the offset there is a piece
    of sphere, not one point per (u, v)."""
    u, v = _samples(surf, 0, _CHECK_PER_SPAN, 0.37), _samples(surf, 1, _CHECK_PER_SPAN, 0.37)
    uv = np.stack(np.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)
    d = np.abs(distance_to(surf, inner.evaluate(uv), uv) - abs(thickness))
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


def _fitted(surf, depth):
    """The surface depth mm inside surf (outside for a negative depth) on surf's basis -> (Surface, error mm, uv of
    it); surf itself for depth 0 (exact)."""
    if depth == 0.0:
        return surf, 0.0, np.array(surf.domain, float).mean(axis=1)
    off = fit_offset(surf, depth)
    err, where = offset_error(surf, off, depth)
    return off, err, where


def offset_surfaces(surf, inward, outward, target, max_rounds=_MAX_ROUNDS):
    """The walls inward mm inside and outward mm outside surf, fitted and refined together until each is within
    target mm of its true offset (or stops improving by a tenth) -> (inner, outer, {method, offset_max_error_mm,
    ...}); both on the same knots and weights."""
    rounds, best = [], None
    for r in range(max_rounds):
        inner, e_in, at_in = _fitted(surf, inward)
        outer, e_out, at_out = _fitted(surf, -outward)
        err = max(e_in, e_out)
        rounds.append({"control_points": list(surf.shape), "max_error_mm": err})
        if best is None or err < best[0]:
            best = (err, surf, inner, outer, (e_in, at_in), (e_out, at_out))
        stalled = len(rounds) > 1 and err > 0.9 * rounds[-2]["max_error_mm"]
        if err <= target or r == max_rounds - 1 or stalled:
            break
        surf = _refined(surf)
    err, surf, inner, outer, fit_in, fit_out = best  # refining past a feature the fit cannot follow can be worse
    fitted = [(name, t, e) for name, t, e in (("inner", inward, fit_in), ("outer", -outward, fit_out)) if t != 0.0]
    name, depth, (_, where) = max(fitted, key=lambda f: f[2][0])  # the worst fitted wall is the one reported
    naive = offset_error(surf, _normal_shift(surf, depth), depth)[0]  # of the reported wall: the comparison
    exact = err <= 1e-6 * _size(surf)  # round-off, and the normals taken a hair off the poles
    info = {"method": "exact (the offset lies in the surface's rational space)" if exact else
            "least-squares fit on the surface's rational basis, knots halved until within the target",
            "offset_max_error_mm": err, "offset_error_surface": name,
            "offset_error_uv": [float(x) for x in where],
            "offset_error_xyz_mm": [float(x) for x in surf.evaluate(np.reshape(where, (1, 2)))[0]],
            "offset_target_mm": target, "fit_rounds": rounds, "normal_shift_max_error_mm": naive}
    for n, _, (e, _where) in fitted:
        info[f"{n}_offset_max_error_mm"] = e
    return inner, outer, info


def shell_volume(outer, inner):
    """The ruled trivariate: w = 0 the inner surface, w = 1 the outer one (same knots and weights)."""
    cps = np.stack([inner.control_points, outer.control_points], axis=2)
    w = None if outer.weights is None else np.stack([outer.weights] * 2, axis=2)
    return Volume(outer.degrees + (1,), outer.knots + (_W,), cps, w)


# --- curvature and folds ------------------------------------------------------------------------------------
def tightest_bends(surf, per_span=16):
    """Where S bends most tightly round its inside (the largest positive principal curvature with the outward
    normal: an inward wall folds there) and round its outside (the most negative one, a hollow such as a neck: an
    outward wall folds there) -> {"inward": (radius mm, uv (2,), xyz (3,)), "outward": (...)}. Radius inf where S
    bends nowhere that way (a plane)."""
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
    root = np.sqrt(np.maximum(H * H - K, 0.0))
    out = {}
    for side, bend in (("inward", H + root), ("outward", -(H - root))):
        bend = np.where(ok, bend, -np.inf)
        k = int(np.argmax(bend))
        radius = float(1.0 / bend[k]) if bend[k] > 0 else float("inf")
        out[side] = (radius, uv[k], surf.evaluate(uv[k:k + 1])[0])
    return out


def tightest_inner_bend(surf, per_span=16):
    """Where S bends most tightly round its inside -> (radius mm, uv (2,), xyz (3,)); see tightest_bends."""
    return tightest_bends(surf, per_span)["inward"]


def _certify(vol):
    from .spline.jacobian import certify_positive

    return certify_positive(vol)


def _fmt(x):
    return f"{float(x):.3g}"


SIDES = {"inward": 0.0, "outward": 1.0, "both": 0.5}  # the share of the wall outside the surface


def outward_share(side):
    """model.shell.side -> the share (0..1) of the thickness that lies outside the surface."""
    return float(SIDES[side]) if isinstance(side, str) else float(side)


def _walls(thickness, share):
    """(mm inside, mm outside) the surface."""
    out = float(thickness) * share
    return float(thickness) - out, out


def _certifies(surf, thickness, share, target, max_rounds=_MAX_ROUNDS):
    inner, outer, _ = offset_surfaces(surf, *_walls(thickness, share), target, max_rounds=max_rounds)
    return _certify(shell_volume(outer, inner)).ok


def _thickest(surf, hi, share, target):
    """The largest thickness below hi, rounded down to 0.1 mm, whose shell certifies with the same share outside the
    surface: bisection on coarse fits (within ~3%), then the full fit of the build, stepping down while it folds (a
    finer fit follows a tight bend closer, so it can fold a little sooner)."""
    lo = 0.0
    for _ in range(6):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _certifies(surf, mid, share, target, max_rounds=2) else (lo, mid)
        if hi - lo < 0.03 * hi:
            break
    t = np.floor(lo * 10) / 10
    for _ in range(4):
        if t <= 0 or _certifies(surf, t, share, target):
            break
        t = np.round(t - 0.1, 1)
    return max(float(t), 0.0)


def _binding_bend(bends, share):
    """The bend that limits a wall with this share outside: (side, radius, uv, xyz, thickness at which it folds)."""
    limits = []
    for side, part in (("inward", 1.0 - share), ("outward", share)):
        radius, uv, xyz = bends[side]
        if part > 0:
            limits.append((side, radius, uv, xyz, radius / part))
    return min(limits, key=lambda x: x[-1])


def _side_words(share):
    """How the message names the wall's side: '' (inward, the default), 'outward ', 'two-sided ', '30% outward '."""
    words = {0.0: "", 1.0: "outward ", 0.5: "two-sided "}
    return words.get(share, f"{_fmt(share * 100)}% outward ")


def make_shell(surf, thickness, target, key="model.shell.thickness", side="inward"):
    """The shell of thickness mm round surf (already in mm): inside it (side inward), outside (outward), half each
    way (both) or a share (0..1) outside -> Shell. Raises ModelError where it folds."""
    share = outward_share(side)
    inward, outward = _walls(thickness, share)
    surf, layout = arrange(surf)
    inner, outer, fit = offset_surfaces(surf, inward, outward, target)
    vol = shell_volume(outer, inner)
    cert = _certify(vol)
    bends = tightest_bends(surf)
    if not cert.ok:
        way, radius, uv, xyz, limit = _binding_bend(bends, share)
        where_uvw = np.asarray(cert.where_uvw, float)
        at = vol.evaluate(where_uvw.reshape(1, 3))[0]
        fits = _thickest(surf, min(thickness, limit), share, target)
        words = _side_words(share)
        if fits > 0:
            advice = f"at most {_fmt(fits)} mm, the thickest {words}shell that certifies"
        else:  # "a smaller thickness" would send the user bisecting down to nothing
            other = "outward" if way == "inward" else "inward"
            alt = (f", or model.shell.side: {other}, whose tightest bend ({_fmt(bends[other][0])} mm) may take it"
                   if share in (0.0, 1.0) and bends[other][0] > thickness else "")
            advice = (f"a surface without so tight a bend: no {words}shell of 0.1 mm or more certifies (mend the "
                      f"surface there{alt})")
        round_ = "its inside" if way == "inward" else "its outside (a hollow)"
        raise ModelError(
            f"{key}: a {_fmt(thickness)} mm {_side_words(share)}shell folds: its Jacobian changes sign near xyz "
            f"({', '.join(_fmt(c) for c in at)}) mm; the surface bends round {round_} with a radius of "
            f"{_fmt(radius)} mm at xyz ({', '.join(_fmt(c) for c in xyz)}) mm, uv ({_fmt(uv[0])}, {_fmt(uv[1])}) "
            f"(got {_fmt(thickness)}, expected {advice})")
    info = {"thickness_mm": float(thickness), "side": side if isinstance(side, str) else float(side),
            "inward_mm": inward, "outward_mm": outward, **layout, **fit,
            "smallest_inner_radius_mm": _finite(bends["inward"][0]),
            "smallest_outer_radius_mm": _finite(bends["outward"][0]),
            "control_points": list(vol.shape)}
    return Shell(vol, outer, info)


def _finite(x):
    return float(x) if np.isfinite(x) else None


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
    """model.shell from the spec -> (Shell, mm per model unit, meta of the surface file). `size` is the printed
    shell's: a wall outside the surface widens the box by its thickness each side (the offset's support is the
    surface's plus t), so the surface is sized that much smaller."""
    from .io import load_surface_with_meta

    side = getattr(shell_spec, "side", "inward")
    _, outward = _walls(shell_spec.thickness, outward_share(side))
    if size is not None and size <= 2 * outward:
        raise ModelError(f"model.size: {_fmt(size)} mm leaves no surface inside a wall {_fmt(outward)} mm outside "
                         f"it each side (got {_fmt(size)}, expected more than {_fmt(2 * outward)})")
    surf, meta = load_surface_with_meta(shell_spec.surface, patch=shell_spec.patch)
    surf, scale = scale_to_mm(surf, unit_scale, None if size is None else size - 2 * outward)
    shell = make_shell(surf, shell_spec.thickness, target=0.25 * tolerance, side=side)
    return shell, scale, meta
