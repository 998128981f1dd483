"""verify: certificates that the maps which shape the pieces do not fold.

verify_warp certifies the random warp R: D -> D (and, on failure, finds by bisection the largest amplitude of the
same family that certifies); verify_model certifies the model M and reports its handedness.

The certificates come from volpuzzle.spline.jacobian: det J of a polynomial (or rational) trivariate spline is
itself a spline, and the signs of its Bezier coefficients bound its sign (convex hull property); subdivision
tightens the bound until it proves the sign or finds a point of the other sign.
"""

import math

import numpy as np

from .errors import GeometryError, ModelError
from .spline import jacobian

_DEFAULT_DEPTH = 6


def _certify(vol, sign, max_depth, det_spline=None):
    """certify_positive / certify_negative, reusing an already computed JacobianSpline when given."""
    fn = jacobian.certify_positive if sign > 0 else jacobian.certify_negative
    return fn(vol, max_depth=max_depth, det_spline=det_spline)


def _absolute(cert):
    """The certificate's smallest coefficient in det J units (the kernel reports it relative to `scale`)."""
    return float(cert.min_coefficient) * float(cert.scale)


def _fmt_uvw(uvw):
    return "(" + ", ".join(f"{float(x):.3g}" for x in np.asarray(uvw, dtype=float).ravel()[:3]) + ")"


def _fmt_num(x):
    return f"{float(x):.3g}"


def _certifies(family, amplitude, max_depth):
    return _certify(family(amplitude), +1, max_depth).status == "proved"


def safe_amplitude(family, hi, max_depth=_DEFAULT_DEPTH, rel_tol=0.01, max_iter=16):
    """Largest amplitude in [0, hi] (to about rel_tol relative) whose R = family(amplitude) certifies det J > 0.

    Amplitude 0 is the identity, which always certifies. Returns hi when hi itself certifies. Otherwise it climbs
    from hi/64 in doublings to the first amplitude that fails, then bisects between the last success and that
    failure: climbing from below finds the first threshold even where certification is not monotone in the
    amplitude (a fold can open and close again as the one drawn direction field grows). At most 6 + max_iter
    certifications after the first.
    """
    hi = float(hi)
    if hi <= 0 or _certifies(family, hi, max_depth):
        return max(hi, 0.0)
    lo = 0.0
    for k in range(6, 0, -1):
        a = hi / 2.0 ** k
        if not _certifies(family, a, max_depth):
            hi = a
            break
        lo = a
    for _ in range(max_iter):
        if lo > 0 and hi - lo <= rel_tol * lo:
            break
        mid = 0.5 * (lo + hi)
        if _certifies(family, mid, max_depth):
            lo = mid
        else:
            hi = mid
    return lo


def _round_down(x, digits):
    if x <= 0:
        return 0.0
    scale = 10.0 ** (digits - 1 - math.floor(math.log10(x)))
    return math.floor(x * scale) / scale


def _quotable(family, safe, max_depth):
    """A short number <= safe that certifies too, for the message (the user will copy it into the spec)."""
    for digits in (2, 3):
        r = _round_down(safe, digits)
        if r > 0 and (r == safe or _certifies(family, r, max_depth)):
            return r
    return safe


def verify_warp(family, amplitude, max_depth=_DEFAULT_DEPTH):
    """Certify that R = family(amplitude) maps D one-to-one onto D.

    Why det J > 0 is enough: R keeps D's boundary (corners and edges fixed, each face mapped into itself, see
    randomize), so on the boundary R is homotopic to the identity through (1 - t) x + t R(x), which stays in each
    (convex) face: R restricted to the boundary has degree one, hence deg(R, D, y) = 1 for every interior y. With
    det J > 0 on the closed box, R is a local homeomorphism and every preimage counts +1 in that degree, so each
    interior point has exactly one preimage: R is a bijection of D onto D (a diffeomorphism of the interior). The
    certificate is a lower bound on det J from Bezier coefficients after subdivision, so "proved" is exact up to
    floating point, not a sampled claim.

    Returns {"amplitude", "jacobian_min_coefficient", "bijective": True, "status": "proved"}. Raises GeometryError,
    phrased as a spec problem on randomize.amplitude, with the smallest coefficient, where it is, and the largest
    amplitude of the same family that certifies.
    """
    amplitude = float(amplitude)
    R = family(amplitude)
    cert = _certify(R, +1, max_depth)
    if cert.status == "proved":
        return {"amplitude": amplitude, "jacobian_min_coefficient": _absolute(cert),
                "bijective": True, "status": cert.status}
    safe = _quotable(family, safe_amplitude(family, amplitude, max_depth), max_depth)
    what = {"disproved": "folds the map R",
            "degenerate": "flattens the map R against D's boundary (det J reaches 0 there)"}.get(
        cert.status, "cannot be certified one-to-one")
    where = _fmt_uvw(cert.where_uvw) if cert.where_uvw is not None else "(unknown)"
    detail = f"smallest Jacobian coefficient {_fmt_num(_absolute(cert))} at uvw {where}"
    if cert.status == "disproved" and cert.value is not None:
        detail += f", det J = {_fmt_num(cert.value)} there"
    raise GeometryError(
        f"randomize.amplitude: {amplitude:g} {what} ({detail}); at most {safe:g} certifies for this seed and "
        f"control_points (got {amplitude:g}, expected <= {safe:g})")


