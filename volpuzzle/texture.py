"""`texture`: colour a model's outer surface from an image through its (u, v) parameters (the paper's Earth).

The textured face (w_max by default) is sampled densely in the model's own parameters, M(face) in mm: the warp R
keeps D's boundary, so the face of every piece lies on M(face) whatever R does inside. A triangle of a finished
piece takes the image colour when its centre lies on that surface (within the tessellation tolerance and the
sampling step) and it faces the same way; every other triangle (cut faces, pins, holes) keeps the piece colour.
Image rows follow the face's first free parameter (top row at its minimum), columns the second (left column at its
minimum); `transpose` swaps them. For the sphere shell (u from the north pole, v the azimuth eastward) an
equirectangular map then lands the right way up.
"""

from dataclasses import dataclass

import numpy as np

from .errors import ModelError
from .progress import warn

_SAMPLES = 720  # per free parameter of the face: about 0.45 mm on a 100 mm sphere, 3 pixels of a 2048 map
_FACING = 0.6  # cosine: a triangle within about 53 degrees of the surface normal belongs to the surface


@dataclass(frozen=True, eq=False)
class FaceSampling:
    """The textured face sampled on a grid: xyz (n, 3) mm, normals (n, 3) pointing out of the model, st (n, 2) in
    [0, 1] (image row, column fractions), step: the largest distance between grid neighbours (mm)."""

    xyz: np.ndarray
    normals: np.ndarray
    st: np.ndarray
    step: float


def load_image(path):
    """The image as (h, w, 3) uint8; ModelError naming the file when it cannot be read."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except (OSError, UnidentifiedImageError, ValueError) as e:
        raise ModelError(f"texture.image: {path}: cannot be read as an image ({e}); expected a JPEG or PNG") from None


def sample_face(vol, face, transpose=False, n=_SAMPLES):
    """Sample the face ('w_max' etc.) of vol (mm) -> FaceSampling."""
    axis, side = "uvw".index(face[0]), face[2:]
    b, c = (k for k in range(3) if k != axis)
    dom = np.array(vol.domain)
    s = np.linspace(0.0, 1.0, n)
    ss, tt = np.meshgrid(s, s, indexing="ij")
    uvw = np.empty((n * n, 3))
    uvw[:, axis] = dom[axis, 1] if side == "max" else dom[axis, 0]
    uvw[:, b] = dom[b, 0] + ss.ravel() * (dom[b, 1] - dom[b, 0])
    uvw[:, c] = dom[c, 0] + tt.ravel() * (dom[c, 1] - dom[c, 0])
    # the normal a hair inside the face: at a pole the face's own partials vanish
    inside = uvw.copy()
    inside[:, b] = np.clip(inside[:, b], dom[b, 0] + 1e-5 * (dom[b, 1] - dom[b, 0]),
                           dom[b, 1] - 1e-5 * (dom[b, 1] - dom[b, 0]))
    xyz = vol.evaluate(uvw)
    _, d = vol.evaluate_with_derivatives(inside)
    nrm = np.cross(d[:, :, b], d[:, :, c])
    # out of the model: along +d/d(axis) at the max face, against it at the min face
    sign = np.sign(np.einsum("ni,ni->n", nrm, d[:, :, axis])) * (1 if side == "max" else -1)
    nrm *= sign[:, None] / np.maximum(np.linalg.norm(nrm, axis=1), 1e-300)[:, None]
    grid = xyz.reshape(n, n, 3)
    step = max(float(np.max(np.linalg.norm(np.diff(grid, axis=0), axis=2))),
               float(np.max(np.linalg.norm(np.diff(grid, axis=1), axis=2))))
    st = np.stack([ss.ravel(), tt.ravel()], 1)
    if transpose:
        st = st[:, ::-1]
    return FaceSampling(xyz, nrm, st, step)


def image_colors(image, st):
    """Bilinear image colours at (row, column) fractions st (n, 2) -> (n, 3) uint8."""
    h, w = image.shape[:2]
    y = np.clip(st[:, 0], 0, 1) * (h - 1)
    x = np.clip(st[:, 1], 0, 1) * (w - 1)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    fy, fx = (y - y0)[:, None], (x - x0)[:, None]
    img = image.astype(float)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return np.clip(np.round(top * (1 - fy) + bottom * fy), 0, 255).astype(np.uint8)


def triangle_colors(sampling, tree, image, mesh, tolerance):
    """Colours at the corners of each triangle of one piece -> (m, 3 corners, 3) int16: the image colour on the
    textured surface, -1 elsewhere (the piece's own material). Corner colours let a reader blend across a triangle,
    so the picture is finer than the tessellation."""
    centres = np.asarray(mesh.triangles_center)
    normals = np.asarray(mesh.face_normals)
    dist, idx = tree.query(centres, k=1)
    on = (dist <= 2 * tolerance + sampling.step) & (np.einsum("ni,ni->n", normals, sampling.normals[idx]) > _FACING)
    out = np.full((len(centres), 3, 3), -1, dtype=np.int16)
    if np.any(on):
        corners = np.asarray(mesh.faces)[on]
        used, inverse = np.unique(corners, return_inverse=True)
        _, vidx = tree.query(np.asarray(mesh.vertices)[used], k=1)
        out[on] = image_colors(image, sampling.st[vidx])[inverse.reshape(-1)].reshape(-1, 3, 3)
    return out


def texture_pieces(texture, vol, pieces, tolerance):
    """{piece id: (m, 3) int16 colours, -1 where the piece colour stays} for the texture spec, and a report dict."""
    from scipy.spatial import cKDTree

    image = load_image(texture.image)
    sampling = sample_face(vol, texture.face, texture.transpose)
    tree = cKDTree(sampling.xyz)
    out = {p.id: triangle_colors(sampling, tree, image, p.mesh, tolerance) for p in pieces}
    textured = sum(int(np.count_nonzero(c[:, 0, 0] >= 0)) for c in out.values())
    total = sum(len(c) for c in out.values())
    report = {"image": str(texture.image), "face": texture.face, "transpose": texture.transpose,
              "image_size": [int(image.shape[1]), int(image.shape[0])],
              "textured_triangles": textured, "triangles": total, "sampling_step_mm": sampling.step,
              "3mf": "colours at triangle corners in a 3MF colour group (materials extension)"}
    return out, report


def blend(piece_rgb, colors):
    """(m, 3, 3) corner colours of a piece: its texture colours, and its own colour where there is none."""
    c = np.asarray(colors)
    return np.where(c >= 0, c, np.asarray(piece_rgb)).astype(np.uint8)


def face_colors(piece_rgb, colors):
    """(m, 3) one colour per triangle (the mean of its corners), for pictures."""
    return np.round(blend(piece_rgb, colors).mean(axis=1)).astype(np.uint8)


def build_texture(spec, volume, pieces, tolerance):
    """Per-triangle texture colours of every piece, or (None, None) without a texture."""

    if spec.texture is None:
        return None, None
    colors, report = texture_pieces(spec.texture, volume, pieces, tolerance)
    if spec.output.format == "stl":
        report["note"] = ("STL cannot hold colour: the pieces/*.stl files are plain; the texture is in puzzle.3mf, "
                          "the plates and preview.png (output.format: 3mf gives coloured piece files too)")
        warn(f"texture: {report['note']}")
    return colors, report
