"""label: engrave each piece's id, 0.4 mm deep, on an inner face that no joint uses, so the outside stays clean.

The text is DejaVu Sans Bold (it ships with matplotlib), flattened to polygons and filled even-odd, so the counters of
'0', '4', '6', '8', '9', 'p' come out as holes. We engrave rather than emboss: the result stays one solid whatever the
glyphs (an island inside an 'o' is simply material left standing).

Site rule. Every face the cell shares with a neighbour (tiling.faces, also across a periodic seam) is a candidate;
outer faces of D never are. On each candidate, centres on a grid of face fractions and two text directions (up along
either in-face parameter) are tried; the text's height is the largest that keeps its box a margin inside the face
(projected on the tangent plane at the centre) and R = reach + clearance + 1 mm from every joint axis of the piece
(pin, hole or dowel, whatever face it is on), capped at MAX_HEIGHT_MM. Faces that carry no joint win if any of them
holds a label; otherwise the best spot away from the joint circles on a jointed face is used. Within a class: larger
text, then nearer the face centre, then the first in face order. Too small for MIN_STROKE_MM strokes: no label (None).

Curvature. The text prism is built in the tangent frame at the site and bent onto the face: its floor follows the
surface measured under the text (from the body mesh itself by ray casting, falling back to F), lowered by
depth * sqrt(1 + slope^2) so the depth holds perpendicular to the surface too, plus a measured allowance for the
interpolation between samples. So the groove is >= depth deep everywhere under the text and only a few hundredths
of a millimetre deeper than that.
"""

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .errors import GeometryError

DEPTH_MM = 0.4
MIN_STROKE_MM = 0.8  # narrowest stem a 0.4 mm nozzle prints as two lines
MAX_HEIGHT_MM = 8.0
MARGIN_MM = 1.0  # text box to face edge
JOINT_CLEAR_MM = 1.0  # text box to a joint's pin/hole surface
TOP_MM = 0.5  # the prism starts this far above the surface, so the cut opens cleanly
MAX_SLOPE = 0.6  # |grad h| under the text; steeper, the face is too curved there for flat text
_STEM_EM = 0.178  # stem width of DejaVu Sans Bold in em, measured on '1' (0.2833 to 0.4609 at y = 0.4)
_FLAT_EM = 0.002  # largest distance between a glyph curve and its polygon, em
_SAMPLE_MM = 0.4  # spacing of surface samples under the text and of the face's boundary samples
_REFINE_MM = 0.8  # longest edge of the prism before it is bent onto the surface
_CENTRES = np.linspace(0.05, 0.95, 19)  # candidate centres, fractions across the face


def _m3():
    import manifold3d

    return manifold3d


def _cyclic(a):
    return (a + 1) % 3, (a + 2) % 3


# ---------------------------------------------------------------------------------------------------------------------
# Text


@lru_cache(maxsize=None)
def _font():
    from matplotlib.font_manager import FontProperties

    return FontProperties(family="DejaVu Sans", weight="bold")


@lru_cache(maxsize=256)
def _outline(text):
    """Closed loops of `text` at 1 em, curves flattened to _FLAT_EM -> (tuple of (k, 2) arrays, ink bbox (2, 2))."""
    from matplotlib.path import Path
    from matplotlib.textpath import TextPath

    if not text.strip():
        return (), np.zeros((2, 2))
    path = TextPath((0.0, 0.0), text, size=1.0, prop=_font())
    loops, cur = [], []
    for seg, code in path.iter_bezier():
        cp = np.asarray(seg.control_points, dtype=float)
        if code == Path.MOVETO:
            if len(cur) > 2:
                loops.append(np.array(cur))
            cur = [cp[0]]
        elif code == Path.CLOSEPOLY:
            if len(cur) > 2:
                loops.append(np.array(cur))
            cur = []
        elif code == Path.LINETO:
            cur.append(cp[-1])
        else:
            # a Bezier segment stays within its control polygon; its chord error is ~ L^2 / (8 r)
            ctrl = float(np.linalg.norm(np.diff(cp, axis=0), axis=1).sum())
            n = int(np.clip(np.ceil(ctrl / np.sqrt(8.0 * _FLAT_EM * 0.05)), 2, 32))
            cur.extend(seg(np.linspace(0.0, 1.0, n + 1)[1:]))
    if len(cur) > 2:
        loops.append(np.array(cur))
    if not loops:
        return (), np.zeros((2, 2))
    allp = np.concatenate(loops)
    return tuple(loops), np.array([allp.min(axis=0), allp.max(axis=0)])


