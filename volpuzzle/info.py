"""What `volpuzzle info MODEL` reports (SPEC section 3): a plain dict for --json, and a short text for people."""

import numpy as np

from .grid import AXES


def _knot_summary(knots, degree):
    k = np.asarray(knots, float)
    lo, hi = float(k[degree]), float(k[-degree - 1])
    values, counts = np.unique(k[degree + 1:len(k) - degree - 1], return_counts=True)
    inner = [[float(v), int(c)] for v, c in zip(values, counts, strict=True)]
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


def _orientation(vol):
    """The kernel's certified orientation (spline.jacobian.orientation): handedness right / left / folded /
    unresolved, a place, and lower / upper bounds of det J from its Bezier coefficients."""
    from .spline.jacobian import orientation

    return orientation(vol)


def _fold_at(vol, uvw, value, frac=None):
    uvw = np.asarray(uvw, float).reshape(3)
    xyz = vol.evaluate(uvw[None])[0]
    share = f" ({frac:.1%} of the samples)" if frac is not None else ""
    out = {"uvw": [float(x) for x in uvw], "xyz": [float(x) for x in xyz], "det_j": float(value),
           "message": (f"the Jacobian changes sign: det J = {value:.4g} at uvw = "
                       f"({', '.join(f'{x:.4g}' for x in uvw)}), xyz = ({', '.join(f'{x:.4g}' for x in xyz)}), "
                       f"against the opposite sign elsewhere{share}")}
    if frac is not None:
        out["fraction_of_samples"] = frac
    return out


def _sampled_fold(vol, uvw, det):
    """Where the sampled det J takes the minority sign (its largest value), or None when it keeps one sign."""
    eps = 1e-9 * (float(np.max(np.abs(det))) if det.size else 0.0)
    pos, neg = det > eps, det < -eps
    if not (pos.any() and neg.any()):
        return None
    minority = neg if pos.sum() >= neg.sum() else pos
    idx = np.flatnonzero(minority)
    i = int(idx[np.argmax(np.abs(det[idx]))])
    return _fold_at(vol, uvw[i], det[i], float(minority.mean()))


def model_info(vol, path=None, patch=0, meta=None):
    """Facts about one volume patch -> dict (JSON-ready). meta: the reader's dict (format, patches, units)."""
    from .spline.measure import bbox, volume
    from .spline.seams import find_seams

    if meta is None and path is not None:
        # Callers that only loaded the Volume still get format, patch count and units (the file is re-read).
        from .errors import VolpuzzleError
        from .io import load_model_with_meta

        try:
            meta = load_model_with_meta(path, patch)[1]
        except (VolpuzzleError, OSError):
            meta = None
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
    ori = _orientation(vol)
    d["jacobian_min"], d["jacobian_max"] = float(ori.lower), float(ori.upper)
    d["jacobian_sampled"] = [float(det.min()), float(det.max())]
    d["jacobian_certificate"] = ori.handedness if ori.handedness in ("folded", "unresolved") else (
        ori.certificate.status if ori.certificate is not None else "coefficients")
    fold = _fold_at(vol, ori.where_uvw, ori.value) if ori.handedness == "folded" else _sampled_fold(vol, uvw, det)
    if ori.handedness in ("right", "left") and fold is None:
        d["handedness"] = ori.handedness
    else:
        # SPEC: right | left. A folded model gets the sign of most of its volume, and the fold entry says where.
        d["handedness"] = "right" if float(np.sum(det)) >= 0 else "left"
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
    rows.append(("degrees", "  ".join(f"{a} {p}" for a, p in zip(AXES, d["degrees"], strict=True))))
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
    size = [b - a for a, b in zip(lo, hi, strict=True)]
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
