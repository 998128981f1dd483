"""label: engrave each piece's id, 0.4 mm deep, on an inner face that no joint uses, so the outside stays clean.

The text is DejaVu Sans Bold (it ships with matplotlib), flattened to polygons and filled even-odd, so the counters of
'0', '4', '6', '8', '9', 'p' come out as holes. We engrave rather than emboss: the result stays one solid whatever the
glyphs (an island inside an 'o' is simply material left standing).

Site rule. Every face the cell shares with a neighbour (tiling.faces, also across a periodic seam) is a candidate, and
D's outer faces after them (below). On each candidate, centres on a grid of face fractions and two text directions (up
along either in-face parameter) are tried; the text's height is the largest that keeps its box a margin inside the face
(projected on the tangent plane at the centre) and R = reach + clearance + 1 mm from every joint axis of the piece (pin,
hole or dowel, whatever face it is on), capped at MAX_HEIGHT_MM. Faces that carry no joint win if any of them holds a
label; otherwise the best spot away from the joint circles on a jointed face is used; then D's outer faces, those that
look into the model first (the inside of a shell, out of sight once assembled). Within a class: larger text, then nearer
the face centre, then the first in face order. Too small for the stroke asked (MIN_STROKE_MM, then the finer
STROKES_MM): no site. A mesh model's piece covers only part of its cage cell's faces: label_piece then searches again on
the piece's real outline on each face (_BodyFaces), and its caller may mirror the id on the bed side (engrave_bed) as
the last resort. A site where the piece is thinner than the groove and MIN_WALL_MM behind the text is passed over
(engrave measures it with the same rays as the surface).

Curvature. The text prism is built in the tangent frame at the site and bent onto the face: its floor follows the
surface measured under the text (from the body mesh itself by ray casting, falling back to F), lowered by
depth * sqrt(1 + slope^2) so the depth holds perpendicular to the surface too, plus a measured allowance for the
interpolation between samples. So the groove is >= depth deep everywhere under the text and only a few hundredths
of a millimetre deeper than that.
"""

import weakref
from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np
from numba import njit

from .errors import GeometryError
from .geometry import is_ok, unique_pairs
from .joint import outer_radius

DEPTH_MM = 0.4
MIN_STROKE_MM = 0.8  # narrowest stem a 0.4 mm nozzle prints as two lines
FINE_STROKE_MM = 0.6  # the fallback: one and a half lines, still a clean groove
HAIR_STROKE_MM = 0.4  # the last resort: one nozzle width, the narrowest groove that still prints as a groove
STROKES_MM = (MIN_STROKE_MM, FINE_STROKE_MM, HAIR_STROKE_MM)
MAX_HEIGHT_MM = 8.0
MARGIN_MM = 1.0  # text box to face edge
JOINT_CLEAR_MM = 1.0  # text box to a joint's pin/hole surface
MIN_WALL_MM = 0.8  # material left under the groove: two lines of a 0.4 mm nozzle (a thinner skin a slicer drops)
TOP_MM = 0.5  # the prism starts this far above the surface, so the cut opens cleanly
MAX_SLOPE = 0.6  # |grad h| under the text; steeper, the face is too curved there for flat text
_STEM_EM = 0.178  # stem width of DejaVu Sans Bold in em, measured on '1' (0.2833 to 0.4609 at y = 0.4)
_FLAT_EM = 0.005  # largest distance between a glyph curve and its polygon, em (0.04 mm on 8 mm text)
_SAMPLE_MM = 0.4  # spacing of surface samples under the text and of the face's boundary samples
_REFINE_MM = (0.8, 4.0)  # shortest and longest edge target of the prism before it is bent onto the surface
_SAG_MM = 0.05  # extra groove depth accepted where a coarser prism floor spares triangles
_AVOID_COS = float(np.cos(np.radians(45.0)))
_CENTRES = np.linspace(0.05, 0.95, 19)  # candidate centres, fractions across the face


def _m3():
    import manifold3d

    return manifold3d


def _cyclic(a):
    return (a + 1) % 3, (a + 2) % 3


# ---------------------------------------------------------------------------------------------------------------------
# Text


@cache
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
    if "$" in text or "\\" in text:  # mathtext, or an escaped dollar: TextPath's own parsing
        path = TextPath((0.0, 0.0), text, size=1.0, prop=_font())
    else:
        # what TextPath does for plain text, without importing matplotlib's artists for its one question (is this
        # mathtext?): the glyphs at FONT_SCALE, scaled to 1 em
        from matplotlib.textpath import text_to_path
        from matplotlib.transforms import Affine2D

        raw = Path(*text_to_path.get_text_path(_font(), text, ismath=False))
        path = Path(Affine2D().scale(1.0 / text_to_path.FONT_SCALE).translate(0.0, 0.0).transform(raw.vertices),
                    raw.codes)
    verts, codes = np.asarray(path.vertices, dtype=float), path.codes
    if codes is None or not np.isin(codes, (Path.MOVETO, Path.LINETO, Path.CURVE3, Path.CLOSEPOLY, Path.STOP)).all():
        return _outline_slow(path)  # cubic curves (not in TrueType fonts) or anything else unexpected
    # Every step of a loop as a quadratic Bezier (p0, p1, p2) sampled n times: a line is (prev, end, end) once, whose
    # one sample at t = 1 is its end point exactly. The samples are then computed all at once.
    starts, steps, loop_of = [], [], []
    prev = None
    i = 0
    while i < len(codes):
        code = codes[i]
        if code == Path.MOVETO:
            prev = i
            starts.append(i)
            i += 1
        elif code == Path.LINETO:
            steps.append((prev, i, i))
            loop_of.append(len(starts) - 1)
            prev = i
            i += 1
        elif code == Path.CURVE3:
            steps.append((prev, i, i + 1))
            loop_of.append(len(starts) - 1)
            prev = i + 1
            i += 2
        elif code == Path.CLOSEPOLY:
            # closing only ends the loop; steps after it without a MOVETO make a loop of their own
            starts.append(None)
            prev = i
            i += 1
        else:
            break
    steps = np.asarray(steps, dtype=np.int64).reshape(-1, 3)
    loop_of = np.asarray(loop_of, dtype=np.int64)
    p0, p1, p2 = verts[steps[:, 0]], verts[steps[:, 1]], verts[steps[:, 2]]
    is_line = steps[:, 1] == steps[:, 2]
    # a line is stored as (prev, end, end), whose second difference is not 0: it keeps its one step by is_line
    dd = p0 - 2.0 * p1 + p2
    n = np.where(is_line, 1, _flat_steps(np.sqrt(dd[:, 0] * dd[:, 0] + dd[:, 1] * dd[:, 1]), 2))
    step = np.repeat(np.arange(len(n)), n)
    k = np.arange(len(step)) - np.repeat(np.cumsum(n) - n, n) + 1
    t = (k / n[step])[:, None]
    pts = ((1 - t) ** 2 * p0[step] + 2 * t * (1 - t) * p1[step] + t ** 2 * p2[step])
    pts[is_line[step]] = p2[step][is_line[step]]
    loops = []
    owner = loop_of[step]
    for li, s in enumerate(starts):
        loop = pts[owner == li] if s is None else np.concatenate([verts[s][None], pts[owner == li]])
        if len(loop) > 2:
            loops.append(loop)
    if not loops:
        return (), np.zeros((2, 2))
    allp = np.concatenate(loops)
    return tuple(loops), np.array([allp.min(axis=0), allp.max(axis=0)])


def _flat_steps(dd, degree):
    """Equal parameter steps (k,) int that keep a Bezier curve of `degree` within _FLAT_EM of its polygon, from the
    largest second difference dd (k,) em of its control points. |C''| <= d (d - 1) dd, and a chord over a parameter
    step h lies within h^2 |C''| / 8 of the curve (Filip, Magedson & Markot, CAGD 3, 1986; Wang's formula), so
    n = sqrt(d (d - 1) dd / (8 _FLAT_EM)) steps suffice: a gentle curve gets few, a tight one many."""
    n = np.ceil(np.sqrt(degree * (degree - 1) * np.asarray(dd, float) / (8.0 * _FLAT_EM)))
    return np.clip(n, 1, 32).astype(np.int64)


