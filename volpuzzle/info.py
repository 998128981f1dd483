"""What `volpuzzle info MODEL` reports (SPEC section 3): a plain dict for --json, and a short text for people."""

import numpy as np

from .errors import VolpuzzleError

AXES = "uvw"


def _knot_summary(knots, degree):
    k = np.asarray(knots, float)
    lo, hi = float(k[degree]), float(k[-degree - 1])
    values, counts = np.unique(k[degree + 1:len(k) - degree - 1], return_counts=True)
    inner = [[float(v), int(c)] for v, c in zip(values, counts)]
    return {"count": int(len(k)), "domain": [lo, hi], "spans": len(inner) + 1,
            "interior": inner}  # [value, multiplicity]


def _sample_params(vol, per_span=3):
    """Parameters on every knot span (its ends plus interior points) -> three 1-D arrays."""
    out = []
    for a in range(3):
        br = np.unique(np.asarray(vol.knots[a])[vol.degrees[a]:len(vol.knots[a]) - vol.degrees[a]])
        t = [br]
        for s in range(1, per_span + 1):
            t.append(br[:-1] + (br[1:] - br[:-1]) * s / (per_span + 1))
        out.append(np.unique(np.concatenate(t)))
    return out


def _sampled_det(vol):
    """det J on a grid through every Bezier element -> (uvw (n, 3), det (n,))."""
    per_span = 3
    while True:
        g = _sample_params(vol, per_span)
        if per_span == 1 or np.prod([len(x) for x in g]) <= 60000:
            break
        per_span -= 1
    uu, vv, ww = np.meshgrid(*g, indexing="ij")
    uvw = np.stack([uu.ravel(), vv.ravel(), ww.ravel()], axis=1)
    return uvw, np.linalg.det(vol.derivatives(uvw))


def _jacobian_bounds(vol):
    """(min, max) of the Bezier coefficients of det J (kernel: spline.jacobian.jacobian_bezier)."""
    from .spline.jacobian import jacobian_bezier

    jb = jacobian_bezier(vol)
    for name in ("coefficients", "coefs", "coeffs"):
        if hasattr(jb, name):
            jb = getattr(jb, name)
            break
    if isinstance(jb, (list, tuple)):
        flat = np.concatenate([np.asarray(x, float).ravel() for x in jb]) if len(jb) else np.zeros(1)
    else:
        flat = np.asarray(jb, float).ravel()
    return float(flat.min()), float(flat.max())


def _handedness(vol, det):
    """'right' or 'left' from the kernel's orientation(vol); the sampled det J decides if that is unavailable."""
    try:
        from .spline.jacobian import orientation

        o = orientation(vol)
        if isinstance(o, str):
            if o in ("right", "left"):
                return o
        elif o is not None and float(o) != 0:
            return "right" if float(o) > 0 else "left"
    except (ImportError, VolpuzzleError):
        pass
    return "right" if float(np.sum(det)) >= 0 else "left"


def _fold(vol, uvw, det):
    """Where det J changes sign on the sample grid, or None: the worst point of the minority sign."""
    scale = float(np.max(np.abs(det))) if det.size else 0.0
    eps = 1e-9 * scale
    pos, neg = det > eps, det < -eps
    if not (pos.any() and neg.any()):
        return None
    minority = neg if pos.sum() >= neg.sum() else pos
    idx = np.flatnonzero(minority)
    i = int(idx[np.argmax(np.abs(det[idx]))])
    xyz = vol.evaluate(uvw[i:i + 1])[0]
    frac = float(minority.mean())
    return {"uvw": [float(x) for x in uvw[i]], "xyz": [float(x) for x in xyz], "det_j": float(det[i]),
            "fraction_of_samples": frac,
            "message": (f"the Jacobian changes sign: det J = {det[i]:.4g} at uvw = "
                        f"({', '.join(f'{x:.4g}' for x in uvw[i])}), xyz = ({', '.join(f'{x:.4g}' for x in xyz)}) "
                        f"against the opposite sign elsewhere ({frac:.1%} of the samples)")}


