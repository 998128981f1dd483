"""preview.png: the assembled puzzle, an exploded view along the assembly plan and the first build plate, shaded.

Drawn with a depth buffer of our own (vectorised numpy, parallel projection): each piece is simplified once, its
triangles facing away from the eye are dropped (pieces are closed), and every triangle is rasterised into fragments
at twice the size; per pixel the nearest fragment wins, then the picture is halved for smooth edges. Pieces get a
dark outline where a pixel's neighbour shows another piece, so seams and pins read at a glance. Painting triangles
far to near instead (the painter's algorithm) let long cut faces poke through the pieces in front of them.
"""

import numpy as np

# The eye: 28 degrees above the horizon, 60 degrees clockwise from the x axis (matplotlib's elev=28, azim=-60).
ELEV, AZIM = np.radians(28.0), np.radians(-60.0)
LIGHT = np.array([0.35, -0.5, 0.8]) / np.linalg.norm([0.35, -0.5, 0.8])
SUPERSAMPLE = 2
_FRAGMENTS = 4_000_000  # fragments rasterised at once (each costs ~60 bytes across the temporary arrays)
_OUTLINE = 0.45  # brightness kept on a piece's outline


def _simplified(mesh, faces=1500, colors=None):
    """(vertices (n, 3), faces (m, 3), per-triangle colours (m, 3) or None) of a mesh simplified to about `faces`
    triangles; per-triangle colours follow the nearest original triangle."""
    v0, f0 = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    if len(f0) <= faces:
        return v0, f0, colors
    try:
        import fast_simplification

        v, f = fast_simplification.simplify(v0.astype(np.float32), f0.astype(np.int32),
                                            target_reduction=1.0 - faces / len(f0))
        v, f = np.asarray(v, float), np.asarray(f)
        if len(f):
            if colors is not None:
                from scipy.spatial import cKDTree

                _, near = cKDTree(v0[f0].mean(axis=1)).query(v[f].mean(axis=1))
                colors = colors[near]
            return v, f, colors
    except Exception:  # noqa: BLE001 - a preview falls back to the full mesh rather than failing the build
        pass
    return v0, f0, colors


def _view_axes():
    """(right, up, toward the eye) unit vectors of the screen, in world coordinates."""
    eye = np.array([np.cos(ELEV) * np.cos(AZIM), np.cos(ELEV) * np.sin(AZIM), np.sin(ELEV)])
    right = np.array([-np.sin(AZIM), np.cos(AZIM), 0.0])
    return right, np.cross(eye, right), eye


def _visible(parts, offsets):
    """Triangles facing the eye of every part, moved by its offset -> (t, 3, 3) corners, (t, 3) colours in 0..1,
    (t,) part index."""
    _, _, eye = _view_axes()
    tris, cols, owner = [], [], []
    for k, ((v, f, rgb), off) in enumerate(zip(parts, offsets, strict=True)):
        t = v[f] + off
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        front = n @ eye > 0  # closed pieces: the back faces are hidden behind the front ones anyway
        shade = 0.35 + 0.65 * np.clip(n[front] @ LIGHT, 0, 1)
        base = np.asarray(rgb, float).reshape(-1, 3)
        base = base[front] if len(base) == len(f) else np.broadcast_to(base[:1], (int(front.sum()), 3))
        tris.append(t[front])
        cols.append(np.clip(base / 255.0 * shade[:, None], 0, 1))
        owner.append(np.full(int(front.sum()), k))
    if not tris:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, int)
    return np.concatenate(tris), np.concatenate(cols), np.concatenate(owner)


