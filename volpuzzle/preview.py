"""preview.png: the assembled puzzle, an exploded view along the assembly plan and the first build plate, shaded.

Drawn with a depth buffer of our own (parallel projection, a compiled scanline loop): the pieces are drawn as they
are unless there are very many triangles (then each is simplified once), their triangles facing away from the eye
are dropped (pieces are closed), and every triangle is rasterised into fragments at twice the size; per pixel the
nearest fragment wins, then the picture is halved for smooth edges. Pieces get a dark outline where a pixel's
neighbour shows another piece, so seams and pins read at a glance. Painting triangles far to near instead (the
painter's algorithm) let long cut faces poke through the pieces in front of them.
"""

from functools import lru_cache
from pathlib import Path

import numpy as np
from numba import njit

from .io.png import png_bytes

# The eye: 28 degrees above the horizon, 60 degrees clockwise from the x axis (matplotlib's elev=28, azim=-60).
ELEV, AZIM = np.radians(28.0), np.radians(-60.0)
LIGHT = np.array([0.35, -0.5, 0.8]) / np.linalg.norm([0.35, -0.5, 0.8])
SUPERSAMPLE = 2
_OUTLINE = 0.45  # brightness kept on a piece's outline
_PREVIEW_TRIANGLES = 600_000  # below this in all, the preview draws the pieces as they are (a view is ~100 B each)


def _simplified(mesh, faces=1500):
    """(vertices (n, 3), faces (m, 3)) of a mesh simplified to about `faces` triangles, or the mesh's own when it has
    no more. Remembered per mesh: the preview and the step pictures ask for the same pieces."""
    from .geometry import memo

    return memo(mesh, ("preview", int(faces)), lambda: _simplify(mesh, faces))


def _nearest(mesh, faces):
    """(m,) index of the original triangle nearest each triangle of _simplified(mesh, faces), or None when the mesh
    is drawn as it is. Only per-triangle colours (a texture) need it, so it has a memo of its own."""
    from .geometry import memo

    def make():
        v, f = _simplified(mesh, faces)
        v0, f0 = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
        if len(f) == 0 or (len(f) == len(f0) and np.array_equal(f, f0)):  # drawn as it is
            return None
        from scipy.spatial import cKDTree

        return cKDTree(v0[f0].mean(axis=1)).query(v[f].mean(axis=1))[1]

    return memo(mesh, ("preview-nearest", int(faces)), make)


def _simplify(mesh, faces):
    v0, f0 = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    if len(f0) <= faces:
        return v0, f0
    try:
        import fast_simplification

        v, f = fast_simplification.simplify(v0.astype(np.float32), f0.astype(np.int32),
                                            target_reduction=1.0 - faces / len(f0))
        if len(f):
            return np.asarray(v, float), np.asarray(f)
    except Exception:  # noqa: BLE001 - a preview falls back to the full mesh rather than failing the build
        pass
    return v0, f0


def _face_cap(meshes, budget, least):
    """Triangles a piece keeps in a picture: the pieces as they are while all of them fit in `budget` triangles
    (simplifying costs more than drawing them), else at most `least` each (a sketch: a large puzzle's pieces are
    a few pixels wide)."""
    return max(int(least), int(budget) // max(len(meshes), 1))


def _view_axes():
    """(right, up, toward the eye) unit vectors of the screen, in world coordinates."""
    eye = np.array([np.cos(ELEV) * np.cos(AZIM), np.cos(ELEV) * np.sin(AZIM), np.sin(ELEV)])
    right = np.array([-np.sin(AZIM), np.cos(AZIM), 0.0])
    return right, np.cross(eye, right), eye


def _facing(parts):
    """Triangles of every part (vertices, faces, colours) that face the eye -> list of ((t, 3, 3) corners, (t, 3)
    colours in 0..1 shaded by the light)."""
    _, _, eye = _view_axes()
    out = []
    for v, f, rgb in parts:
        t = v[f]
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        front = n @ eye > 0  # closed pieces: the back faces are hidden behind the front ones anyway
        shade = 0.35 + 0.65 * np.clip(n[front] @ LIGHT, 0, 1)
        base = np.asarray(rgb, float).reshape(-1, 3)
        base = base[front] if len(base) == len(f) else np.broadcast_to(base[:1], (int(front.sum()), 3))
        out.append((t[front], np.clip(base / 255.0 * shade[:, None], 0, 1)))
    return out


def _visible(facing, offsets):
    """The facing triangles (_facing) of every part, moved by its offset -> (t, 3, 3) corners, (t, 3) colours,
    (t,) part index."""
    if not facing:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, int)
    tris = np.concatenate([t + off for (t, _), off in zip(facing, offsets, strict=True)])
    cols = np.concatenate([c for _, c in facing])
    owner = np.repeat(np.arange(len(facing)), [len(t) for t, _ in facing])
    return tris, cols, owner