def _ink(text):
    """Ink box (width, height) of `text` at 1 em."""
    loops, box = _outline(text)
    return box[1] - box[0]


def min_height_mm(text):
    """Smallest ink height (mm) of `text` whose stems are MIN_STROKE_MM wide."""
    h = float(_ink(text)[1])
    return MIN_STROKE_MM / _STEM_EM * h if h > 0 else float("inf")


def text_cross_section(text, height_mm):
    """Filled outlines of `text` whose ink box is height_mm tall, centred at the origin (x along the baseline) ->
    manifold3d.CrossSection, or None when the text is empty or so small that its strokes would not print."""
    loops, box = _outline(str(text))
    if not loops or not height_mm >= min_height_mm(text) - 1e-9:
        return None
    m3 = _m3()
    scale = float(height_mm) / float(box[1, 1] - box[0, 1])
    mid = box.mean(axis=0)
    cs = m3.CrossSection([np.ascontiguousarray((lp - mid) * scale) for lp in loops], m3.FillRule.EvenOdd)
    return cs


# ---------------------------------------------------------------------------------------------------------------------
# Site


@dataclass(frozen=True, eq=False)
class LabelSite:
    """Where a piece's label goes. center (3,) mm on the mapped face; normal (3,) unit, outward from the piece; up (3,)
    unit in the face, the text's up (its baseline runs along up x normal, so it reads from outside the piece);
    height_mm: ink height; face: (axis, side), side +1 the cell's max face along axis, -1 its min face; uvw (3,): the
    centre's parameters; has_joint: the face carries a joint; grid_x (nx,), grid_y (ny,) mm and heights (ny, nx) mm:
    the surface above the tangent plane (along normal) under the text, from F; error_mm: largest gap measured between
    F and the bilinear interpolant of heights."""

    center: np.ndarray
    normal: np.ndarray
    up: np.ndarray
    height_mm: float
    face: tuple
    uvw: np.ndarray
    has_joint: bool
    text: str
    grid_x: np.ndarray
    grid_y: np.ndarray
    heights: np.ndarray
    error_mm: float

    @property
    def right(self):
        return np.cross(self.up, self.normal)

    def frame(self):
        """3x4 rigid map: local x -> right, y -> up, z -> normal, origin -> center."""
        m = np.zeros((3, 4))
        m[:, 0], m[:, 1], m[:, 2], m[:, 3] = self.right, self.up, self.normal, self.center
        return m

    def to_report(self):
        """The label as report.json can list it: face like 'v+' (the cell's max v face), sizes in mm."""
        return {"text": self.text, "face": "uvw"[self.face[0]] + ("+" if self.face[1] > 0 else "-"),
                "height_mm": round(float(self.height_mm), 3), "center_mm": [round(float(x), 4) for x in self.center],
                "normal": [round(float(x), 6) for x in self.normal], "on_joint_face": bool(self.has_joint)}


def _face_joints(face, joints):
    """Joints on a shared face (the same pair of cells, axis, and seam crossing)."""
    out = []
    for j in joints or ():
        if (int(j.axis) == face.axis and tuple(j.pin_cell) in (face.lower, face.upper)
                and tuple(j.hole_cell) in (face.lower, face.upper)
                and bool(getattr(j, "across_seam", False)) == (face.seam is not None)):
            out.append(j)
    return out