def rasterize(px, py, depth, w, h):
    """Depth buffer: triangles with pixel corners px, py (t, 3) and depth (t, 3) (larger is nearer the eye) on a w x h
    grid -> (h, w) index of the nearest triangle at each pixel centre, -1 where none.

    Scanlines: every (triangle, pixel row) pair gets the span of pixel centres inside the triangle from its edges,
    so only covered pixels become fragments; a fragment's depth comes from its triangle's plane. Each depth
    (quantised to 2^-(62 - b) of the depth range) and triangle index (b bits) share one int64 key, so one
    np.maximum.at per batch keeps the nearest fragment and says whose it is."""
    keys = np.full(w * h, -1, dtype=np.int64)
    px, py, depth = (np.asarray(a, float) for a in (px, py, depth))
    e1x, e1y, e2x, e2y = px[:, 1] - px[:, 0], py[:, 1] - py[:, 0], px[:, 2] - px[:, 0], py[:, 2] - py[:, 0]
    det = e1x * e2y - e1y * e2x
    keep = np.flatnonzero(np.abs(det) > 1e-12)
    if not len(keep):
        return keys.reshape(h, w)
    bits = max(1, int(len(px) - 1).bit_length())
    zlo, zhi = float(depth.min()), float(depth.max())
    zscale = (2.0 ** (62 - bits) - 1) / max(zhi - zlo, 1e-12)
    dz1, dz2 = depth[:, 1] - depth[:, 0], depth[:, 2] - depth[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        dzdx = (dz1 * e2y - dz2 * e1y) / det
        dzdy = (dz2 * e1x - dz1 * e2x) / det
    # pixel rows whose centre (j + 0.5) lies within each triangle's height
    r0 = np.clip(np.ceil(py.min(axis=1) - 0.5), 0, h).astype(np.int64)[keep]
    r1 = np.clip(np.floor(py.max(axis=1) - 0.5), -1, h - 1).astype(np.int64)[keep]
    rows = np.maximum(r1 - r0 + 1, 0)
    t = np.repeat(keep, rows)
    yc = (np.repeat(r0, rows) + np.arange(len(t)) - np.repeat(np.cumsum(rows) - rows, rows)).astype(float) + 0.5
    xl, xr = np.full(len(t), np.inf), np.full(len(t), -np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        yi, yj, xi, xj = py[t, i], py[t, j], px[t, i], px[t, j]
        cross = (np.minimum(yi, yj) <= yc) & (yc <= np.maximum(yi, yj)) & (yi != yj)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = xi + (yc - yi) * (xj - xi) / (yj - yi)
        xl = np.where(cross, np.minimum(xl, x), xl)
        xr = np.where(cross, np.maximum(xr, x), xr)
    c0 = np.clip(np.ceil(xl - 0.5 - 1e-9), 0, w).astype(np.int64)
    c1 = np.clip(np.floor(xr - 0.5 + 1e-9), -1, w - 1).astype(np.int64)
    span = np.maximum(c1 - c0 + 1, 0)
    ends = np.cumsum(span)
    start = 0
    while start < len(t):
        # spans whose fragments fit in one batch (at least one span)
        base = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, base + _FRAGMENTS, side="right")))
        n = span[start:stop]
        tt = np.repeat(t[start:stop], n)
        gy = np.repeat(yc[start:stop], n)
        gx = (np.repeat(c0[start:stop], n) + np.arange(len(tt)) - np.repeat(np.cumsum(n) - n, n)).astype(float) + 0.5
        z = depth[tt, 0] + (gx - px[tt, 0]) * dzdx[tt] + (gy - py[tt, 0]) * dzdy[tt]
        key = (np.clip((z - zlo) * zscale, 0, None).astype(np.int64) << bits) | tt
        np.maximum.at(keys, (gy - 0.5).astype(np.int64) * w + (gx - 0.5).astype(np.int64), key)
        start = stop
    return np.where(keys >= 0, keys & ((1 << bits) - 1), -1).reshape(h, w)


def _paint(img, tris, cols, owner, box):
    """Draw the triangles into img (H, W, 3) float, the whole set scaled to fit box (x0, y0, x1, y1) in pixels."""
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
    hit = ibuf >= 0
    region = img[by0:by1, bx0:bx1]
    region[hit] = cols[ibuf[hit]]
    # outlines where the neighbouring pixel shows another part, or nothing
    part = np.where(hit, owner[np.maximum(ibuf, 0)], -1)
    edge = np.zeros_like(hit)
    edge[:, 1:] |= part[:, 1:] != part[:, :-1]
    edge[1:, :] |= part[1:, :] != part[:-1, :]
    edge &= hit
    region[edge] *= _OUTLINE