def model_info(vol, path=None, patch=0, meta=None):
    """Facts about one volume patch -> dict (JSON-ready). meta: the reader's dict (format, patches, units)."""
    from .spline.measure import bbox, volume
    from .spline.seams import find_seams

    meta = dict(meta or {})
    d = {}
    if path is not None:
        d["file"] = str(path)
    if meta.get("format"):
        d["format"] = meta["format"]
    d["patch"] = int(patch)
    if meta.get("patches") is not None:
        d["patches"] = int(meta["patches"])
    d["units"] = meta.get("units")
    d["degrees"] = [int(p) for p in vol.degrees]
    d["control_points"] = [int(n) for n in vol.shape]
    d["rational"] = bool(vol.is_rational)
    d["knots"] = {AXES[a]: _knot_summary(vol.knots[a], vol.degrees[a]) for a in range(3)}
    d["domain"] = [[float(lo), float(hi)] for lo, hi in vol.domain]
    seams = find_seams(vol)
    d["periodic"] = [AXES[a] for a in sorted(seams)]
    d["seams"] = {AXES[a]: {"swap": bool(s.swap), "flip": [bool(f) for f in s.flip]} for a, s in sorted(seams.items())}
    lo, hi = bbox(vol)
    d["bbox"] = [[float(x) for x in lo], [float(x) for x in hi]]
    d["volume"] = abs(float(volume(vol)))
    uvw, det = _sampled_det(vol)
    d["handedness"] = _handedness(vol, det)
    d["jacobian_min"], d["jacobian_max"] = _jacobian_bounds(vol)
    d["jacobian_sampled"] = [float(det.min()), float(det.max())]
    fold = _fold(vol, uvw, det)
    if fold is not None:
        d["fold"] = fold
    return d


def _g(x):
    return f"{x:.6g}"


def _vec(v):
    return "(" + ", ".join(_g(x) for x in v) + ")"


def format_info(d):
    """The info dict as short aligned lines for a terminal."""
    rows = []
    if "file" in d:
        where = f"{d['file']}"
        extra = [d.get("format")] if d.get("format") else []
        if d.get("patches") is not None:
            extra.append(f"patch {d['patch']} of {d['patches']}")
        rows.append(("file", where + (f"  [{', '.join(extra)}]" if extra else "")))
    rows.append(("degrees", "  ".join(f"{a} {p}" for a, p in zip(AXES, d["degrees"]))))
    n = d["control_points"]
    rows.append(("control points", f"{n[0]} x {n[1]} x {n[2]} = {n[0] * n[1] * n[2]}"
                                   f" ({'rational' if d.get('rational') else 'polynomial'})"))
    if "knots" in d:
        rows.append(("knots", "  ".join(f"{a}: {k['count']} knots, {k['spans']} span{'s' if k['spans'] != 1 else ''}"
                                        for a, k in d["knots"].items())))
    rows.append(("domain", " x ".join(f"[{_g(lo)}, {_g(hi)}]" for lo, hi in d["domain"])))
    periodic = d.get("periodic") or []
    rows.append(("periodic", ", ".join(periodic) if periodic else "none"))
    lo, hi = d["bbox"]
    size = [h - l for l, h in zip(lo, hi)]
    units = d.get("units") or "model units"
    rows.append(("bounding box", f"{_vec(lo)} .. {_vec(hi)}  size {' x '.join(_g(s) for s in size)} {units}"))
    cubed = f"{units}^3" if d.get("units") else "model units cubed"
    rows.append(("volume", f"{_g(d['volume'])} {cubed}"))
    rows.append(("handedness", d["handedness"]))
    rows.append(("jacobian", f"[{_g(d['jacobian_min'])}, {_g(d['jacobian_max'])}] (bounds from coefficients)"))
    if "fold" in d:
        rows.append(("FOLD", d["fold"]["message"]))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)


__all__ = ["model_info", "format_info"]
