"""layout: print orientation of every piece and its place on build plates.

Packing is a guillotine packer of the pieces' footprint rectangles (_pack), one plate at a time; trimesh's
roll_transform turns its boxes into transforms.
"""

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import ConvexHull
from trimesh.path import packing

from .errors import SpecError

# Faces within this angle of the plate count as resting on it; faces steeper than 45 degrees down overhang.
FLAT_COS = np.cos(np.radians(3.0))
OVERHANG_COS = np.cos(np.radians(45.0))


@dataclass(frozen=True, eq=False)
class Placement:
    """Where one part goes: plate number (1-based) and the (4, 4) transform from assembled mm to plate mm."""

    name: str
    plate: int
    transform: np.ndarray
    footprint_mm2: float


@dataclass(frozen=True, eq=False)
class Plate:
    index: int
    names: tuple
    fill_ratio: float

    @property
    def file(self):
        return f"plates/plate-{self.index:02d}.3mf"


def _candidate_downs(hull, count=24):
    """Outward normals of the largest convex-hull facets (and single hull faces) -> (k, 3), areas (k,)."""
    facets = hull.facets
    normals = [hull.facets_normal] if len(facets) else []
    areas = [hull.facets_area] if len(facets) else []
    in_facet = np.zeros(len(hull.faces), bool)
    if len(facets):
        in_facet[np.concatenate(facets)] = True
    normals.append(hull.face_normals[~in_facet])
    areas.append(hull.area_faces[~in_facet])
    normals, areas = np.concatenate(normals), np.concatenate(areas)
    order = np.argsort(-areas, kind="stable")[:count]
    return normals[order], areas[order]


def _scores(mesh, downs, up_dirs):
    """For every candidate `down` (k, 3) facing the plate: contact area on the plate (k,), overhanging area (k,),
    pins pointing down (k,); and the piece's whole surface area. All candidates at once, on plain arrays: trimesh's
    cached properties re-hash the mesh on every access."""
    vertices = mesh.vertices.view(np.ndarray)
    faces = mesh.faces.view(np.ndarray)
    cross = mesh.triangles_cross.view(np.ndarray)  # usually cached by the volume checks already
    double = np.sqrt(np.einsum("ij,ij->i", cross, cross))
    area = 0.5 * double
    scale = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    h = vertices @ downs.T
    near = h > h.max(axis=0) - 1e-3 * max(scale, 1.0)
    # cosines against unit normals, without dividing by each face's |cross|
    n_dot = cross @ downs.T
    on_plate = (n_dot > FLAT_COS * double[:, None]) & near[faces[:, 0]] & near[faces[:, 1]] & near[faces[:, 2]]
    contact = area @ on_plate
    overhang = area @ ((n_dot > OVERHANG_COS * double[:, None]) & ~on_plate)
    up_dirs = np.reshape(np.asarray(up_dirs, float), (-1, 3))
    pins_down = (downs @ up_dirs.T > 0.5).sum(axis=1)
    return contact, overhang, pins_down, float(area.sum())


def _orient(mesh, pin_directions=()):
    """print_orientation's rotation, and the piece's convex-hull vertices (all its extreme points)."""
    hull = mesh.convex_hull
    downs, _ = _candidate_downs(hull)
    downs = np.concatenate([downs, np.vstack([np.eye(3), -np.eye(3)])])
    contact, overhang, pins_down, total_area = _scores(mesh, downs, pin_directions)
    best_contact = contact.max()
    index = np.arange(len(downs))
    # A face is "large" when it carries a real share of the piece's footprint; else the piece has no flat side.
    if best_contact > 0.02 * total_area:
        best = np.lexsort((index, overhang - contact, contact < 0.8 * best_contact, pins_down))[0]
    else:
        best = np.lexsort((index, overhang, pins_down))[0]
    rot = trimesh.geometry.align_vectors(downs[best], [0.0, 0.0, -1.0])
    # Then turn about z so that the footprint's bounding rectangle is smallest.
    hull_points = hull.vertices.view(np.ndarray)
    pts = hull_points @ rot[:3, :3].T
    t2d, _ = trimesh.bounds.oriented_bounds_2D(pts[:, :2])
    spin = np.eye(4)
    spin[:2, :2] = t2d[:2, :2]
    if np.linalg.det(spin[:2, :2]) < 0:
        spin[1, :2] *= -1  # a mirror would print the piece's mirror image; flipping one row keeps the box aligned
    return spin @ rot, hull_points


def print_orientation(mesh, pin_directions=()):
    """(4, 4) rotation that puts a large flat face down when the piece has one, else the least overhang; pins pointing
    up are preferred. Deterministic for the same mesh."""
    return _orient(mesh, pin_directions)[0]


def _resting(points, rot):
    """Translate the rotated piece so that it is centred on the origin in xy and rests on z = 0. points: the piece's
    vertices, or just its convex-hull vertices (the same extremes). -> (4, 4), extents (2,)"""
    pts = trimesh.transform_points(points, rot)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    move = np.eye(4)
    move[:3, 3] = [-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]]
    return move @ rot, hi[:2] - lo[:2]