def _font(size):
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
    parts = [_part(m, c) for m, c in zip(meshes, colors, strict=True)]
    exploded = _radial(meshes, explode) if offsets is None else np.asarray(offsets, float)
    views = [(parts, np.zeros((len(parts), 3)), "assembled"), (parts, exploded, "exploded")]
    if plate is not None:
        on_plate, (pw, pd) = plate
        import trimesh

        bed = trimesh.creation.box([pw, pd, 1.0])
        bed.apply_translation([pw / 2, pd / 2, -0.5])
        bed_parts = [_part(bed, (225, 225, 225))]
        for i, m in on_plate:  # the simplified piece, moved: simplifying once serves every view
            v, f, c = parts[i]
            m = np.asarray(m, float)
            bed_parts.append((v @ m[:3, :3].T + m[:3, 3], f, c))
        views.append((bed_parts, np.zeros((len(bed_parts), 3)), "plate 1"))
    img = np.ones((h, w, 3))
    top = int(0.09 * h)
    margin = int(0.06 * w / panels)
    for i, (ps, offs, _) in enumerate(views):
        x0 = i * w // panels
        tris, cols, owner = _visible(ps, offs)
        _paint(img, tris, cols, owner, (x0 + margin, top + margin, x0 + w // panels - margin, h - margin))
    pil = Image.fromarray(np.round(np.clip(img, 0, 1) * 255).astype(np.uint8))
    draw = ImageDraw.Draw(pil)
    for i, (_, _, label) in enumerate(views):
        _text(draw, (i + 0.5) * w / panels, int(0.05 * h), label, 19 * k)
    if title:
        _text(draw, w / 2, int(0.012 * h), str(title), 22 * k)
    # zlib's fastest level: a third the time of the default for a picture about a quarter larger
    pil.reduce(k).save(path, format="PNG", compress_level=1)


def _part(mesh, rgb):
    """(vertices, faces, colours) of a mesh ready to draw: one (3,) colour or (m, 3) per triangle."""
    rgb = np.asarray(rgb)
    per_triangle = rgb.ndim == 2 and len(rgb) == len(mesh.faces)
    v, f, c = _simplified(mesh, colors=rgb if per_triangle else None)
    return v, f, (c if per_triangle else rgb.reshape(3))


STEP_SIZE = (360, 270)  # pixels of one assembly step's picture
_STEP_FACES = 300  # triangles per piece in step pictures: a sketch, many of them


def render_steps(directory, meshes, names, colors, steps, size=STEP_SIZE):
    """One small PNG per assembly step, directory/step-NN.png: the pieces placed so far in light grey, the block
    added in this step in its colours, drawn back against its direction with an arrow to where it goes. Every
    picture is framed on the whole puzzle, so the steps line up. meshes: Trimesh in mm; names: their piece ids;
    colors (n, 3) uint8; steps: report.json assembly steps. -> list of file names, one per step."""
    from pathlib import Path

    from PIL import Image, ImageDraw

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    where = {n: i for i, n in enumerate(names)}
    parts = [_simplified(m, faces=_STEP_FACES)[:2] for m in meshes]
    right, up, eye = _view_axes()
    every = np.concatenate([v for v, _ in parts])
    reach = 0.6 * float(np.median([np.linalg.norm(np.ptp(v, axis=0)) for v, _ in parts]))
    w, h = size
    k = 1  # sketches: many of them, no supersampling
    grey = np.full((len(parts), 3), 215, np.uint8)
    seen_grey = [_visible([(*parts[i], grey[i])], [np.zeros(3)]) for i in range(len(parts))]
    seen_own = [_visible([(*parts[i], colors[i])], [np.zeros(3)]) for i in range(len(parts))]
    files, placed = [], set()
    for n, step in enumerate(steps, start=1):
        moving = [where[p] for p in (step.get("pieces") or [step.get("piece")]) if p in where]
        d = step.get("direction")
        back = -reach * np.asarray(d, float) if d is not None else np.zeros(3)
        # the view never changes, so each piece's triangles facing the eye are found once
        shown = [(seen_grey[i], np.zeros(3)) for i in sorted(placed - set(moving))]
        shown += [(seen_own[i], back) for i in moving]
        # frame: the whole puzzle and the block drawn back, the same scale for every step
        frame = np.concatenate([every, every + back])
        x, y = frame @ right, frame @ up
        lo = np.array([x.min(), y.min()])
        span = np.maximum(np.array([x.max(), y.max()]) - lo, 1e-9)
        scale = min((w * k * 0.9) / span[0], (h * k * 0.82) / span[1])
        img = np.ones((h * k, w * k, 3))
        if shown:
            tris = np.concatenate([t + off for (t, _, _), off in shown])
            cols = np.concatenate([c for (_, c, _), _ in shown])
            owner = np.repeat(np.arange(len(shown)), [len(t) for (t, _, _), _ in shown])
        if shown and len(tris):
            tx, ty = tris @ right, tris @ up
            px = w * k / 2 + (tx - (lo[0] + span[0] / 2)) * scale
            py = h * k * 0.54 - (ty - (lo[1] + span[1] / 2)) * scale
            ibuf = rasterize(px, py, tris @ eye, w * k, h * k)
            hit = ibuf >= 0
            img[hit] = cols[ibuf[hit]]
            part = np.where(hit, owner[np.maximum(ibuf, 0)], -1)
            edge = np.zeros_like(hit)
            edge[:, 1:] |= part[:, 1:] != part[:, :-1]
            edge[1:, :] |= part[1:, :] != part[:-1, :]
            img[edge & hit] *= _OUTLINE
        pil = Image.fromarray(np.round(np.clip(img, 0, 1) * 255).astype(np.uint8))
        draw = ImageDraw.Draw(pil)
        if moving and d is not None:
            centre = np.mean([parts[i][0].mean(axis=0) for i in moving], axis=0)

            def to_px(p, lo=lo, span=span, scale=scale):
                return (w * k / 2 + (p @ right - (lo[0] + span[0] / 2)) * scale,
                        h * k * 0.54 - (p @ up - (lo[1] + span[1] / 2)) * scale)

            a, b = np.array(to_px(centre + back)), np.array(to_px(centre + 0.25 * back))
            _arrow(draw, a, b, width=3 * k)
        _text(draw, w * k / 2, 4 * k, f"step {n}", 14 * k)
        name = f"step-{n:02d}.png"
        pil.reduce(k).save(directory / name, format="PNG", compress_level=1)
        files.append(name)
        placed.update(moving)
    return files


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