def _joint_axes(cell_index, joints):
    """(points (k, 3) along the axes of the cell's joints, every 0.25 mm, covering pin, base and hole; keep-out
    radius R (k,)) of every joint touching the cell."""
    pts, rad = [], []
    for j in joints or ():
        if tuple(j.pin_cell) != cell_index and tuple(j.hole_cell) != cell_index:
            continue
        swell = 1.15 if getattr(j, "shape", "cylinder") == "snap" else 1.0
        r = float(j.radius) * swell + float(j.clearance) + JOINT_CLEAR_MM
        base = float(getattr(j, "base_depth", 0.0) or 0.0)
        reach = float(j.length) + float(getattr(j, "axial_clearance", 0.0)) + base + 1.0
        t = np.linspace(-reach, reach, int(np.ceil(2 * reach / 0.25)) + 1)
        pts.append(np.asarray(j.center, float)[None] + t[:, None] * np.asarray(j.direction, float)[None])
        rad.append(np.full(len(t), r))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(pts), np.concatenate(rad)


def _face_uvw(cell, a, side, fb, fc):
    """Parameters of face fractions fb, fc (same shape) on the cell's face along axis a."""
    b, c = _cyclic(a)
    lo, hi = cell.box
    fb, fc = np.broadcast_arrays(np.asarray(fb, float), np.asarray(fc, float))
    uvw = np.empty(fb.shape + (3,))
    uvw[..., a] = hi[a] if side > 0 else lo[a]
    uvw[..., b] = lo[b] + fb * (hi[b] - lo[b])
    uvw[..., c] = lo[c] + fc * (hi[c] - lo[c])
    return uvw


def _outward(jac, a, side, orientation):
    """Outward unit normals (n, 3) of the face along axis a, side +-1, from Jacobians (n, 3, 3); 0 where collapsed."""
    b, c = _cyclic(a)
    nrm = np.cross(jac[:, :, b], jac[:, :, c])
    det = np.einsum("ni,ni->n", jac[:, :, a], nrm)
    # J_a . (J_b x J_c) = det J: with det > 0, J_b x J_c points to growing a, out of the max face
    sign = np.where(np.abs(det) > 1e-12, np.sign(det), orientation) * side
    size = np.linalg.norm(nrm, axis=1)
    return np.where(size[:, None] > 1e-12, nrm * (sign / np.maximum(size, 1e-300))[:, None], 0.0)


def _boundary(cell, fmap, a, side):
    """Points (k, 3) mm along the face's four edges, at most ~_SAMPLE_MM apart."""
    t = np.linspace(0.0, 1.0, 17)
    one, zero = np.ones_like(t), np.zeros_like(t)
    edges = [(t, zero), (one, t), (t[::-1], one), (zero, t[::-1])]
    coarse = fmap.evaluate(np.concatenate([_face_uvw(cell, a, side, fb, fc) for fb, fc in edges]))
    lengths = np.linalg.norm(np.diff(coarse.reshape(4, 17, 3), axis=1), axis=2).sum(axis=1)
    uvw = []
    for (fb, fc), length in zip(edges, lengths):
        n = int(np.clip(np.ceil(length / _SAMPLE_MM), 16, 4000))
        s = np.linspace(0.0, 1.0, n + 1)
        uvw.append(_face_uvw(cell, a, side, np.interp(s, t, fb), np.interp(s, t, fc)))
    return fmap.evaluate(np.concatenate(uvw))


def _limit(d, right, up, pad, aspect):
    """Largest text height (k,) for which a box of half-extents (aspect/2, 1/2) * H about each centre stays `pad`
    clear of every point: H <= max((|qx| - pad) / (aspect/2), (|qy| - pad) / (1/2)). d (k, m, 3) points less centres."""
    qx = np.abs(np.einsum("kmi,ki->km", d, right))
    qy = np.abs(np.einsum("kmi,ki->km", d, up))
    return np.maximum((qx - pad) / (0.5 * aspect), (qy - pad) / 0.5)