def _outline_slow(path):
    """_outline for any path matplotlib may give (cubic curves too), one segment at a time."""
    from matplotlib.path import Path

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
            dd = float(np.linalg.norm(cp[:-2] - 2.0 * cp[1:-1] + cp[2:], axis=1).max())
            n = int(_flat_steps(np.array([dd]), len(cp) - 1)[0])
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


def min_height_mm(text, stroke=MIN_STROKE_MM):
    """Smallest ink height (mm) of `text` whose stems are `stroke` mm wide."""
    h = float(_ink(text)[1])
    return stroke / _STEM_EM * h if h > 0 else float("inf")


def text_cross_section(text, height_mm, stroke=MIN_STROKE_MM):
    """Filled outlines of `text` whose ink box is height_mm tall, centred at the origin (x along the baseline) ->
    manifold3d.CrossSection, or None when the text is empty or so small that its strokes (at least `stroke` mm)
    would not print."""
    loops, box = _outline(str(text))
    if not loops or not height_mm >= min_height_mm(text, stroke) - 1e-9:
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
    outer: bool = False

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
                "normal": [round(float(x), 6) for x in self.normal], "on_joint_face": bool(self.has_joint),
                "on_outer_face": bool(self.outer), "mirrored": False}


def _face_joints(face, joints):
    """Joints on a shared face (the same pair of cells, axis, and seam crossing)."""
    out = []
    for j in joints or ():
        if (int(j.axis) == face.axis and tuple(j.pin_cell) in (face.lower, face.upper)
                and tuple(j.hole_cell) in (face.lower, face.upper)
                and bool(getattr(j, "across_seam", False)) == (face.seam is not None)):
            out.append(j)
    return out


def site_on_joint_face(site, joints, cell_index):
    """True when a joint of the cell opens on the face the label sits on: its axis within 45 degrees of the label's
    normal and its centre within 2 mm of the label's tangent plane (whatever face pairing the joint was planned on,
    e.g. after a mesh model moved it)."""
    n = np.asarray(site.normal, float)
    for j in joints or ():
        if tuple(j.pin_cell) != tuple(cell_index) and tuple(j.hole_cell) != tuple(cell_index):
            continue
        d = np.asarray(j.direction, float)
        if abs(float(d @ n)) > np.cos(np.radians(45.0)) and abs(float((np.asarray(j.center) - site.center) @ n)) < 2.0:
            return True
    return False


def _joint_axes(cell_index, joints):
    """(points (k, 3) along the axes of the cell's joints, every 0.25 mm, covering pin, base and hole; keep-out
    radius R (k,)) of every joint touching the cell."""
    pts, rad = [], []
    for j in joints or ():
        if tuple(j.pin_cell) != cell_index and tuple(j.hole_cell) != cell_index:
            continue
        r = outer_radius(float(j.radius), getattr(j, "shape", "cylinder")) + float(j.clearance) + JOINT_CLEAR_MM
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
    # the four edges in turn, as face fractions running from s = 0 to 1
    coarse = fmap.evaluate(_face_uvw(cell, a, side, np.concatenate([t, one, t[::-1], zero]),
                                     np.concatenate([zero, t, one, t[::-1]])))
    lengths = np.linalg.norm(np.diff(coarse.reshape(4, 17, 3), axis=1), axis=2).sum(axis=1)
    n = np.clip(np.ceil(lengths / _SAMPLE_MM), 16, 4000).astype(np.int64)
    edge = np.repeat(np.arange(4), n + 1)
    s = (np.arange(len(edge)) - np.repeat(np.cumsum(n + 1) - (n + 1), n + 1)) / np.repeat(n, n + 1)
    fb = np.choose(edge, [s, np.ones_like(s), 1.0 - s, np.zeros_like(s)])
    fc = np.choose(edge, [np.zeros_like(s), s, np.ones_like(s), 1.0 - s])
    return fmap.evaluate(_face_uvw(cell, a, side, fb, fc))


def _limit(pts, x0, right, up, pad, aspect):
    """Largest text height (m, k) for which a box of half-extents (aspect/2, 1/2) * H about each centre x0 (k, 3)
    stays `pad` (scalar or (m,)) clear of each point pts (m, 3), seen along the normal:
    H <= max((|qx| - pad) / (aspect/2), (|qy| - pad) / (1/2))."""
    qx = np.abs(pts @ right.T - np.einsum("ki,ki->k", x0, right))
    qy = np.abs(pts @ up.T - np.einsum("ki,ki->k", x0, up))
    pad = np.asarray(pad, float).reshape(-1, 1)
    return np.maximum((qx - pad) * (2.0 / aspect), (qy - pad) * 2.0)


_CHUNK = 16  # keep-out points bounded together by one ball when looking for the few that can limit a centre