def layout(parts, plate, spacing, pin_directions=None):
    """Pack parts onto as few plates as fit. parts: list of (name, Trimesh) in assembled mm; plate (w, d) mm;
    pin_directions: {name: [(3,) unit vectors of its pins]}. -> (list of Placement, list of Plate)."""
    pin_directions = pin_directions or {}
    plate = np.asarray(plate, float)
    oriented, extents, areas = [], [], []
    for name, mesh in parts:
        rot, hull_points = _orient(mesh, pin_directions.get(name, ()))
        place, ext = _resting(hull_points, rot)
        oriented.append(place)
        extents.append(ext)
        hull2d = trimesh.transform_points(hull_points, place)[:, :2]
        areas.append(_hull_area(hull2d))
    extents = np.array(extents)
    fits = np.all(np.sort(extents, axis=1)[:, ::-1] <= np.sort(plate)[::-1] + 1e-9, axis=1)
    if not fits.all():
        need = np.sort(extents[~fits], axis=1)[:, ::-1].max(axis=0)
        raise SpecError(f"output.plate: piece {parts[int(np.argmin(fits))][0]} does not fit on the plate "
                        f"(got {plate.tolist()}, expected at least [{need[0]:.1f}, {need[1]:.1f}] mm)")
    placements, plates = [None] * len(parts), []
    remaining = list(range(len(parts)))
    while remaining:
        bounds, inserted = _pack(extents[remaining], plate, spacing)
        if not np.any(inserted):
            inserted = np.zeros(len(remaining), bool)
            inserted[0] = True
            bounds = np.array([[[0, 0], extents[remaining[0]]]]) + spacing / 2.0
        chosen = [remaining[i] for i in np.flatnonzero(inserted)]
        moves = packing.roll_transform(bounds, extents[chosen])
        index = len(plates) + 1
        for i, m2 in zip(chosen, moves):
            m3 = np.eye(4)
            m3[:2, :2] = m2[:2, :2]
            m3[:2, 3] = m2[:2, 2]
            placements[i] = Placement(parts[i][0], index, m3 @ oriented[i], areas[i])
        fill = sum(areas[i] for i in chosen) / float(np.prod(plate))
        plates.append(Plate(index, tuple(parts[i][0] for i in chosen), round(fill, 4)))
        remaining = [r for j, r in enumerate(remaining) if not inserted[j]]
    return placements, plates


def _pack(extents, plate, spacing):
    """Parts onto one plate: (n, 2) footprints -> (bounds (m, 2, 2) of the inserted ones in plate mm, inserted (n,)
    bool). Two insertion orders (longest side first, largest area first); the second only runs when the first leaves
    parts over, and wins only by putting more area on this plate."""
    extents = np.asarray(extents, float).reshape(-1, 2)
    grown = extents + spacing
    best = None
    for key in (grown.max(axis=1), grown.prod(axis=1)):
        order = np.lexsort((np.arange(len(extents)), -grown.min(axis=1), -key))
        bounds, inserted = _guillotine(extents, order, plate, spacing)
        if inserted.all():
            return bounds, inserted
        area = grown[inserted].prod(axis=1).sum()
        if best is None or area > best[0] + 1e-9:
            best = area, bounds, inserted
    return best[1], best[2]


def _guillotine(extents, order, plate, spacing):
    """One plate of guillotine packing, parts taken in `order` (n,) -> (bounds, inserted) as _pack. Each part goes
    into the free rectangle it fills most tightly (either way round), which is then cut in two along the leftover's
    shorter side. Parts are `spacing` apart and spacing / 2 from the plate's edge.

    Every part is one vectorised test against all free rectangles: trimesh's packer walks a Python tree per part,
    and was rerun 50 times with shuffled orders whenever the parts overflowed the plate (555 s for 1024 pieces)."""
    grown = extents + spacing
    width, depth = (float(s) for s in plate)
    slack = 1e-9 * max(width, depth)
    # free rectangles as rows of x, y, w, h; at most one more per placed part
    free = np.zeros((2 * len(extents) + 1, 4))
    free[0] = 0.0, 0.0, width, depth
    count = 1
    bounds = np.zeros((len(extents), 2, 2))
    inserted = np.zeros(len(extents), bool)
    for i in order:
        a, b = grown[i]
        f = free[:count]
        leftover = f[:, 2] * f[:, 3] - a * b
        fit_ab = (f[:, 2] >= a - slack) & (f[:, 3] >= b - slack)
        fit_ba = (f[:, 2] >= b - slack) & (f[:, 3] >= a - slack)
        # the tighter of the two ways round by the shorter leftover side, then the smallest leftover area
        short_ab = np.minimum(f[:, 2] - a, f[:, 3] - b)
        short_ba = np.minimum(f[:, 2] - b, f[:, 3] - a)
        score_ab = np.where(fit_ab, leftover + 1e-6 * short_ab, np.inf)
        score_ba = np.where(fit_ba, leftover + 1e-6 * short_ba, np.inf)
        j_ab, j_ba = int(np.argmin(score_ab)), int(np.argmin(score_ba))
        if not np.isfinite(min(score_ab[j_ab], score_ba[j_ba])):
            continue
        j, (pw, ph) = (j_ab, (a, b)) if score_ab[j_ab] <= score_ba[j_ba] else (j_ba, (b, a))
        x, y, w, h = free[j]
        inserted[i] = True
        ext = extents[i] if pw == a else extents[i][::-1]
        bounds[i, 0] = x + spacing / 2.0, y + spacing / 2.0
        bounds[i, 1] = bounds[i, 0] + ext
        # The longer leftover keeps the full side of the free rectangle.
        if w - pw < h - ph:
            right, top = (x + pw, y, w - pw, ph), (x, y + ph, w, h - ph)
        else:
            right, top = (x + pw, y, w - pw, h), (x, y + ph, pw, h - ph)
        free[j] = free[count - 1]
        count -= 1
        for r in (right, top):
            if r[2] > slack and r[3] > slack:
                free[count] = r
                count += 1
    return bounds[inserted], inserted


def _hull_area(points):
    """Area of the 2D convex hull of (n, 2) points (scipy calls a 2D hull's area its volume)."""
    return float(ConvexHull(points).volume)