def rasterize(px, py, depth, w, h):
    """Depth buffer: triangles with pixel corners px, py (t, 3) and depth (t, 3) (larger is nearer the eye) on a w x h
    grid -> (h, w) index of the nearest triangle at each pixel centre, -1 where none.

    Scanlines: every (triangle, pixel row) pair gets the span of pixel centres inside the triangle from its edges;
    a fragment's depth comes from its triangle's plane. Each depth (quantised to 2^-(62 - b) of the depth range)
    and triangle index (b bits) share one int64 key, and the largest key per pixel is the nearest fragment and
    says whose it is (ties go to the later triangle, whatever the order the fragments come in)."""
    px, py, depth = (np.ascontiguousarray(a, dtype=float).reshape(-1, 3) for a in (px, py, depth))
    t = len(px)
    # the general scan with nothing moved: pixel = 0 + (x + 0) * 1 exactly, and y enters negated
    return _depth_buffer(px, -py, depth, np.zeros(t, np.int64), np.zeros((1, 3)), np.ones(1, np.bool_),
                         (0.0, 0.0, 1.0), (float(depth.min()), float(depth.max())) if t else (0.0, 0.0), w, h)


def _depth_buffer(sx, sy, sz, part, shift, show, frame, zrange, w, h):
    """rasterize for screen coordinates sx, sy, sz (t, 3) (right, up, toward the eye) of triangles of parts
    part (t,), each part moved by shift (parts, 3) on the screen and drawn where show (parts,) is set; frame
    (cx, cy, scale) puts x at cx + x * scale pixels and y at cy - y * scale; zrange (lo, hi) bounds the depths of
    the drawn triangles. -> (h, w) triangle index, -1 where none."""
    buffer = _DepthKeys(sx, sy, sz, part, frame, zrange, w, h)
    keys = buffer.empty()
    buffer.draw(keys, show, shift)
    return buffer.triangles(keys)


class _DepthKeys:
    """A depth buffer of triangles sx, sy, sz (t, 3) on the screen, of parts part (t,), in one frame (cx, cy, scale)
    and depth range zrange (lo, hi), w x h pixels. Its keys (w * h,) int64 hold per pixel the depth (quantised to
    2^-(62 - b) of the range) and the index (b bits) of the nearest triangle drawn so far, -1 where none: drawing
    more triangles into keys never needs the earlier ones again."""

    def __init__(self, sx, sy, sz, part, frame, zrange, w, h):
        self.sx, self.sy, self.sz, self.part = sx, sy, sz, part
        self.frame, self.w, self.h = tuple(float(x) for x in frame), int(w), int(h)
        self.bits = max(1, int(len(sx) - 1).bit_length())
        self.zlo = float(zrange[0])
        self.zscale = (2.0 ** (62 - self.bits) - 1) / max(float(zrange[1]) - self.zlo, 1e-12)

    def empty(self):
        return np.full(self.w * self.h, -1, dtype=np.int64)

    def draw(self, keys, show, shift):
        """The triangles of the parts where show (parts,) is set, moved by shift (parts, 3), into keys."""
        if len(self.sx) and np.any(show):
            cx, cy, scale = self.frame
            _scan(self.sx, self.sy, self.sz, self.part, np.ascontiguousarray(shift, dtype=float),
                  np.ascontiguousarray(show, dtype=np.bool_), cx, cy, scale, self.w, self.h, self.zlo, self.zscale,
                  self.bits, keys)

    def triangles(self, keys):
        """(h, w) index of the nearest triangle at each pixel centre, -1 where none."""
        return np.where(keys >= 0, keys & ((1 << self.bits) - 1), -1).reshape(self.h, self.w)