def _keep_out(pts, pad, lo, hi):
    """Keep-out points for _heights_allowed: points (m, 3), pad (m,), and the band (lo, hi) (m,) each must lie in,
    strictly, along a centre's normal to count; cut into runs of _CHUNK consecutive points (the last padded with its
    last point), each bounded by a ball. Points along an edge or an axis come in order, so a run is a short curve."""
    m = len(pts)
    idx = np.minimum(np.arange(-(-m // _CHUNK) * _CHUNK).reshape(-1, _CHUNK), m - 1)
    ball = pts[idx]
    centres = ball.mean(axis=1)
    # a little more than the farthest point, so rounding never lets a bound pass a point it covers
    radii = np.linalg.norm(ball - centres[:, None], axis=2).max(axis=1) + 1e-9
    return {"pts": pts, "pad": pad, "lo": lo, "hi": hi, "idx": idx, "centres": centres,
            "slack": radii + pad[idx].min(axis=1), "mid": idx[:, _CHUNK // 2],
            # a run lies wholly outside the band where its centre is beyond these
            "below": lo[idx].min(axis=1) - radii, "above": hi[idx].max(axis=1) + radii}


def _centre_terms(ko, x0, normal, right, up):
    """What _heights_allowed measures at centres x0 (k, 3) whatever the text: the centres along their frames (k,),
    each run's centre across them less its slack ((runs, k), 2x across up) and whether it lies outside the band, and
    the same of each run's middle point less its pad. A face's candidates ask this of every text tried on it."""
    pts, pad, lo, hi, mid = ko["pts"], ko["pad"], ko["lo"], ko["hi"], ko["mid"]
    xr, xu, xn = (np.einsum("ki,ki->k", x0, v) for v in (right, up, normal))
    slack = ko["slack"][:, None]
    cz = ko["centres"] @ normal.T - xn
    qx = np.abs(pts[mid] @ right.T - xr)
    qy = np.abs(pts[mid] @ up.T - xu)
    z = pts[mid] @ normal.T - xn
    return {"xr": xr, "xu": xu, "xn": xn, "cx": np.abs(ko["centres"] @ right.T - xr) - slack,
            "cy2": (np.abs(ko["centres"] @ up.T - xu) - slack) * 2.0,
            "out": (cz <= ko["below"][:, None]) | (cz >= ko["above"][:, None]),
            "mx": qx - pad[mid][:, None], "my2": (qy - pad[mid][:, None]) * 2.0,
            "mout": (z <= lo[mid][:, None]) | (z >= hi[mid][:, None])}


def _terms_at(terms, at):
    """_centre_terms of the centres `at` (indices) only, C-ordered as _centre_terms gives them: a column subset comes
    out in Fortran order, and _refined is compiled for C-ordered arrays alone (precompile.KERNELS)."""
    return {key: (v[at] if v.ndim == 1 else np.ascontiguousarray(v[:, at])) for key, v in terms.items()}


def _heights_allowed(ko, x0, normal, right, up, aspect, cap, alive_min, terms=None):
    """The text height (k,) at centres x0 (k, 3) with frames (normal, right, up): the smallest _limit over the
    keep-out points ko (_keep_out) in their bands, capped at `cap`. Heights below alive_min are only guaranteed to be
    below it (those centres are dropped anyway). terms: _centre_terms of these centres, when known.

    A ball of points bounds the _limit of all of them from below; runs whose bound is no smaller than a height one of
    their own points already allows cannot lower it, so only the few runs near a centre are measured point by point."""
    k = len(x0)
    height = np.full(k, float(cap))
    pts, pad, lo, hi = ko["pts"], ko["pad"], ko["lo"], ko["hi"]
    if not len(pts):
        return height
    if terms is None:
        terms = _centre_terms(ko, x0, normal, right, up)
    xr, xu, xn = terms["xr"], terms["xu"], terms["xn"]
    low = np.maximum(terms["cx"] * (2.0 / aspect), terms["cy2"])
    low[terms["out"]] = np.inf
    # one real point per run: its limit (_limit) is an upper bound on the height
    lim = np.maximum(terms["mx"] * (2.0 / aspect), terms["my2"])
    lim[terms["mout"]] = np.inf
    height = np.minimum(height, lim.min(axis=0))
    return _refined(height, low, float(alive_min), ko["idx"], pts, pad, lo, hi, right, up, normal, xr, xu, xn,
                    2.0 / aspect)


@njit(cache=True, nogil=True)
def _refined(height, low, alive_min, idx, pts, pad, lo, hi, right, up, normal, xr, xu, xn, scale_x):
    """_heights_allowed's last step: height (k,) lowered by the points of every run (idx (runs, _CHUNK)) whose bound
    low (runs, k) is below the height of a centre that may still hold the text (at least alive_min) -> (k,).
    Compiled: most calls measure a few runs, and numpy spent most of them gathering and allocating; the arithmetic
    is numpy's, in its order (a dot product x0 y0 + x1 y1 + x2 y2, NaN wins every maximum and minimum)."""
    runs, k = low.shape
    out = height.copy()
    for j in range(k):
        bar = height[j] if height[j] >= alive_min else -np.inf
        for c in range(runs):
            if not low[c, j] < bar:
                continue
            best = np.inf
            for g in range(idx.shape[1]):
                q = idx[c, g]
                z = pts[q, 0] * normal[j, 0] + pts[q, 1] * normal[j, 1] + pts[q, 2] * normal[j, 2] - xn[j]
                if z <= lo[q] or z >= hi[q]:
                    continue  # outside its band: no limit (inf)
                qx = abs(pts[q, 0] * right[j, 0] + pts[q, 1] * right[j, 1] + pts[q, 2] * right[j, 2] - xr[j])
                qy = abs(pts[q, 0] * up[j, 0] + pts[q, 1] * up[j, 1] + pts[q, 2] * up[j, 2] - xu[j])
                a, b = (qx - pad[q]) * scale_x, (qy - pad[q]) * 2.0
                v = np.nan if (a != a or b != b) else (a if a > b else b)
                if v < best or v != v:
                    best = v
                if best != best:
                    break
            if best < out[j] or best != best:
                out[j] = best
    return out


_FACE_SAMPLES = weakref.WeakKeyDictionary()  # fmap -> {face: samples}; both cells of a face share them


def _face_samples(cell, fmap, a, side):
    """The candidate centres of the cell's face along axis a, side +-1: face fractions fb, fc (n,), parameters (n, 3),
    points (n, 3) and Jacobians (n, 3, 3) of F there, and the face's boundary points (m, 3) (_boundary). Read-only;
    the same arrays for the two cells that share the face."""
    key = cell.face_key(a, side > 0)
    try:
        faces = _FACE_SAMPLES.setdefault(fmap, {})
    except TypeError:  # a map that cannot be weakly referenced is simply not cached
        faces = {}
    if key not in faces:
        fb, fc = (x.ravel() for x in np.meshgrid(_CENTRES, _CENTRES, indexing="ij"))
        uvw = _face_uvw(cell, a, side, fb, fc)
        x0, jac = fmap.evaluate_with_jacobian(uvw)
        samples = (fb, fc, uvw, np.asarray(x0), np.asarray(jac), _boundary(cell, fmap, a, side))
        for arr in samples:
            arr.setflags(write=False)
        faces[key] = samples
    return faces[key]


def _face_frames(cell, fmap, a, side, axes_pts, axes_r, depth, region=None):
    """What _candidates needs of a face whatever the text: face fractions' distance from the face's centre (n,),
    parameters uvw (n, 3), points x0 (n, 3) and outward normals (n, 3) of its n samples; for both text directions
    (2n rows: up along either in-face parameter) the centres relative to the face's mean point, normals, up and
    right (2n, 3) and which may hold text (2n,); and the keep-out points (_keep_out) of its outline and the joint
    axes."""
    b, c = _cyclic(a)
    fb, fc, uvw, x0, jac, edge = _face_samples(cell, fmap, a, side)
    normals = _outward(jac, a, side, int(getattr(fmap, "orientation", 1) or 1))
    good = np.any(normals != 0, axis=1)
    # differences of coordinates ~100 mm lose less to rounding about a point on the face
    origin = x0.mean(axis=0)
    x0_local = x0 - origin
    edge = edge - origin
    # the face's outline keeps the text MARGIN_MM inside it; an axis point keeps it R away, but only within reach
    # of the face along the normal: below it, a groove `depth` deep leaves R - r - clearance = JOINT_CLEAR_MM of
    # wall to a hole whose axis lies deeper than depth + R, so such an axis (one running along the face) is no bar
    on_piece = good
    if region is not None:
        outline, covered = region.on_face(x0, normals)
        edge = np.concatenate([edge, outline - origin])
        on_piece = good & covered
    ko = _keep_out(np.concatenate([edge, axes_pts - origin]),
                   np.concatenate([np.full(len(edge), MARGIN_MM), axes_r]),
                   np.concatenate([np.full(len(edge), -np.inf), -(depth + axes_r)]),
                   np.concatenate([np.full(len(edge), np.inf), TOP_MM + 2.0 + axes_r]))
    off_centre = np.round(np.hypot(fb - 0.5, fc - 0.5), 6)
    # both text directions (up along either in-face parameter) at once: centres k = 0 .. n-1, then n .. 2n-1
    tangent = np.concatenate([jac[:, :, b], jac[:, :, c]])
    normals2, x0_2 = np.concatenate([normals, normals]), np.concatenate([x0_local, x0_local])
    up = tangent - np.einsum("ki,ki->k", tangent, normals2)[:, None] * normals2
    size = np.linalg.norm(up, axis=1)
    ok = np.concatenate([on_piece, on_piece]) & (size > 1e-12)
    up = up / np.maximum(size, 1e-300)[:, None]
    right = np.cross(up, normals2)
    return off_centre, uvw, x0, normals, x0_2, normals2, up, right, ok, ko


def _candidates(cell, fmap, a, side, has_joint, axes_pts, axes_r, text, depth, order, stroke=MIN_STROKE_MM, rank=None,
                region=None, memo=None):
    """Every (centre, direction) on one face that holds the text -> _Cands (their sort keys and site arguments as
    arrays: a mesh model's faces give tens of thousands, of which a few are measured). rank: the face's class in the
    site rule (default: has_joint); region: a _BodyFaces of the piece, whose real outline on the face then keeps the
    text in as the face's own edge does, and whose centres must lie on the piece. memo: a dict for the face's
    _face_frames, for calls on the same cell, map, joints and depth."""
    ink_w, ink_h = _ink(text)
    aspect = ink_w / ink_h
    hmin = min_height_mm(text, stroke)
    key = ("face", int(a), int(side), id(region))
    frames = None if memo is None else memo.get(key)
    if frames is None:
        frames = _face_frames(cell, fmap, a, side, axes_pts, axes_r, depth, region)
        if memo is not None:
            memo[key] = frames + (region,)  # the region kept alive, so that its id stays its own
    off_centre, uvw, x0, normals, x0_2, normals2, up, right, ok, ko = frames[:10]
    # the face's outline and the joint axes, seen along the normal. A height does not depend on the stroke, which
    # only sets the least height kept: at or above the least height it was measured for, a height is exact (each
    # centre on its own), so a finer stroke's pass measures again only the centres below that
    hkey = ("height", int(a), int(side), id(region), str(text))
    known = None if memo is None else memo.get(hkey)
    tkey = ("terms", int(a), int(side), id(region))
    terms = None if memo is None else memo.get(tkey)
    if terms is None:
        terms = _centre_terms(ko, x0_2, normals2, right, up)
        if memo is not None:
            memo[tkey] = terms
    if known is None:
        height = _heights_allowed(ko, x0_2, normals2, right, up, aspect, MAX_HEIGHT_MM, hmin, terms)
    else:
        height, floor = known
        if hmin < floor:
            again = np.flatnonzero(height < floor)
            height = height.copy()
            height[again] = _heights_allowed(ko, x0_2[again], normals2[again], right[again], up[again], aspect,
                                             MAX_HEIGHT_MM, hmin, _terms_at(terms, again))
    if memo is not None and (known is None or hmin < known[1]):
        memo[hkey] = (height, hmin)
    j = np.flatnonzero(ok & (height >= hmin))
    k, i = np.divmod(j, len(x0))
    u = up[j]
    # upright text where the face allows it: up turned to the global +z, so labels read alike
    flip = (u[:, 2] < -1e-9) | ((np.abs(u[:, 2]) <= 1e-9)
                                & ((u[:, 1] < -1e-9) | ((np.abs(u[:, 1]) <= 1e-9) & (u[:, 0] < 0))))
    u = np.where(flip[:, None], -u, u)
    h = height[j]
    # Python's round (correctly rounded, unlike np.round's scaling) keeps the order the site rule always had
    neg_h = np.array([-round(v, 3) for v in h.tolist()], dtype=float)
    return _Cands(int(has_joint if rank is None else rank), neg_h, off_centre[i], int(order), k, i, x0, normals, u, h,
                  uvw)


@dataclass(frozen=True, eq=False)
class _Cands:
    """The candidates of one face (_candidates), c of them: the sort key of each (rank, -height rounded to 0.001 mm,
    distance of the centre from the face's centre in face fractions, the face's order, direction k, centre i; (c,)
    arrays but rank and order) and what _make_site needs: centres x0 (n, 3), normals (n, 3) and parameters uvw (n, 3)
    of the face's n samples (indexed by i), the text's up (c, 3) and height (c,)."""

    rank: int
    neg_height: np.ndarray
    off_centre: np.ndarray
    order: int
    k: np.ndarray
    i: np.ndarray
    x0: np.ndarray
    normals: np.ndarray
    up: np.ndarray
    height: np.ndarray
    uvw: np.ndarray

    def args(self, c):
        """The site arguments of candidate c: (centre, normal, up, height, uvw)."""
        i = self.i[c]
        return self.x0[i], self.normals[i], self.up[c], float(self.height[c]), self.uvw[i]


def _on_face(cell, fmap, a, uvw0, center, normal, up, target, st, inv=None):
    """Face points over `target` (n, 2), points (x, y) of the tangent plane at `center`, by Newton on the face's two
    parameters from the guess st (n, 2) -> (points (n, 3), parameters (n, 2), inverse Jacobians d(s, t)/d(x, y)
    (n, 2, 2), ok); ok is False where Newton left the face or did not converge. inv: inverse Jacobians to start with
    (from nearby points), else the map's own at st."""
    b, c = _cyclic(a)
    right = np.cross(up, normal)
    lo, hi = cell.box
    box_lo, box_hi = np.asarray(lo, float)[[b, c]], np.asarray(hi, float)[[b, c]]
    uvw = np.repeat(np.asarray(uvw0, float)[None], len(target), axis=0)
    proj = np.stack([right, up], axis=1)  # (3, 2)
    fresh, last = inv is None, np.inf
    for _ in range(25):
        st = np.clip(st, box_lo, box_hi)
        uvw[:, b], uvw[:, c] = st[:, 0], st[:, 1]
        # Newton contracts quadratically, so once a step has gained 10x the Jacobian it used serves the next steps as
        # well (a chord step), and the map evaluates in a third of the time without its derivatives
        if fresh:
            x, jac = fmap.evaluate_with_jacobian(uvw)
            j = np.einsum("nik,ir->nrk", jac[:, :, [b, c]], proj)  # d (x, y) / d (s, t)
            det = j[:, 0, 0] * j[:, 1, 1] - j[:, 0, 1] * j[:, 1, 0]
            inv = np.stack([np.stack([j[:, 1, 1], -j[:, 0, 1]], 1), np.stack([-j[:, 1, 0], j[:, 0, 0]], 1)], 1)
            inv /= np.where(det == 0.0, np.inf, det)[:, None, None]  # a collapsed spot takes no step, never converges
        else:
            x = fmap.evaluate(uvw)
        err = (x - center) @ proj - target
        worst = float(np.sqrt((err * err).sum(axis=1)).max())
        if worst < 1e-7:
            break
        fresh, last = worst > 0.1 * last, worst
        st = st - np.einsum("nrk,nk->nr", inv, err)
    return x, st, inv, bool(worst < 1e-5)


def _spline_grid(xs, ys, values, x_new, y_new):
    """Smooth values (len(ys), len(xs), d) on a grid -> their cubic spline on the grid x_new, y_new."""
    from scipy.interpolate import RectBivariateSpline

    deg_y, deg_x = min(3, len(ys) - 1), min(3, len(xs) - 1)
    return np.stack([RectBivariateSpline(ys, xs, values[..., i], kx=deg_y, ky=deg_x)(y_new, x_new)
                     for i in range(values.shape[-1])], axis=-1)


def _cell_means(grid):
    """Values (ny, nx, ...) on a grid -> their mean over each cell's corners (ny - 1, nx - 1, ...)."""
    return 0.25 * (grid[:-1, :-1] + grid[1:, :-1] + grid[:-1, 1:] + grid[1:, 1:])


def _heights(cell, fmap, a, center, normal, up, uvw0, xs, ys, st=None, inv=None):
    """Surface heights (len(ys), len(xs)) mm along `normal` above the tangent plane at points (x, y) of it, by Newton
    on the face's two parameters -> (heights, parameters (ny, nx, 2), inverse Jacobians (ny, nx, 2, 2), ok); ok is
    False where Newton left the face or did not converge. st, inv: a guess of both (as _on_face takes them), else one
    from the face's tangent plane, refined on a coarse grid first."""
    b, c = _cyclic(a)
    uvw0 = np.asarray(uvw0, float)
    gx, gy = np.meshgrid(xs, ys)
    target = np.stack([gx.ravel(), gy.ravel()], axis=1)
    if st is None:
        right = np.cross(up, normal)
        _, jac0 = fmap.evaluate_with_jacobian(uvw0[None])
        j2 = np.array([[jac0[0][:, b] @ right, jac0[0][:, c] @ right], [jac0[0][:, b] @ up, jac0[0][:, c] @ up]])
        st = uvw0[[b, c]][None] + target @ np.linalg.inv(j2).T
        if min(len(xs), len(ys)) > 8:
            # every 4th sample first: from there the rest starts close to its answer, with a Jacobian to match
            ix, iy = (np.unique(np.r_[0:len(v):4, len(v) - 1]) for v in (xs, ys))
            grid = st.reshape(len(ys), len(xs), 2)
            _, coarse, cinv, ok = _on_face(cell, fmap, a, uvw0, center, normal, up,
                                           target.reshape(len(ys), len(xs), 2)[np.ix_(iy, ix)].reshape(-1, 2),
                                           grid[np.ix_(iy, ix)].reshape(-1, 2))
            if ok:
                shape = (len(iy), len(ix))
                st = _spline_grid(xs[ix], ys[iy], coarse.reshape(shape + (2,)), xs, ys).reshape(-1, 2)
                inv = _spline_grid(xs[ix], ys[iy], cinv.reshape(shape + (4,)), xs, ys).reshape(-1, 2, 2)
    else:
        st = np.asarray(st, float).reshape(-1, 2)
        inv = None if inv is None else np.asarray(inv, float).reshape(-1, 2, 2)
    x, st, inv, ok = _on_face(cell, fmap, a, uvw0, center, normal, up, target, st, inv)
    h = ((x - center) @ normal).reshape(gx.shape)
    return h, st.reshape(gx.shape + (2,)), inv.reshape(gx.shape + (2, 2)), ok


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


def _make_site(cell, fmap, a, side, has_joint, args, text, outer=False):
    """Measure the surface under the text at one candidate -> LabelSite, or None when it is too curved there."""
    center, normal, up, height, uvw0 = args
    ink_w, ink_h = _ink(text)
    half_x = 0.5 * height * ink_w / ink_h + 0.5
    half_y = 0.5 * height + 0.5
    xs, ys = _axis_grid(half_x), _axis_grid(half_y)
    h, st, inv, ok = _heights(cell, fmap, a, center, normal, up, uvw0, xs, ys)
    if not ok:
        return None
    gy, gx = np.gradient(h, ys, xs)
    if float(np.max(np.hypot(gx, gy))) > MAX_SLOPE:
        return None
    # the interpolant's error, measured at the cells' centres
    xm, ym = 0.5 * (xs[1:] + xs[:-1]), 0.5 * (ys[1:] + ys[:-1])
    hm, _, _, ok = _heights(cell, fmap, a, center, normal, up, uvw0, xm, ym, st=_spline_grid(xs, ys, st, xm, ym),
                            inv=_cell_means(inv))
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
                     ro[4], ro[5], ro[6], err, bool(outer))


_CENTRES_OF = weakref.WeakKeyDictionary()  # fmap -> {domain: the model's centre (3,)}


def _model_centre(tiling, fmap):
    """Mean of F over a 5 x 5 x 5 grid of the domain (3,): which way a face looks, into the model or out of it."""
    key = tuple(np.asarray(tiling.domain, float).ravel())
    try:
        known = _CENTRES_OF.setdefault(fmap, {})
    except TypeError:
        known = {}
    if key not in known:
        lo, hi = np.asarray(tiling.domain, float)
        t = np.linspace(0.1, 0.9, 5)
        uvw = lo + np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * (hi - lo)
        known[key] = np.asarray(fmap.evaluate(uvw)).mean(axis=0)
    return known[key]


def _outer_faces(cell, tiling, fmap):
    """The cell's faces on D's boundary (none across a periodic seam) -> list of (axis, side, hidden): hidden when the
    face looks into the model (the inside of a shell, out of sight once assembled) rather than out of it."""
    shared = {(f.axis, side) for f, side in tiling.faces_of(tuple(cell.index))}
    centre = _model_centre(tiling, fmap)
    out = []
    for a in range(3):
        if a in tuple(tiling.periodic):
            continue
        for side in (-1, +1):
            if (a, side) in shared:
                continue
            _, _, _, x0, jac, _ = _face_samples(cell, fmap, a, side)
            normals = _outward(jac, a, side, int(getattr(fmap, "orientation", 1) or 1))
            look = float(np.einsum("ni,ni->n", normals, centre - x0).mean())
            out.append((a, side, look > 0.0))
    return out


def label_sites(cell, tiling, fmap, joints, text=None, depth=DEPTH_MM, stroke=MIN_STROKE_MM, tries=64, avoid=None,
                region=None, outer=True, measured=None):
    """The places for the cell's label, best first (rule in the module docstring): LabelSites that hold `text`
    (default: the piece id) with strokes of at least `stroke` mm, at most `tries` candidates measured per class; none
    whose normal is within 45 degrees of `avoid` (3,) (the bed, where the text would print upside down on the plate).
    region: the piece's _BodyFaces, to keep the text on the piece's real faces (a mesh model's piece covers only part
    of its cage cell's faces). outer: also D's outer faces, after every inner one (the hidden ones first).
    measured: a dict that keeps the sites measured and the faces' frames, for calls on the same cell, map, joints
    and depth (label_piece's): a finer stroke ranks the same sites first, and each costs a surface measurement."""
    text = str(text if text is not None else cell.id)
    if not _outline(text)[0]:
        return
    index = tuple(cell.index)
    axes_pts, axes_r = _joint_axes(index, joints)
    # classes in the order they are tried: inner faces without a joint, with one; outer faces hidden, in sight
    faces = [(int(hj), order, face.axis, side, hj)
             for order, (face, side) in enumerate(tiling.faces_of(index))
             for hj in [bool(_face_joints(face, joints))]]
    # A class is measured only when none of the earlier ones holds the text: the same order as sorting all at once.
    for rank in range(4 if outer else 2):
        if rank == 2:  # the outer faces are looked at only when no inner face held the text
            n = len(faces)
            outer_faces = None if measured is None else measured.get("outer faces")
            if outer_faces is None:  # every text and stroke of label_piece asks the same of the cell
                outer_faces = _outer_faces(cell, tiling, fmap)
                if measured is not None:
                    measured["outer faces"] = outer_faces
            faces += [(2 if hidden else 3, n + k, a, side, False) for k, (a, side, hidden) in enumerate(outer_faces)]
        found = [(_candidates(cell, fmap, a, side, hj, axes_pts, axes_r, text, depth, order, stroke, rank=rank,
                              region=region, memo=measured), a, side, hj)
                 for r, order, a, side, hj in faces if r == rank]
        found = [f for f in found if len(f[0].k)]
        if not found:
            continue
        # every candidate of the class in the order of its key (rank, -height, off centre, face order, k, i): the
        # keys are distinct, so this is the order a sort of the key tuples gives
        face = np.concatenate([np.full(len(f[0].k), n) for n, f in enumerate(found)])
        at = np.concatenate([np.arange(len(f[0].k)) for f in found])
        key = [np.concatenate([getattr(f[0], name) for f in found]) for name in ("i", "k")]
        key += [np.repeat([f[0].order for f in found], [len(f[0].k) for f in found])]
        key += [np.concatenate([getattr(f[0], name) for f in found]) for name in ("off_centre", "neg_height")]
        # each class measures `tries` candidates of its own: a crowded inner face whose small spots turn out too
        # curved must not use up the tries of a clear face further down the list
        left = tries
        for c in np.lexsort(key).tolist():
            if left <= 0:
                break
            cands, a, side, hj = found[face[c]]
            args = cands.args(at[c])
            if avoid is not None and float(np.dot(args[1], avoid)) > _AVOID_COS:
                continue
            left -= 1
            if measured is None:
                site = _make_site(cell, fmap, a, side, hj, args, text, outer=rank >= 2)
            else:
                # the site is fixed by its face, sample, direction and height (args follow from those)
                known = ("site", text, a, side, hj, rank >= 2, int(cands.i[at[c]]), int(cands.k[at[c]]), args[3])
                if known not in measured:
                    measured[known] = _make_site(cell, fmap, a, side, hj, args, text, outer=rank >= 2)
                site = measured[known]
            if site is not None:
                yield site


def choose_label_site(cell, tiling, fmap, joints, text=None, depth=DEPTH_MM, stroke=MIN_STROKE_MM):
    """The best place for the cell's label -> LabelSite, or None when no inner face holds `text` (default: the
    piece id) with `stroke` mm strokes: a single cell, or faces too small or too crowded with joints."""
    return next(iter(label_sites(cell, tiling, fmap, joints, text, depth, stroke)), None)


# ---------------------------------------------------------------------------------------------------------------------
# Engraving


def _mesh_arrays(body):
    """A Manifold's vertices (n, 3) float64 and triangles (m, 3) int64."""
    mesh = body.to_mesh64()
    return (np.asarray(mesh.vert_properties, dtype=float)[:, :3],
            np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3))


def _measured(body, site, arrays=None):
    """Heights (ny, nx) of the body's own surface above the site's tangent plane (its printed surface, not F), by a ray
    down the normal at every grid point, F's height where the ray finds nothing near it; (ny, nx) bool: where the ray
    found the body's surface near F's (False where the face of F lies off the body, as a cage's face outside a mesh
    model does); and (ny, nx) mm: how thick the body is there along the ray, from that surface to the next one it meets
    going down (inf where it meets none within reach, or off the body): a face whose other side comes close behind it (a
    gear's tooth flank behind a cut face) has no room for a groove.

    All rays are parallel, so in the site's frame each is a point of the plane: a triangle is hit where its shadow
    covers the point, at the height its plane has there. Each triangle is tested only against the grid points
    inside its shadow's box."""
    h = np.array(site.heights, dtype=float)
    xs, ys = np.asarray(site.grid_x, float), np.asarray(site.grid_y, float)
    frame = site.frame()
    span = float(h.max() - h.min()) + 2.0
    verts, faces = arrays if arrays is not None else _mesh_arrays(body)
    verts = (verts - frame[:, 3]) @ frame[:, :3]
    corners = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    lo = np.minimum(np.minimum(corners[0], corners[1]), corners[2])
    hi = np.maximum(np.maximum(corners[0], corners[1]), corners[2])
    # each ray runs from h + span down to h - span
    keep = np.flatnonzero((hi[:, 0] >= xs[0]) & (lo[:, 0] <= xs[-1]) & (hi[:, 1] >= ys[0]) & (lo[:, 1] <= ys[-1])
                          & (hi[:, 2] >= h.min() - span) & (lo[:, 2] <= h.max() + span))
    tri, lo, hi = verts[faces[keep]], lo[keep], hi[keep]  # (t, 3 corners, xyz in the frame)
    dx, dy = xs[1] - xs[0], ys[1] - ys[0]
    i0 = np.clip(np.floor((lo[:, 0] - xs[0]) / dx), 0, len(xs) - 1).astype(np.int64)
    i1 = np.clip(np.ceil((hi[:, 0] - xs[0]) / dx), 0, len(xs) - 1).astype(np.int64)
    j0 = np.clip(np.floor((lo[:, 1] - ys[0]) / dy), 0, len(ys) - 1).astype(np.int64)
    j1 = np.clip(np.ceil((hi[:, 1] - ys[0]) / dy), 0, len(ys) - 1).astype(np.int64)
    nx_t, ny_t = i1 - i0 + 1, j1 - j0 + 1
    count = nx_t * ny_t
    t = np.repeat(np.arange(len(tri)), count)
    r = np.arange(len(t)) - np.repeat(np.cumsum(count) - count, count)  # rank of the pair within its triangle
    gi = i0[t] + r % nx_t[t]
    gj = j0[t] + r // nx_t[t]
    a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
    px, py = xs[gi], ys[gj]
    e1x, e1y, e2x, e2y = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1], c[:, 0] - a[:, 0], c[:, 1] - a[:, 1]
    qx, qy = px - a[:, 0], py - a[:, 1]
    det = e1x * e2y - e1y * e2x
    with np.errstate(divide="ignore", invalid="ignore"):
        wb = (qx * e2y - qy * e2x) / det
        wc = (e1x * qy - e1y * qx) / det
        z = a[:, 2] + wb * (b[:, 2] - a[:, 2]) + wc * (c[:, 2] - a[:, 2])  # not finite for edge-on triangles
        eps = 1e-9  # a ray through an edge or a corner hits both sides; either gives the same height
        inside = (np.abs(det) > 1e-15) & (wb >= -eps) & (wc >= -eps) & (wb + wc <= 1 + eps)
    ref = h[gj, gi]
    inside &= (z >= ref - span) & (z <= ref + span)
    first = np.full(h.shape, -np.inf)  # the first hit going down is the highest
    np.maximum.at(first, (gj[inside], gi[inside]), z[inside])
    near = np.abs(first - h) < 0.5  # the first hit is this face, not some other part of the piece
    h[near] = first[near]
    # the next hit below the first is where the ray leaves the body again (a hit within rounding of the first is the
    # same surface, met on the edge of two of its triangles)
    beyond = inside & (z < first[gj, gi] - 1e-6)
    second = np.full(h.shape, -np.inf)
    np.maximum.at(second, (gj[beyond], gi[beyond]), z[beyond])
    wall = np.full(h.shape, np.inf)
    wall[near] = first[near] - second[near]  # first is finite there; second -inf where the ray leaves nowhere near
    return h, near, wall


def engrave(body, site, text=None, depth=DEPTH_MM, what=None, stroke=MIN_STROKE_MM, arrays=None, measured=None):
    """body (manifold3d.Manifold, mm) with `text` (default, and the text the site was sized for: the site's) cut
    `depth` mm into it at `site` -> Manifold. measured: _measured(body, site) when the caller has it.
    The groove is >= depth deep, measured from the body's own surface, everywhere under the text. Raises
    GeometryError naming `what` when the engine fails, when the body is thinner than depth + MIN_WALL_MM anywhere
    under the text (the groove would leave a skin no printer keeps, or open through), or when the piece would not
    stay one solid."""
    m3 = _m3()
    text = str(text if text is not None else site.text)
    what = what or f"piece labelled {text}"
    cs = text_cross_section(text, site.height_mm, stroke)
    if cs is None:
        raise GeometryError(f"{what}: label {text!r} at {site.height_mm:.2f} mm is too small to print "
                            f"(expected at least {min_height_mm(text, stroke):.2f} mm)")
    if not is_ok(body):
        raise GeometryError(f"{what}: the geometry engine failed before engraving (status {body.status().name})")
    xs, ys = site.grid_x, site.grid_y
    h, _near, wall = _measured(body, site, arrays) if measured is None else measured
    h = np.array(h, dtype=float)
    thinnest = float(np.min(wall, initial=np.inf))
    if thinnest < depth + MIN_WALL_MM:
        raise GeometryError(f"{what}: the piece is {thinnest:.2f} mm thick behind the label {text!r} (expected at "
                            f"least {depth + MIN_WALL_MM:g} mm: the {depth:g} mm groove and {MIN_WALL_MM:g} mm of "
                            f"wall under it)")
    gy, gx = np.gradient(h, ys, xs)
    # depth along the surface normal: a slope g lowers the floor by depth * sqrt(1 + g^2) measured vertically
    floor = h - depth * np.sqrt(1.0 + gx ** 2 + gy ** 2)
    # between samples and along the prism's edges the floor is linear: allow for the curvature over one cell and edge
    dxx = np.abs(np.diff(floor, 2, axis=1)).max(initial=0.0) / (xs[1] - xs[0]) ** 2
    dyy = np.abs(np.diff(floor, 2, axis=0)).max(initial=0.0) / (ys[1] - ys[0]) ** 2
    curv = max(dxx, dyy)
    step = max(xs[1] - xs[0], ys[1] - ys[0])

    # The walls are bent along straight verticals, so only the footprint needs refining: a prism this thin keeps
    # every wall edge (and its quads' diagonals) shorter than any target, so none of them is split. The floor's
    # chords sag by curv * edge^2 / 8: on a gently curved face, longer edges cost at most _SAG_MM of extra depth
    # and spare the piece (and every later stage) thousands of triangles.
    thick = 0.05
    # (refine_to_length leaves edges up to ~1.7x its target)
    target = _REFINE_MM[1] if curv <= 0 else np.clip(np.sqrt(8.0 * _SAG_MM / curv) / 1.7, *_REFINE_MM)
    prism = m3.Manifold.extrude(cs, thick).refine_to_length(float(target))
    # refining leaves some footprint edges longer than asked (up to ~1.7x): the sag allowance uses the real ones
    edge = _longest_edge(prism)
    allowance = site.error_mm + curv * (step ** 2 + edge ** 2) / 8.0 + 1e-3
    floor = floor - allowance
    ceiling = h + TOP_MM
    frame = site.frame()

    def bend(v):
        v = np.asarray(v, dtype=float)
        lo = _bilinear(xs, ys, floor, v[:, 0], v[:, 1])
        hi = _bilinear(xs, ys, ceiling, v[:, 0], v[:, 1])
        z = lo + (v[:, 2] / thick) * (hi - lo)
        return frame[:, 3] + v[:, 0:1] * frame[:, 0] + v[:, 1:2] * frame[:, 1] + z[:, None] * frame[:, 2]

    prism = prism.warp_batch(bend)
    if not is_ok(prism) or prism.is_empty():
        raise GeometryError(f"{what}: the geometry engine failed building the label {text!r} "
                            f"(status {prism.status().name})")
    before = len(body.decompose())
    out = body - prism
    if not is_ok(out):
        raise GeometryError(f"{what}: the geometry engine failed engraving the label {text!r} "
                            f"(status {out.status().name})")
    if out.is_empty() or len(out.decompose()) != before:
        raise GeometryError(f"{what}: engraving the label {text!r} splits the piece into {len(out.decompose())} "
                            f"bodies (expected {before}); the face is too thin for a {depth:g} mm groove")
    return out


def _longest_edge(solid):
    """Longest triangle edge of a manifold3d solid, mm."""
    mesh = solid.to_mesh()
    v = np.asarray(mesh.vert_properties)[:, :3]
    t = np.asarray(mesh.tri_verts)
    if len(t) == 0:
        return 0.0
    return float(max(np.linalg.norm(v[t[:, k]] - v[t[:, (k + 1) % 3]], axis=1).max() for k in range(3)))


class _BodyFaces:
    """The piece's own triangles, to find which part of a face of F it really covers (a mesh model's piece is its cage
    cell cut by the mesh: most of the cell's faces lie off it). Built from a Manifold in mm."""

    TOL_MM = 0.3  # a triangle this close to the face (and parallel to it) lies on it: tessellation and sampling error
    PARALLEL_COS = float(np.cos(np.radians(15.0)))

    def __init__(self, body, arrays=None):
        self.verts, self.tris = arrays if arrays is not None else _mesh_arrays(body)
        a, b, c = (self.verts[self.tris[:, k]] for k in range(3))
        cross = np.cross(b - a, c - a)
        size = np.linalg.norm(cross, axis=1)
        self.centroids = (a + b + c) / 3.0
        self.normals = cross / np.maximum(size, 1e-300)[:, None]
        self.keep = size > 1e-12

    def on_face(self, x0, normals):
        """For a face sampled at points x0 (n, 3) with outward normals (n, 3) (0 where collapsed): the outline of the
        piece's part of it, points (m, 3) at most ~_SAMPLE_MM apart, and which samples lie on the piece (n,) bool."""
        from scipy.spatial import cKDTree

        good = np.flatnonzero(np.any(normals != 0, axis=1))
        covered = np.zeros(len(x0), bool)
        if not len(good) or not self.keep.any():
            return np.zeros((0, 3)), covered
        tree = cKDTree(x0[good])
        spacing = float(np.median(tree.query(x0[good], k=2)[0][:, 1])) if len(good) > 1 else 1.0
        dist, near = tree.query(self.centroids)
        p, n = x0[good][near], normals[good][near]
        on = (self.keep & (dist < 2.0 * spacing + 1.0)
              & (np.abs(np.einsum("ni,ni->n", self.centroids - p, n)) < self.TOL_MM)
              & (np.einsum("ni,ni->n", self.normals, n) > self.PARALLEL_COS))
        tris = self.tris[on]
        if not len(tris):
            return np.zeros((0, 3)), covered
        edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
        uniq, count = unique_pairs(edges)
        border = uniq[count == 1]
        p0, p1 = self.verts[border[:, 0]], self.verts[border[:, 1]]
        steps = np.maximum(1, np.ceil(np.linalg.norm(p1 - p0, axis=1) / _SAMPLE_MM)).astype(np.int64)
        seg = np.repeat(np.arange(len(border)), steps)
        t = ((np.arange(len(seg)) - np.repeat(np.cumsum(steps) - steps, steps)) / steps[seg])[:, None]
        outline = p0[seg] + t * (p1[seg] - p0[seg])
        # which samples the piece covers: seen along the face's mean normal, inside one of its triangles there
        mean = normals[good].mean(axis=0)
        mean /= max(np.linalg.norm(mean), 1e-300)
        e1 = np.cross(mean, [1.0, 0.0, 0.0] if abs(mean[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(mean, e1)
        basis = np.stack([e1, e2], 1)
        a, b, c = (self.verts[tris[:, k]] @ basis for k in range(3))
        q = x0[good] @ basis
        lo, hi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
        e1x, e1y, e2x, e2y = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1], c[:, 0] - a[:, 0], c[:, 1] - a[:, 1]
        det = e1x * e2y - e1y * e2x
        flat = np.abs(det) > 1e-12
        hit = np.zeros(len(good), bool)
        for start in range(0, len(tris), 4096):
            sl = slice(start, start + 4096)
            qx = q[:, None, 0] - a[None, sl, 0]
            qy = q[:, None, 1] - a[None, sl, 1]
            inbox = ((q[:, None, 0] >= lo[None, sl, 0] - 1e-9) & (q[:, None, 0] <= hi[None, sl, 0] + 1e-9)
                     & (q[:, None, 1] >= lo[None, sl, 1] - 1e-9) & (q[:, None, 1] <= hi[None, sl, 1] + 1e-9)
                     & flat[None, sl])
            with np.errstate(divide="ignore", invalid="ignore"):
                wb = (qx * e2y[None, sl] - qy * e2x[None, sl]) / det[None, sl]
                wc = (e1x[None, sl] * qy - e1y[None, sl] * qx) / det[None, sl]
            hit |= (inbox & (wb >= -1e-9) & (wc >= -1e-9) & (wb + wc <= 1 + 1e-9)).any(axis=1)
        covered[good] = hit
        return outline, covered


def label_piece(body, cell, tiling, fmap, joints, text=None, depth=DEPTH_MM, what=None, texts=None, avoid=None,
                tries=6, cut_by_mesh=False):
    """Engrave the piece's id where it can be read -> (Manifold, LabelSite or None, note): the body unchanged and
    a note saying why when no place holds it. Tried in turn: each text of `texts` (default: just `text`, the piece
    id), at each stroke of STROKES_MM, on the best `tries` sites; a site is passed over when its face faces `avoid`
    (3,) (the bed), lies off the body (a cage's face outside a mesh) or the engraving fails. When sites were found
    off the body, the search runs again on the piece's real faces (_BodyFaces). cut_by_mesh: the piece is its cage
    cell cut by a mesh model, so the search runs on its real faces from the start: most of such a cell's faces lie
    off the piece, and each site measured there is a try lost (the bunny's pieces took the number after the id's
    tries had all landed off them)."""
    texts = list(texts) if texts else [str(text if text is not None else cell.id)]
    reasons = []
    budget = tries
    arrays = _mesh_arrays(body)  # the body's triangles, once for every site measured on it
    region = _BodyFaces(body, arrays) if cut_by_mesh else None
    measured = {}  # sites, for label_sites: each finer stroke and each pass tries the best ones again
    on_body = {}  # id of a site -> (the site, whether its text lies on the body)
    for _ in range(2):
        tries = budget
        off = False
        for stroke in STROKES_MM:
            for t in texts:
                sites = label_sites(cell, tiling, fmap, joints, text=t, depth=depth, stroke=stroke, tries=16,
                                    avoid=avoid, region=region, measured=measured)
                # the budget is looked at before the next site is asked for: each one costs a surface measurement
                while tries > 0:
                    site = next(sites, None)
                    if site is None:
                        break
                    tries -= 1
                    if id(site) not in on_body:
                        found = _measured(body, site, arrays)
                        on_body[id(site)] = site, float(np.mean(found[1])) >= 0.98, found
                    if not on_body[id(site)][1]:
                        reasons.append("off the piece")
                        off = True
                        continue
                    try:
                        out = engrave(body, site, t, depth=depth, what=what or cell.id, stroke=stroke,
                                      arrays=arrays, measured=on_body[id(site)][2])
                    except GeometryError as e:
                        reasons.append(str(e))
                        continue
                    return out, site, None
                tries = max(tries, 3)  # each fallback gets a few sites of its own
        if not off or region is not None:
            break
        region = _BodyFaces(body, arrays)
    if not reasons:
        return body, None, "no face large enough and clear of the joints"
    return body, None, "no site held it: " + "; ".join(sorted(set(reasons))[:3])


def engrave_bed(body, rotation, text, depth=DEPTH_MM, what=None):
    """The last resort for a piece with no inner face that holds its id: the text engraved mirrored into the side
    that rests on the bed, so it reads from below once printed. body: Manifold in assembled mm; rotation (4, 4) to
    the print orientation (the bed below). -> (Manifold, report dict) or (body, None) when the bed side holds no text
    MARGIN_MM inside its outline (holes included) with FINE_STROKE_MM strokes."""
    from .geometry import boolean

    m3 = _m3()
    rot = np.asarray(rotation, float)
    placed = body.transform(rot[:3, :])
    lowest = float(placed.bounding_box()[2])
    section = placed.slice(lowest + 0.05)
    inner = section.offset(-MARGIN_MM, m3.JoinType.Round)
    if inner.is_empty():
        return body, None
    x0, y0, x1, y1 = inner.bounds()
    full = float(inner.area())
    for stroke in STROKES_MM:
        for height in (MAX_HEIGHT_MM, 6.0, 5.0, 4.0, 3.0, 2.5, 2.0, 1.7):
            cs = text_cross_section(text, height, stroke)
            if cs is None:
                continue
            cs = cs.mirror((1.0, 0.0))  # seen from below, through the bed
            for turn in (0.0, 90.0):
                glyphs = cs.rotate(turn)
                gx0, gy0, gx1, gy1 = glyphs.bounds()
                box = m3.CrossSection.square((gx1 - gx0, gy1 - gy0)).translate((gx0, gy0))
                for fx in np.linspace(0.2, 0.8, 7):
                    for fy in np.linspace(0.2, 0.8, 7):
                        at = (x0 + fx * (x1 - x0), y0 + fy * (y1 - y0))
                        moved = box.translate(at)
                        if (moved - inner).area() > 1e-6 * full:
                            continue
                        # the groove from below the bed up to `depth` into the piece, back in assembled mm
                        prism = m3.Manifold.extrude(glyphs.translate(at), depth + 0.5).translate(
                            (0.0, 0.0, lowest - 0.5))
                        groove = prism.transform(np.linalg.inv(rot)[:3, :])
                        out = boolean(body, groove, "difference", what or f"piece labelled {text}")
                        if out.is_empty() or len(out.decompose()) != len(body.decompose()):
                            continue
                        centre = np.linalg.inv(rot) @ np.array([at[0] + (gx0 + gx1) / 2, at[1] + (gy0 + gy1) / 2,
                                                                lowest, 1.0])
                        down = np.linalg.inv(rot)[:3, :3] @ np.array([0.0, 0.0, -1.0])
                        return out, {"text": str(text), "face": "bed", "mirrored": True,
                                     "height_mm": round(float(height), 3),
                                     "center_mm": [round(float(x), 4) for x in centre[:3]],
                                     "normal": [round(float(x), 6) for x in down], "on_joint_face": False}
    return body, None


def label_pieces(tiling, fmap, pieces, joints, poses=None, workers=None, cut_by_mesh=False):
    """Engrave each piece's id on an inner face no joint uses, off its bed side. -> (pieces, {id: label report or
    None}, mm^3 removed). workers: a volpuzzle.workers.Workers that labels some of the pieces (same results);
    cut_by_mesh: the pieces are cage cells cut by a mesh model (label_piece)."""
    import dataclasses

    from .joint import cell_joints
    from .workers import MeshRef, map_pieces

    poses = poses or {}
    joints = list(joints or ())
    touching = cell_joints(joints)
    items = []
    for k, p in enumerate(pieces):
        pose = poses.get(p.id)
        items.append((k, p.id, tuple(p.cell), MeshRef(p.mesh), p.volume, None if pose is None else pose.down))
    shared = (tiling, fmap, touching, bool(cut_by_mesh))
    results = map_pieces(workers, _label_one, items, shared=shared, what="label")
    out = [p if r[0] is None else dataclasses.replace(p, mesh=r[0].mesh, volume=r[1],
                                                      triangles=int(len(r[0].mesh.faces)))
           for p, r in zip(pieces, results, strict=True)]
    sites = {p.id: r[2] for p, r in zip(pieces, results, strict=True)}
    removed = sum(r[3] for r in results)
    return out, sites, removed


_TURNED = {"0": "0", "1": "1", "6": "9", "8": "8", "9": "6"}  # digits as they read turned half a turn


def number_text(k: int) -> str:
    """The label of the piece numbered k (from 0) when its id does not fit: k + 1, with a dot after it when the
    number turned upside down reads as another (6 and 9, 16 and 91): a loose piece has no up, and its number must
    not pass for another's."""
    text = str(int(k) + 1)
    turned = "".join(_TURNED.get(c, "?") for c in reversed(text))
    return text + "." if "?" not in turned and turned != text else text


def _label_one(shared, item):
    """One piece of label_pieces, wherever it runs: shared (tiling, fmap, {cell: its joints}, cut_by_mesh), item
    (number, id, cell, MeshRef, volume, bed direction or None) -> (MeshRef or None when unchanged, volume, label
    report, mm^3 removed)."""
    from .geometry import solid_of, to_trimesh
    from .workers import MeshRef

    tiling, fmap, touching, cut_by_mesh = shared
    k, pid, cell, ref, volume_before, down = item
    # the piece id, else its number in the piece list (report.md gives the key)
    texts = (pid, number_text(k))
    mine = touching.get(cell, [])  # the only joints label_piece looks at
    try:
        body, site, note = label_piece(solid_of(ref.mesh, pid), tiling.cell(cell), tiling, fmap, mine,
                                       what=pid, texts=texts, avoid=down, cut_by_mesh=cut_by_mesh)
    except GeometryError as e:
        # A label is a convenience: a piece too thin to take the groove keeps its material and says why.
        return None, volume_before, {"skipped": str(e)}, 0.0
    if site is None:
        return None, volume_before, {"skipped": note}, 0.0
    mesh = to_trimesh(body)
    volume = float(body.volume())  # the engine's own sum, as compose measured p.volume; trimesh's costs more
    entry = site.to_report()
    entry["on_joint_face"] = bool(entry["on_joint_face"] or site_on_joint_face(site, mine, cell))
    return MeshRef(mesh), volume, entry, volume_before - volume


def bed_labels(pieces, labels, poses):
    """Pieces left without a label get it mirrored on their bed side (after the base cut, which would take it off).
    Updates labels in place. -> (pieces, mm^3 removed)"""
    import dataclasses

    from .geometry import from_trimesh, to_trimesh

    out, removed = [], 0.0
    for k, p in enumerate(pieces):
        entry = labels.get(p.id)
        pose = poses.get(p.id)
        if (entry or {}).get("text") or pose is None:
            out.append(p)
            continue
        body = from_trimesh(p.mesh, p.id)
        for text in (p.id, number_text(k)):
            new, site = engrave_bed(body, pose.rotation, text, what=p.id)
            if site is not None:
                volume = float(new.volume())
                mesh = to_trimesh(new)
                removed += p.volume - volume
                p = dataclasses.replace(p, mesh=mesh, volume=volume, triangles=int(len(mesh.faces)))
                labels[p.id] = site
                break
        out.append(p)
    return out, removed