# --- the model ---------------------------------------------------------------------------------------------------

def _det(vol, uvw):
    return np.linalg.det(vol.derivatives(np.asarray(uvw, dtype=float).reshape(-1, 3)))


def _sample_grid(vol, k=9):
    dom = vol.domain_array
    t = (np.arange(k) + 0.5) / k
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    return dom[0] + g * (dom[1] - dom[0])


def _sign_change_near(vol, uvw_bad, bad_sign):
    """A point near where det J crosses zero: bisect from uvw_bad towards the nearest sample of the other sign."""
    uvw_bad = np.asarray(uvw_bad, dtype=float).ravel()
    pts = _sample_grid(vol)
    d = _det(vol, pts)
    other = pts[np.sign(d) == -bad_sign]
    if len(other) == 0:
        return uvw_bad
    good = other[np.argmin(np.linalg.norm(other - uvw_bad, axis=1))]
    a, b = uvw_bad, good
    for _ in range(30):
        m = 0.5 * (a + b)
        if np.sign(_det(vol, m)[0]) == bad_sign:
            a = m
        else:
            b = m
    return 0.5 * (a + b)


def verify_model(vol, max_depth=_DEFAULT_DEPTH):
    """Certify the model M (control points in mm): its det J keeps one sign on D.

    Returns {"handedness": "right" | "left", "degenerate": bool, "certified": bool, "notes": [str],
    "jacobian_min_coefficient", "jacobian_max_coefficient"} (the coefficient bounds of det J over the whole domain).
    A left-handed model (det J < 0 everywhere) is valid. A degenerate axis (det J = 0 on a face, as at a sphere's
    pole or a cylinder's axis) is allowed with a note. A fold (det J changes sign) raises ModelError with the place.
    """
    bez = jacobian.jacobian_bezier(vol)
    # For a rational M the coefficients bound W^4 det J; lower/upper are the kernel's bounds on det J itself.
    lo, hi = float(bez.lower), float(bez.upper)
    if lo == hi == 0.0 and (bez.min != 0 or bez.max != 0):
        lo, hi = float(bez.min), float(bez.max)
    out = {"jacobian_min_coefficient": lo, "jacobian_max_coefficient": hi,
           "degenerate": False, "certified": True, "notes": []}
    pos = _certify(vol, +1, max_depth, bez)
    if pos.status in ("proved", "degenerate"):
        out["handedness"] = "right"
        cert = pos
    else:
        neg = _certify(vol, -1, max_depth, bez)
        if neg.status in ("proved", "degenerate"):
            out["handedness"] = "left"
            cert = neg
        elif pos.status == "disproved" and neg.status == "disproved":
            # Both signs occur. Report the minority sign's place, moved to where det J crosses zero.
            s = np.sign(_det(vol, _sample_grid(vol)))
            majority = 1.0 if np.count_nonzero(s > 0) >= np.count_nonzero(s < 0) else -1.0
            bad = pos if majority > 0 else neg
            uvw = _sign_change_near(vol, bad.where_uvw, -majority)
            xyz = vol.evaluate(uvw.reshape(1, 3))[0]
            raise ModelError(
                f"model folds: det J changes sign near uvw {_fmt_uvw(uvw)}, xyz {_fmt_uvw(xyz)} mm "
                f"(det J ranges over about [{_fmt_num(lo)}, {_fmt_num(hi)}]; expected one sign on the "
                f"whole domain: fix the control points there)")
        else:
            # Neither sign proved nor a sign change found within max_depth: det J touches zero somewhere inside.
            # Accept on the evidence of the samples, but say the certificate is missing.
            s = np.sign(_det(vol, _sample_grid(vol, 13)))
            if np.all(s >= 0) or np.all(s <= 0):
                out["handedness"] = "right" if np.count_nonzero(s > 0) >= np.count_nonzero(s < 0) else "left"
                out["certified"] = False
                c = pos if pos.status != "disproved" else neg
                out["notes"].append(
                    f"det J could not be certified to keep one sign (smallest coefficient "
                    f"{_fmt_num(_absolute(c))} near uvw {_fmt_uvw(c.where_uvw)}); sampled values agree in sign")
                return out
            bad = pos if pos.status == "disproved" else neg
            raise ModelError(
                f"model folds: det J changes sign near uvw {_fmt_uvw(bad.where_uvw)}, xyz "
                f"{_fmt_uvw(vol.evaluate(np.asarray(bad.where_uvw, dtype=float).reshape(1, 3))[0])} mm "
                f"(expected one sign on the whole domain)")
    if cert.status == "degenerate":
        out["degenerate"] = True
        where = f" near uvw {_fmt_uvw(cert.where_uvw)}" if cert.where_uvw is not None else ""
        out["notes"].append(
            f"det J vanishes on part of the boundary{where} (a collapsed edge or face, as at a pole); allowed, "
            f"the pieces there meet in a line or point")
    return out