def _candidates(cell, fmap, a, side, has_joint, axes_pts, axes_r, text, depth, order):
    """Every (centre, direction) on one face -> list of (sort key, site arguments)."""
    b, c = _cyclic(a)
    ink_w, ink_h = _ink(text)
    aspect = ink_w / ink_h
    hmin = min_height_mm(text)
    fb, fc = (x.ravel() for x in np.meshgrid(_CENTRES, _CENTRES, indexing="ij"))
    uvw = _face_uvw(cell, a, side, fb, fc)
    x0, jac = fmap.evaluate_with_jacobian(uvw)
    normals = _outward(jac, a, side, int(getattr(fmap, "orientation", 1) or 1))
    good = np.any(normals != 0, axis=1)
    edge = _boundary(cell, fmap, a, side)
    d_edge = edge[None] - x0[:, None]
    d_axes = axes_pts[None] - x0[:, None]
    off_centre = np.round(np.hypot(fb - 0.5, fc - 0.5), 6)
    out = []
    for k, tangent in enumerate((jac[:, :, b], jac[:, :, c])):
        up = tangent - np.einsum("ki,ki->k", tangent, normals)[:, None] * normals
        size = np.linalg.norm(up, axis=1)
        ok = good & (size > 1e-12)
        up = up / np.maximum(size, 1e-300)[:, None]
        right = np.cross(up, normals)
        # the face's outline and the joint axes, seen along the normal
        height = np.minimum(_limit(d_edge, right, up, MARGIN_MM, aspect).min(axis=1), MAX_HEIGHT_MM)
        if len(axes_pts):
            z = np.einsum("kmi,ki->km", d_axes, normals)
            lim = _limit(d_axes, right, up, axes_r[None], aspect)
            near = (z > -(depth + 2.0 + axes_r[None])) & (z < TOP_MM + 2.0 + axes_r[None])
            height = np.minimum(height, np.where(near, lim, np.inf).min(axis=1))
        for i in np.flatnonzero(ok & (height >= hmin)):
            u = up[i]
            # upright text where the face allows it: up turned to the global +z, so labels read alike
            if u[2] < -1e-9 or (abs(u[2]) <= 1e-9 and (u[1] < -1e-9 or (abs(u[1]) <= 1e-9 and u[0] < 0))):
                u = -u
            key = (has_joint, -round(float(height[i]), 3), off_centre[i], order, k, i)
            out.append((key, (x0[i], normals[i], u, float(height[i]), uvw[i])))
    return out


def _heights(cell, fmap, a, side, center, normal, up, uvw0, xs, ys):
    """Surface heights (len(ys), len(xs)) mm along `normal` above the tangent plane at points (x, y) of it, by Newton
    on the face's two parameters -> (heights, ok); ok is False where Newton left the face or did not converge."""
    b, c = _cyclic(a)
    right = np.cross(up, normal)
    lo, hi = cell.box
    gx, gy = np.meshgrid(xs, ys)
    target = np.stack([gx.ravel(), gy.ravel()], axis=1)
    _, jac0 = fmap.evaluate_with_jacobian(uvw0[None])
    j2 = np.array([[jac0[0][:, b] @ right, jac0[0][:, c] @ right], [jac0[0][:, b] @ up, jac0[0][:, c] @ up]])
    st = uvw0[[b, c]][None] + target @ np.linalg.inv(j2).T
    box_lo, box_hi = lo[[b, c]], hi[[b, c]]
    uvw = np.repeat(uvw0[None], len(target), axis=0)
    res = np.full(len(target), np.inf)
    for _ in range(25):
        st = np.clip(st, box_lo, box_hi)
        uvw[:, b], uvw[:, c] = st[:, 0], st[:, 1]
        x, jac = fmap.evaluate_with_jacobian(uvw)
        d = x - center
        err = np.stack([d @ right, d @ up], axis=1) - target
        res = np.linalg.norm(err, axis=1)
        if res.max() < 1e-7:
            break
        jj = np.stack([np.stack([jac[:, :, b] @ right, jac[:, :, c] @ right], axis=1),
                       np.stack([jac[:, :, b] @ up, jac[:, :, c] @ up], axis=1)], axis=1)
        st = st - np.linalg.solve(jj, err[..., None])[..., 0]
    h = ((x - center) @ normal).reshape(gx.shape)
    return h, bool(res.max() < 1e-5)


