"""layout: print orientation of every piece and its place on build plates.

Packing is trimesh's rectangle packer (trimesh.path.packing); this module only decides how each piece rests on the
plate and turns the packer's boxes into transforms.
"""

from dataclasses import dataclass

import numpy as np
import trimesh
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


def _candidate_downs(mesh, count=24):
    """Outward normals of the largest convex-hull facets (and single hull faces) -> (k, 3), areas (k,)."""
    hull = mesh.convex_hull
    normals = [hull.facets_normal] if len(hull.facets) else []
    areas = [hull.facets_area] if len(hull.facets) else []
    in_facet = np.zeros(len(hull.faces), bool)
    for f in hull.facets:
        in_facet[f] = True
    normals.append(hull.face_normals[~in_facet])
    areas.append(hull.area_faces[~in_facet])
    normals, areas = np.concatenate(normals), np.concatenate(areas)
    order = np.argsort(-areas, kind="stable")[:count]
    return normals[order], areas[order]


def _score(mesh, down, up_dirs):
    """(contact area on the plate, overhanging area, pins pointing down) when `down` faces the plate."""
    h = mesh.vertices @ down
    support = h.max()
    n_dot = mesh.face_normals @ down
    on_plate = (n_dot > FLAT_COS) & np.all(h[mesh.faces] > support - 1e-3 * max(mesh.scale, 1.0), axis=1)
    contact = float(mesh.area_faces[on_plate].sum())
    overhang = float(mesh.area_faces[(n_dot > OVERHANG_COS) & ~on_plate].sum())
    pins_down = int(sum(1 for d in up_dirs if np.dot(d, down) > 0.5))
    return contact, overhang, pins_down


def print_orientation(mesh, pin_directions=()):
    """(4, 4) rotation that puts a large flat face down when the piece has one, else the least overhang; pins pointing
    up are preferred. Deterministic for the same mesh."""
    downs, _ = _candidate_downs(mesh)
    downs = np.concatenate([downs, np.vstack([np.eye(3), -np.eye(3)])])
    scores = [_score(mesh, d, pin_directions) for d in downs]
    best_contact = max(s[0] for s in scores)
    # A face is "large" when it carries a real share of the piece's footprint; else the piece has no flat side.
    flat_enough = best_contact > 0.02 * mesh.area
    keys = []
    for i, (contact, overhang, pins_down) in enumerate(scores):
        if flat_enough:
            key = (pins_down, contact < 0.8 * best_contact, overhang - contact, i)
        else:
            key = (pins_down, overhang, i)
        keys.append(key)
    down = downs[min(range(len(keys)), key=lambda i: keys[i])]
    rot = trimesh.geometry.align_vectors(down, [0.0, 0.0, -1.0])
    # Then turn about z so that the footprint's bounding rectangle is smallest.
    pts = trimesh.transform_points(mesh.convex_hull.vertices, rot)[:, :2]
    t2d, _ = trimesh.bounds.oriented_bounds_2D(pts)
    spin = np.eye(4)
    spin[:2, :2] = t2d[:2, :2]
    if np.linalg.det(spin[:2, :2]) < 0:
        spin[1, :2] *= -1  # a mirror would print the piece's mirror image; flipping one row keeps the box aligned
    return spin @ rot


def _resting(mesh, rot):
    """Translate the rotated piece so that it is centred on the origin in xy and rests on z = 0. -> (4, 4), extents (2,)"""
    pts = trimesh.transform_points(mesh.vertices, rot)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    move = np.eye(4)
    move[:3, 3] = [-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]]
    return move @ rot, hi[:2] - lo[:2]


def footprint_needed(meshes):
    """Smallest plate (w, d) that can hold the largest piece in its print orientation."""
    need = np.zeros(2)
    for mesh in meshes:
        _, ext = _resting(mesh, print_orientation(mesh))
        need = np.maximum(need, np.sort(ext)[::-1])
    return need


def layout(parts, plate, spacing, pin_directions=None):
    """Pack parts onto as few plates as fit. parts: list of (name, Trimesh) in assembled mm; plate (w, d) mm;
    pin_directions: {name: [(3,) unit vectors of its pins]}. -> (list of Placement, list of Plate)."""
    pin_directions = pin_directions or {}
    plate = np.asarray(plate, float)
    oriented, extents, areas = [], [], []
    for name, mesh in parts:
        rot = print_orientation(mesh, pin_directions.get(name, ()))
        place, ext = _resting(mesh, rot)
        oriented.append(place)
        extents.append(ext)
        hull2d = trimesh.transform_points(mesh.convex_hull.vertices, place)[:, :2]
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
        bounds, inserted = packing.rectangles(extents[remaining], size=plate, spacing=spacing / 2.0, rotate=True,
                                              seed=0)
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


def _hull_area(points):
    """Area of the 2D convex hull of (n, 2) points (scipy calls a 2D hull's area its volume)."""
    from scipy.spatial import ConvexHull

    return float(ConvexHull(points).volume)