@njit(cache=True, nogil=True)
def _scan(sx, sy, sz, part, shift, show, cx, cy, scale, w, h, zlo, zscale, bits, keys):
    # Compiled: a picture is millions of fragments, and numpy's version spent ~1 s a preview building (triangle,
    # row) and fragment arrays and scattering them with np.maximum.at, and the step pictures as much again in
    # moving and projecting the pieces for each step.
    for t in range(sx.shape[0]):
        p = part[t]
        if not show[p]:
            continue
        x0 = cx + (sx[t, 0] + shift[p, 0]) * scale
        x1 = cx + (sx[t, 1] + shift[p, 0]) * scale
        x2 = cx + (sx[t, 2] + shift[p, 0]) * scale
        y0 = cy - (sy[t, 0] + shift[p, 1]) * scale
        y1 = cy - (sy[t, 1] + shift[p, 1]) * scale
        y2 = cy - (sy[t, 2] + shift[p, 1]) * scale
        d0 = sz[t, 0] + shift[p, 2]
        dz1 = sz[t, 1] + shift[p, 2] - d0
        dz2 = sz[t, 2] + shift[p, 2] - d0
        e1x, e1y, e2x, e2y = x1 - x0, y1 - y0, x2 - x0, y2 - y0
        det = e1x * e2y - e1y * e2x
        if not abs(det) > 1e-12:
            continue
        dzdx = (dz1 * e2y - dz2 * e1y) / det
        dzdy = (dz2 * e1x - dz1 * e2x) / det
        # pixel rows whose centre (j + 0.5) lies within the triangle's height
        r0 = max(0.0, min(float(h), np.ceil(min(y0, y1, y2) - 0.5)))
        r1 = max(-1.0, min(float(h - 1), np.floor(max(y0, y1, y2) - 0.5)))
        for r in range(int(r0), int(r1) + 1):
            yc = r + 0.5
            xl, xr = np.inf, -np.inf
            if min(y0, y1) <= yc <= max(y0, y1) and y0 != y1:
                x = x0 + (yc - y0) * (x1 - x0) / (y1 - y0)
                xl, xr = min(xl, x), max(xr, x)
            if min(y1, y2) <= yc <= max(y1, y2) and y1 != y2:
                x = x1 + (yc - y1) * (x2 - x1) / (y2 - y1)
                xl, xr = min(xl, x), max(xr, x)
            if min(y2, y0) <= yc <= max(y2, y0) and y2 != y0:
                x = x2 + (yc - y2) * (x0 - x2) / (y0 - y2)
                xl, xr = min(xl, x), max(xr, x)
            if not xl <= xr:
                continue
            c0 = int(max(0.0, min(float(w), np.ceil(xl - 0.5 - 1e-9))))
            c1 = int(max(-1.0, min(float(w - 1), np.floor(xr - 0.5 + 1e-9))))
            row = r * w
            for c in range(c0, c1 + 1):
                z = d0 + (c + 0.5 - x0) * dzdx + (yc - y0) * dzdy
                q = (z - zlo) * zscale
                key = (np.int64(q if q > 0.0 else 0.0) << bits) | t
                if key > keys[row + c]:
                    keys[row + c] = key