def _bilinear(xs, ys, grid, px, py):
    """grid (len(ys), len(xs)) at points (px, py), clamped to the grid."""
    fx = np.clip((px - xs[0]) / (xs[1] - xs[0]), 0.0, len(xs) - 1 - 1e-9)
    fy = np.clip((py - ys[0]) / (ys[1] - ys[0]), 0.0, len(ys) - 1 - 1e-9)
    i, j = fx.astype(int), fy.astype(int)
    tx, ty = fx - i, fy - j
    return ((1 - tx) * (1 - ty) * grid[j, i] + tx * (1 - ty) * grid[j, i + 1] + (1 - tx) * ty * grid[j + 1, i]
            + tx * ty * grid[j + 1, i + 1])


def _axis_grid(half):
    n = int(np.ceil(2 * half / _SAMPLE_MM)) + 1
    return np.linspace(-half, half, max(n, 3))


def _make_site(cell, fmap, a, side, has_joint, args, text):
    """Measure the surface under the text at one candidate -> LabelSite, or None when it is too curved there."""
    center, normal, up, height, uvw0 = args
    ink_w, ink_h = _ink(text)
    half_x = 0.5 * height * ink_w / ink_h + 0.5
    half_y = 0.5 * height + 0.5
    xs, ys = _axis_grid(half_x), _axis_grid(half_y)
    h, ok = _heights(cell, fmap, a, side, center, normal, up, uvw0, xs, ys)
    if not ok:
        return None
    gy, gx = np.gradient(h, ys, xs)
    if float(np.max(np.hypot(gx, gy))) > MAX_SLOPE:
        return None
    # the interpolant's error, measured at the cells' centres
    xm, ym = 0.5 * (xs[1:] + xs[:-1]), 0.5 * (ys[1:] + ys[:-1])
    hm, ok = _heights(cell, fmap, a, side, center, normal, up, uvw0, xm, ym)
    if not ok:
        return None
    px, py = np.meshgrid(xm, ym)
    err = float(np.max(np.abs(hm - _bilinear(xs, ys, h, px, py))))
    ro = []
    for arr in (center, normal, up, uvw0, xs, ys, h):
        arr = np.array(arr, dtype=float)
        arr.setflags(write=False)
        ro.append(arr)
    return LabelSite(ro[0], ro[1], ro[2], float(height), (int(a), int(side)), ro[3], bool(has_joint), str(text),
                     ro[4], ro[5], ro[6], err)


def choose_label_site(cell, tiling, fmap, joints, text=None, depth=DEPTH_MM):
    """The best place for the cell's label (rule in the module docstring) -> LabelSite, or None when no inner face
    holds `text` (default: the piece id) with MIN_STROKE_MM strokes: a single cell, or faces too small or too
    crowded with joints."""
    text = str(text if text is not None else cell.id)
    if not _outline(text)[0]:
        return None
    index = tuple(cell.index)
    axes_pts, axes_r = _joint_axes(index, joints)
    cands = []
    for order, (face, side) in enumerate(tiling.faces_of(index)):
        has_joint = bool(_face_joints(face, joints))
        for key, args in _candidates(cell, fmap, face.axis, side, has_joint, axes_pts, axes_r, text, depth, order):
            cands.append((key, face.axis, side, has_joint, args))
    cands.sort(key=lambda c: c[0])
    for _, a, side, has_joint, args in cands[:64]:
        site = _make_site(cell, fmap, a, side, has_joint, args, text)
        if site is not None:
            return site
    return None


# ---------------------------------------------------------------------------------------------------------------------
# Engraving


