"""preview.png: the assembled puzzle and an exploded view side by side, shaded, one colour per piece.

Painted with Pillow in parallel projection: each piece is simplified once, its triangles facing away from the eye are
dropped (pieces are closed), and the rest are filled far to near at twice the size, then halved for smooth edges.
matplotlib's 3D axes painted the same way but took about four times as long, half of it importing pyplot.
"""

import numpy as np

# The eye: 28 degrees above the horizon, 60 degrees clockwise from the x axis (matplotlib's elev=28, azim=-60).
ELEV, AZIM = np.radians(28.0), np.radians(-60.0)
LIGHT = np.array([0.35, -0.5, 0.8]) / np.linalg.norm([0.35, -0.5, 0.8])
SUPERSAMPLE = 2


def _simplified(mesh, faces=1500):
    if len(mesh.faces) <= faces:
        return np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    try:
        import fast_simplification

        v, f = fast_simplification.simplify(mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32),
                                            target_reduction=1.0 - faces / len(mesh.faces))
        if len(f):
            return np.asarray(v, float), np.asarray(f)
    except Exception:  # noqa: BLE001 - a preview falls back to the full mesh rather than failing the build
        pass
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces)


def _part(mesh, rgb):
    """(vertices, faces, colour) simplified; per-triangle colours (m, 3) follow to the nearest original triangle."""
    rgb = np.asarray(rgb)
    v, f = _simplified(mesh, 8000 if rgb.ndim == 2 else 1500)  # a texture needs more triangles to show
    if rgb.ndim == 2 and len(f) != len(mesh.faces):
        from scipy.spatial import cKDTree

        _, idx = cKDTree(mesh.triangles_center).query(v[f].mean(axis=1))
        rgb = rgb[idx]
    return v, f, rgb


def _view_axes():
    """(right, up, toward the eye) unit vectors of the screen, in world coordinates."""
    eye = np.array([np.cos(ELEV) * np.cos(AZIM), np.cos(ELEV) * np.sin(AZIM), np.sin(ELEV)])
    right = np.array([-np.sin(AZIM), np.cos(AZIM), 0.0])
    return right, np.cross(eye, right), eye


def _visible(parts, offsets):
    """Triangles facing the eye of every part, moved by its offset -> (t, 3, 3) corners, (t, 3) colours in 0..1."""
    _, _, eye = _view_axes()
    tris, cols = [], []
    for (v, f, rgb), off in zip(parts, offsets):
        t = v[f] + off
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        front = n @ eye > 0  # closed pieces: the back faces are hidden behind the front ones anyway
        shade = 0.35 + 0.65 * np.clip(n[front] @ LIGHT, 0, 1)
        tris.append(t[front])
        c = np.asarray(rgb, float)
        c = c[front] if c.ndim == 2 else c[None, :]  # (m, 3) per triangle (a texture) or one colour
        cols.append(np.clip(c / 255.0 * shade[:, None], 0, 1))
    return np.concatenate(tris), np.concatenate(cols)


def _paint(draw, tris, cols, box):
    """Fill the triangles far to near, the whole set scaled to fit box (x0, y0, x1, y1) in pixels."""
    if not len(tris):
        return
    right, up, eye = _view_axes()
    x = tris @ right
    y = tris @ up
    # by each triangle's nearest corner: long cut faces inside the assembled puzzle then go under its skin, which
    # sorting by the mean lets them paint streaks over
    depth = (tris @ eye).max(axis=1)
    lo = np.array([x.min(), y.min()])
    span = np.maximum(np.array([x.max(), y.max()]) - lo, 1e-9)
    x0, y0, x1, y1 = box
    scale = min((x1 - x0) / span[0], (y1 - y0) / span[1])
    px = (x0 + x1) / 2 + (x - (lo[0] + span[0] / 2)) * scale
    py = (y0 + y1) / 2 - (y - (lo[1] + span[1] / 2)) * scale
    order = np.argsort(depth, kind="stable")
    xy = np.stack([px, py], axis=2)[order].reshape(len(order), 6).tolist()
    rgb = [tuple(c) for c in np.round(cols[order] * 255).astype(int).tolist()]
    polygon = draw.polygon
    for p, c in zip(xy, rgb):
        polygon(p, fill=c)


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


def render_preview(path, meshes, colors, size=(1600, 800), explode=0.6, title=None):
    """Write a PNG: left the assembled puzzle, right exploded. meshes: list of Trimesh in mm; colors (n, 3) uint8, or
    per mesh (m, 3) per-triangle colours (a texture)."""
    from PIL import Image, ImageDraw

    k = SUPERSAMPLE
    w, h = size[0] * k, size[1] * k
    parts = [_part(m, rgb) for m, rgb in zip(meshes, colors)]
    centers = np.array([m.centroid for m in meshes])
    exploded = (centers - centers.mean(axis=0)) * explode
    img = Image.new("RGB", (w, h), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    top = int(0.09 * h)
    margin = int(0.06 * w / 2)
    for i, (offs, label) in enumerate(((np.zeros_like(centers), "assembled"), (exploded, "exploded"))):
        x0 = i * w // 2
        tris, cols = _visible(parts, offs)
        _paint(draw, tris, cols, (x0 + margin, top + margin, x0 + w // 2 - margin, h - margin))
        _text(draw, x0 + w / 4, int(0.05 * h), label, 19 * k)
    if title:
        _text(draw, w / 2, int(0.012 * h), str(title), 22 * k)
    # zlib's fastest level: a third the time of the default for a picture about a quarter larger
    img.reduce(k).save(path, format="PNG", compress_level=1)