def _paint(img, tris, cols, owner, box):
    """Draw the triangles into img (H, W, 3) uint8, the whole set scaled to fit box (x0, y0, x1, y1) in pixels."""
    if not len(tris):
        return
    right, up, eye = _view_axes()
    x = tris @ right
    y = tris @ up
    lo = np.array([x.min(), y.min()])
    span = np.maximum(np.array([x.max(), y.max()]) - lo, 1e-9)
    x0, y0, x1, y1 = box
    scale = min((x1 - x0) / span[0], (y1 - y0) / span[1])
    px = (x0 + x1) / 2 + (x - (lo[0] + span[0] / 2)) * scale
    py = (y0 + y1) / 2 - (y - (lo[1] + span[1] / 2)) * scale
    H, W = img.shape[:2]
    bx0, by0 = int(max(0, np.floor(px.min()) - 1)), int(max(0, np.floor(py.min()) - 1))
    bx1, by1 = int(min(W, np.ceil(px.max()) + 2)), int(min(H, np.ceil(py.max()) + 2))
    ibuf = rasterize(px - bx0, py - by0, tris @ eye, bx1 - bx0, by1 - by0)
    _shade(ibuf, cols[None], np.zeros(int(owner.max()) + 1, np.int64), owner, _OUTLINE, img, by0, bx0)


@njit(cache=True, nogil=True)
def _shade(ibuf, cols, which, owner, outline, img, top, left):
    """Colour the pixels of img (H, W, 3) uint8 that the depth buffer ibuf (h, w) covers, its corner at pixel (top,
    left) of img: triangle t of part owner[t] takes cols[which[owner[t]], t] (colours (k, t, 3) in 0..1), times
    `outline` where the pixel to the left or above shows another part or nothing, so that seams and pins read at a
    glance."""
    h, w = ibuf.shape
    for r in range(h):
        for c in range(w):
            t = ibuf[r, c]
            if t < 0:
                continue
            p = owner[t]
            f = 1.0
            if (c > 0 and (ibuf[r, c - 1] < 0 or owner[ibuf[r, c - 1]] != p)) or \
                    (r > 0 and (ibuf[r - 1, c] < 0 or owner[ibuf[r - 1, c]] != p)):
                f = outline
            for k in range(3):
                v = cols[which[p], t, k] * f
                img[top + r, left + c, k] = np.uint8(np.rint(min(max(v, 0.0), 1.0) * 255.0))


@lru_cache(maxsize=8)
def _font(size):
    """Pillow's default font at `size` px: loaded once per size (each step picture asks for it again)."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow before 10.1: only the small bitmap font
        return ImageFont.load_default()


def _text(draw, cx, top, text, size):
    font = _font(size)
    left, _, right, _ = draw.textbbox((0, 0), text, font=font)
    draw.text((cx - (right - left) / 2, top), text, fill=(0, 0, 0), font=font)


def plan_offsets(meshes, names, steps, explode=0.6):
    """Offsets (n, 3) mm that pull the puzzle apart along its assembly plan: every block slid in by a step moves
    back against its direction, by `explode` times the median piece size, and later steps carry what they move with
    them, so the view shows the plan's tree. steps: report.json assembly steps (dicts with pieces, direction)."""
    offsets = np.zeros((len(meshes), 3))
    if not meshes:
        return offsets
    size = float(np.median([np.linalg.norm(np.ptp(np.asarray(m.vertices), axis=0)) for m in meshes]))
    where = {n: i for i, n in enumerate(names)}
    for step in steps or ():
        d = step.get("direction")
        if d is None:
            continue
        moved = [where[p] for p in step.get("pieces") or () if p in where]
        offsets[moved] -= explode * size * np.asarray(d, float)
    return offsets


def _radial(meshes, explode):
    centers = np.array([np.asarray(m.vertices).mean(axis=0) for m in meshes])
    return (centers - centers.mean(axis=0)) * explode