def _measured_heights(body, site):
    """Heights (ny, nx) of the body's own surface above the site's tangent plane (its printed surface, not F), by a
    ray down the normal at every grid point; F's height where the ray finds nothing near it."""
    h = np.array(site.heights, dtype=float)
    frame = site.frame()
    span = float(h.max() - h.min()) + 2.0
    for j, y in enumerate(site.grid_y):
        for i, x in enumerate(site.grid_x):
            top = frame[:, 3] + frame[:, 0] * x + frame[:, 1] * y + frame[:, 2] * (h[j, i] + span)
            end = top - frame[:, 2] * (2 * span)
            hits = body.ray_cast(tuple(top), tuple(end))
            if hits:
                z = float((np.asarray(hits[0].position) - frame[:, 3]) @ frame[:, 2])
                if abs(z - h[j, i]) < 0.5:  # the first hit is this face, not some other part of the piece
                    h[j, i] = z
    return h


def engrave(body, site, text=None, depth=DEPTH_MM, what=None):
    """body (manifold3d.Manifold, mm) with `text` (default, and the text the site was sized for: the site's) cut
    `depth` mm into it at `site` -> Manifold.
    The groove is >= depth deep, measured from the body's own surface, everywhere under the text. Raises
    GeometryError naming `what` when the engine fails or the piece would not stay one solid."""
    m3 = _m3()
    text = str(text if text is not None else site.text)
    what = what or f"piece labelled {text}"
    cs = text_cross_section(text, site.height_mm)
    if cs is None:
        raise GeometryError(f"{what}: label {text!r} at {site.height_mm:.2f} mm is too small to print "
                            f"(expected at least {min_height_mm(text):.2f} mm)")
    if body.status() != m3.Error.NoError:
        raise GeometryError(f"{what}: the geometry engine failed before engraving (status {body.status().name})")
    xs, ys = site.grid_x, site.grid_y
    h = _measured_heights(body, site)
    gy, gx = np.gradient(h, ys, xs)
    # depth along the surface normal: a slope g lowers the floor by depth * sqrt(1 + g^2) measured vertically
    floor = h - depth * np.sqrt(1.0 + gx ** 2 + gy ** 2)
    # between samples and along the prism's edges the floor is linear: allow for the curvature over one cell and edge
    dxx = np.abs(np.diff(floor, 2, axis=1)).max(initial=0.0) / (xs[1] - xs[0]) ** 2
    dyy = np.abs(np.diff(floor, 2, axis=0)).max(initial=0.0) / (ys[1] - ys[0]) ** 2
    curv = max(dxx, dyy)
    step = max(xs[1] - xs[0], ys[1] - ys[0])
    allowance = site.error_mm + curv * (step ** 2 + _REFINE_MM ** 2) / 8.0 + 1e-3
    floor = floor - allowance
    ceiling = h + TOP_MM

    prism = m3.Manifold.extrude(cs, 1.0).refine_to_length(_REFINE_MM)

    def bend(v):
        v = np.asarray(v, dtype=float)
        lo = _bilinear(xs, ys, floor, v[:, 0], v[:, 1])
        hi = _bilinear(xs, ys, ceiling, v[:, 0], v[:, 1])
        out = v.copy()
        out[:, 2] = lo + v[:, 2] * (hi - lo)
        return out

    prism = prism.warp_batch(bend).transform(site.frame())
    if prism.status() != m3.Error.NoError or prism.is_empty():
        raise GeometryError(f"{what}: the geometry engine failed building the label {text!r} "
                            f"(status {prism.status().name})")
    before = len(body.decompose())
    out = body - prism
    if out.status() != m3.Error.NoError:
        raise GeometryError(f"{what}: the geometry engine failed engraving the label {text!r} "
                            f"(status {out.status().name})")
    if out.is_empty() or len(out.decompose()) != before:
        raise GeometryError(f"{what}: engraving the label {text!r} splits the piece into {len(out.decompose())} "
                            f"bodies (expected {before}); the face is too thin for a {depth:g} mm groove")
    return out


def label_piece(body, cell, tiling, fmap, joints, text=None, depth=DEPTH_MM, what=None):
    """choose_label_site then engrave -> (Manifold, LabelSite or None); the body unchanged when no face holds it."""
    site = choose_label_site(cell, tiling, fmap, joints, text=text, depth=depth)
    if site is None:
        return body, None
    return engrave(body, site, text, depth=depth, what=what or cell.id), site