def render_preview(path, meshes, colors, size=(1600, 800), explode=0.6, title=None, offsets=None, plate=None):
    """Write a PNG: the assembled puzzle, the exploded one and, with `plate`, the first build plate.

    meshes: list of Trimesh in mm; colors: (n, 3) uint8, or a list with one (3,) colour or one (m, 3) uint8 array of
    per-triangle colours per mesh; offsets: (n, 3) mm for the exploded view (plan_offsets), default radial from the
    centre; plate: ([(index into meshes, (4, 4) transform to the plate)], (w, d) plate size mm), drawn in a third
    panel (size is then widened by half)."""
    from PIL import Image, ImageDraw

    k = SUPERSAMPLE
    panels = 3 if plate is not None else 2
    width = size[0] if panels == 2 else size[0] * 3 // 2
    w, h = width * k, size[1] * k
    colors = list(colors)
    cap = _face_cap(meshes, _PREVIEW_TRIANGLES, 1500)
    parts = [_part(m, c, cap) for m, c in zip(meshes, colors, strict=True)]
    exploded = _radial(meshes, explode) if offsets is None else np.asarray(offsets, float)
    facing = _facing(parts)  # the assembled and the exploded views differ by offsets only
    views = [(facing, np.zeros((len(parts), 3)), "assembled"), (facing, exploded, "exploded")]
    if plate is not None:
        on_plate, (pw, pd) = plate
        import trimesh

        bed = trimesh.creation.box([pw, pd, 1.0])
        bed.apply_translation([pw / 2, pd / 2, -0.5])
        bed_parts = [_part(bed, (225, 225, 225), cap)]
        for i, m in on_plate:  # the simplified piece, moved: simplifying once serves every view
            v, f, c = parts[i]
            m = np.asarray(m, float)
            bed_parts.append((v @ m[:3, :3].T + m[:3, 3], f, c))
        views.append((_facing(bed_parts), np.zeros((len(bed_parts), 3)), "plate 1"))
    img = np.full((h, w, 3), 255, np.uint8)
    top = int(0.09 * h)
    margin = int(0.06 * w / panels)
    for i, (ps, offs, _) in enumerate(views):
        x0 = i * w // panels
        tris, cols, owner = _visible(ps, offs)
        _paint(img, tris, cols, owner, (x0 + margin, top + margin, x0 + w // panels - margin, h - margin))
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    for i, (_, _, label) in enumerate(views):
        _text(draw, (i + 0.5) * w / panels, int(0.05 * h), label, 19 * k)
    if title:
        _text(draw, w / 2, int(0.012 * h), str(title), 22 * k)
    Path(path).write_bytes(png_bytes(np.asarray(pil.reduce(k))))


def _part(mesh, rgb, faces):
    """(vertices, faces, colours) of a mesh ready to draw, with at most about `faces` triangles: one (3,) colour or
    (m, 3) per triangle."""
    rgb = np.asarray(rgb)
    v, f = _simplified(mesh, faces)
    if rgb.ndim == 2 and len(rgb) == len(mesh.faces):
        near = _nearest(mesh, faces)
        return v, f, (rgb if near is None else rgb[near])
    return v, f, rgb.reshape(3)


STEP_SIZE = (360, 270)  # pixels of one assembly step's picture
_STEP_FACES = 300  # triangles per piece in step pictures of a large puzzle: a sketch, many of them
_STEP_TRIANGLES = 200_000  # below this in all, step pictures draw the pieces as they are


def save_pictures(directory, pictures):
    """Files [(name, bytes)] written into directory (made if need be) -> their names."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for name, data in pictures:
        (directory / name).write_bytes(data)
    return [name for name, _ in pictures]


def step_pictures(meshes, names, colors, steps, size=STEP_SIZE):
    """One small PNG per assembly step, step-NN.png: the pieces placed so far in light grey, the block added in this
    step in its colours, drawn back against its direction with an arrow to where it goes. Every picture has one
    frame, on the whole puzzle and each block drawn back, so the steps line up. meshes: Trimesh in mm; names: their
    piece ids; colors (n, 3) uint8; steps: report.json assembly steps. -> [(file name, PNG bytes)], one per step
    (plain data: a worker may draw them while the build goes on)."""
    from PIL import Image, ImageDraw

    where = {n: i for i, n in enumerate(names)}
    cap = _face_cap(meshes, _STEP_TRIANGLES, _STEP_FACES)
    parts = [_simplified(m, cap) for m in meshes]
    right, up, eye = _view_axes()
    every = np.concatenate([v for v, _ in parts])
    reach = 0.6 * float(np.median([np.linalg.norm(np.ptp(v, axis=0)) for v, _ in parts]))
    w, h = size
    k = 1  # sketches: many of them, no supersampling
    # The view never changes, so each piece's triangles facing the eye are found and put on the screen (right, up,
    # depth) once; a step only shows some of them and moves the block it adds.
    facing = _facing([(v, f, (255, 255, 255)) for v, f in parts])
    axes = np.stack([right, up, eye], axis=1)
    screen = np.concatenate([t for t, _ in facing]).reshape(-1, 3, 3) @ axes  # (t, 3, 3)
    sx, sy, sz = (np.ascontiguousarray(screen[..., a]) for a in range(3))
    owner = np.repeat(np.arange(len(parts)), [len(t) for t, _ in facing])
    light = np.concatenate([c for _, c in facing])  # the shade alone, on white
    cols = np.stack([light * (215 / 255.0), light * (np.asarray(colors, float)[owner] / 255.0)])  # grey, own
    near, far = np.full(len(parts), np.inf), np.full(len(parts), -np.inf)  # each piece's depth range
    np.minimum.at(near, owner, sz.min(axis=1))
    np.maximum.at(far, owner, sz.max(axis=1))
    centres = np.array([v.mean(axis=0) for v, _ in parts])  # each piece's, for the arrows
    moves = []  # per step: the pieces of its block, its direction, and the way back on the screen
    for step in steps:
        moving = [where[p] for p in (step.get("pieces") or [step.get("piece")]) if p in where]
        d = step.get("direction")
        back = -reach * np.asarray(d, float) if d is not None else np.zeros(3)
        moves.append((moving, d, back, back @ axes))
    # One frame and one depth range for every step, spanning the puzzle and each block drawn back: the steps line up
    # exactly, and the pieces in place are drawn once into a depth buffer that every later step starts from (a step
    # then draws only its own block: at 256 pieces, 383 pictures each of all ~100k triangles were 5 CPU s). The
    # extremes of a moved copy are the moved extremes (rounding is monotonic), so no step looks at every vertex.
    every_x, every_y = every @ right, every @ up
    ex, ey = (every_x.min(), every_x.max()), (every_y.min(), every_y.max())
    backs = np.array([b for _, _, _, b in moves] or [np.zeros(3)])
    bx, by = backs[:, 0], backs[:, 1]
    lo = np.array([min(ex[0], ex[0] + bx.min()), min(ey[0], ey[0] + by.min())])
    span = np.maximum(np.array([max(ex[1], ex[1] + bx.max()), max(ey[1], ey[1] + by.max())]) - lo, 1e-9)
    scale = min((w * k * 0.9) / span[0], (h * k * 0.82) / span[1])
    frame = (w * k / 2 - (lo[0] + span[0] / 2) * scale, h * k * 0.54 + (lo[1] + span[1] / 2) * scale, scale)
    drawn = np.isfinite(near)  # pieces with a triangle facing the eye
    lows, highs = [near[drawn]], [far[drawn]]
    for moving, _, _, b in moves:
        shown = [p for p in moving if drawn[p]]
        lows.append(near[shown] + b[2]), highs.append(far[shown] + b[2])
    zlo, zhi = float(np.concatenate(lows).min(initial=0.0)), float(np.concatenate(highs).max(initial=1.0))
    buffer = _DepthKeys(sx, sy, sz, owner, frame, (zlo, zhi), w * k, h * k)
    placed = buffer.empty()  # the pieces in place so far
    in_place = np.zeros(len(parts), np.bool_)
    none = np.zeros((len(parts), 3))
    bases = _step_bases([m for m, _, _, _ in moves])
    last_use = {b: n for n, b in enumerate(bases) if b >= 0}
    saved = {}  # step -> the keys of the pieces in place before it, while a later step still starts from them

    def to_px(p):  # a point's pixel in the frame, as _scan places the corners
        return frame[0] + (p @ right) * scale, frame[1] - (p @ up) * scale

    files = []  # (name, PNG bytes)
    for n, (moving, d, back, back_screen) in enumerate(moves):
        if n in last_use:
            saved[n] = placed.copy()
        img = np.full((h * k, w * k, 3), 255, np.uint8)
        which = np.zeros(len(parts), np.int64)  # grey for the pieces in place, their own colours for the block
        which[moving] = 1
        show = np.zeros(len(parts), np.bool_)
        show[moving] = True
        shift = np.zeros((len(parts), 3))
        shift[moving] = back_screen
        base = bases[n]
        if base == -1:  # the block is new: every piece in place stays
            keys = placed.copy()
        elif base >= 0:
            keys = saved.pop(base) if last_use[base] == n else saved[base].copy()
        else:
            keys = buffer.empty()
            buffer.draw(keys, in_place & ~show, none)
        buffer.draw(keys, show, shift)
        _shade(buffer.triangles(keys), cols, which, owner, _OUTLINE, img, 0, 0)
        pil = Image.fromarray(img)
        draw = ImageDraw.Draw(pil)
        if moving and d is not None:
            centre = centres[moving].mean(axis=0)
            a, b = np.array(to_px(centre + back)), np.array(to_px(centre + 0.25 * back))
            _arrow(draw, a, b, width=3 * k)
        _text(draw, w * k / 2, 4 * k, f"step {n + 1}", 14 * k)
        files.append((f"step-{n + 1:02d}.png", png_bytes(np.asarray(pil.reduce(k)))))
        buffer.draw(placed, show, none)
        in_place[moving] = True
    return files


def _step_bases(blocks):
    """Where each step picture finds the pieces in place without its own block: blocks [[part index]] moved at each
    step -> per step -1 when none of its block is in place yet (the pieces in place, as they are), s >= 0 when the
    block's pieces in place were all placed from step s on and nothing else was since (the pieces in place before
    step s), -2 otherwise (drawn again). A plan assembles a block, then moves it whole: its pieces were the last
    placed, so the pieces in place without it are those of an earlier step."""
    first = {}  # part -> the step that placed it
    new_at = []  # per step, the parts it placed
    out = []
    for n, block in enumerate(blocks):
        mine = set(block)
        old = [p for p in block if p in first]
        if not old:
            out.append(-1)
        else:
            s = min(first[p] for p in old)
            out.append(s if all(p in mine for k in range(s, n) for p in new_at[k]) else -2)
        new_at.append([p for p in dict.fromkeys(block) if p not in first])
        first.update((p, n) for p in new_at[-1])
    return out


def _arrow(draw, a, b, width):
    """A black arrow from a to b (pixels), its head at b."""
    v = b - a
    length = float(np.linalg.norm(v))
    if length < 1e-6:
        return
    u = v / length
    n = np.array([-u[1], u[0]])
    head = min(0.35 * length, 8.0 * width)
    draw.line([tuple(a), tuple(b - u * head * 0.5)], fill=(0, 0, 0), width=int(width))
    draw.polygon([tuple(b), tuple(b - u * head + n * head * 0.5), tuple(b - u * head - n * head * 0.5)],
                 fill=(0, 0, 0))
