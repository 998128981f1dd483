"""layout: print orientation of every piece, a stable base for it, and its place on build plates.

Orientation: every candidate `down` (the largest convex-hull facets, the axes, and the directions that turn a pin up
or a hole's opening up) is scored at once on plain arrays: no pin reaching down to the bed first (the piece would
stand on it, and a base cut would shave it), then a stable base (a flat face, or a flat cut a few tenths of a mm
deep, of at least MIN_BED_MM2), then no pin pointing into the bed and no hole opening onto it (support inside a
blind hole cannot be removed), then the least overhang less the base, with a bonus for every pin
within PIN_UP_DEG of vertical. A piece without a flat face that large gets a base cut (base_cut): the plane
BASE_CUT_MM[i] above its lowest point that first gives it BASE_TARGET of bed contact.

Packing is a guillotine packer of the pieces' footprint rectangles (_pack), one plate at a time, inside the plate
less `margin` on every side; the packed group is then centred on the plate, and trimesh's roll_transform turns its
boxes into transforms.
"""

from dataclasses import dataclass
from functools import partial

import numpy as np
import trimesh
from scipy.spatial import ConvexHull
from trimesh.path import packing

from .errors import GeometryError, SpecError
from .geometry import hull_points_of

# Faces within this angle of the plate count as resting on it; faces steeper than 45 degrees down overhang.
FLAT_COS = np.cos(np.radians(3.0))
OVERHANG_COS = np.cos(np.radians(45.0))
MIN_BED_MM2 = 10.0  # less than this on the bed and the first layer has nothing to hold (the slicer refuses it)
BASE_TARGET = (25.0, 0.08)  # a base cut aims at max(mm^2, share of the footprint) of bed contact
BASE_CUT_MM = (0.2, 0.3, 0.4, 0.5, 0.6)  # base cut depths tried, shallowest first (a few layers at most)
# only where those leave less than MIN_BED_MM2 (a piece resting on a round bump): a deeper flat beats a print that
# the slicer refuses or that comes loose on the first layer
DEEP_CUT_MM = (0.8, 1.0, 1.3, 1.6, 2.0)
FIRST_SLICE_MM = 0.1  # a slicer cuts its first 0.2 mm layer here: what it finds is the piece's contact with the bed
TALL_RATIO = 4.0  # height over the side of the base (the square root of its area) a piece stands up to
PIN_UP_DEG = 30.0  # a pin within this angle of vertical prints round and strong, with no support
PIN_UP_WEIGHT = 0.3  # a pin up is worth this share of the piece's surface area in overhang (lying, it prints oval)


@dataclass(frozen=True, eq=False)
class Placement:
    """Where one part goes: plate number (1-based) and the (4, 4) transform from assembled mm to plate mm."""

    name: str
    plate: int
    transform: np.ndarray
    footprint_mm2: float


@dataclass(frozen=True, eq=False)
class Pose:
    """How one piece is printed. rotation (4, 4) from assembled mm to print orientation (resting on nothing yet);
    down (3,) the assembled direction that faces the bed; base_cut_mm: depth of the flat cut made for its base (0
    when it rests on a flat face); bed_contact_mm2 of the piece as printed (after the cut); pins, pins_up (within
    PIN_UP_DEG of vertical), pins_down (into the bed) and holes_down (opening onto the bed)."""

    rotation: np.ndarray
    down: np.ndarray
    base_cut_mm: float
    bed_contact_mm2: float
    pins: int
    pins_up: int
    pins_down: int
    holes_down: int

    def to_report(self):
        return {"down": [round(float(x), 6) for x in self.down], "base_cut_mm": round(float(self.base_cut_mm), 3),
                "bed_contact_mm2": round(float(self.bed_contact_mm2), 2), "pins": int(self.pins),
                "pins_up": int(self.pins_up), "pins_down": int(self.pins_down), "holes_down": int(self.holes_down)}


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


def _scores(mesh, downs, up_dirs, open_dirs=(), pin_tips=()):
    """For every candidate `down` (k, 3) facing the plate: contact area on the plate (k,), the bed area a base cut
    of BASE_CUT_MM[-1] would give (k,, from the down-facing triangles within that depth of the lowest point),
    overhanging area (k,), pins pointing down (k,), pins within PIN_UP_DEG of up (k,), holes opening down (k,), pins
    reaching within BASE_CUT_MM[-1] of the lowest point (k,); and the piece's whole surface area. pin_tips: per pin
    of up_dirs, (centre of its tip (3,) mm, radius mm). All candidates at once, on plain arrays: trimesh's cached
    properties re-hash the mesh on every access."""
    vertices = mesh.vertices.view(np.ndarray)
    faces = mesh.faces.view(np.ndarray)
    cross = mesh.triangles_cross.view(np.ndarray)  # usually cached by the volume checks already
    double = np.sqrt(np.einsum("ij,ij->i", cross, cross))
    area = 0.5 * double
    scale = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    h = vertices @ downs.T
    low = h.max(axis=0)
    near = h > low - 1e-3 * max(scale, 1.0)
    # cosines against unit normals, without dividing by each face's |cross|
    n_dot = cross @ downs.T
    on_plate = (n_dot > FLAT_COS * double[:, None]) & near[faces[:, 0]] & near[faces[:, 1]] & near[faces[:, 2]]
    contact = area @ on_plate
    in_cut = h > low - BASE_CUT_MM[-1]
    cut = in_cut[faces[:, 0]] & in_cut[faces[:, 1]] & in_cut[faces[:, 2]] & (n_dot > 0)
    base = 0.5 * np.where(cut, n_dot, 0.0).sum(axis=0)  # the cut's flat is the shadow of what it removes
    overhang = area @ ((n_dot > OVERHANG_COS * double[:, None]) & ~on_plate)
    up_dirs = np.reshape(np.asarray(up_dirs, float), (-1, 3))
    open_dirs = np.reshape(np.asarray(open_dirs, float), (-1, 3))
    pin_dot = downs @ up_dirs.T
    pins_down = (pin_dot > 0.5).sum(axis=1)
    pins_up = (pin_dot < -np.cos(np.radians(PIN_UP_DEG))).sum(axis=1)
    holes_down = (downs @ open_dirs.T > 0.5).sum(axis=1)
    on_bed = np.zeros(len(downs), dtype=np.int64)
    if len(pin_tips):
        tips = np.array([t for t, _ in pin_tips], float)
        radii = np.array([r for _, r in pin_tips], float)
        # the lowest point of each pin's tip disc, along each candidate's down
        reach = tips @ downs.T + radii[:, None] * np.sqrt(np.clip(1.0 - pin_dot.T ** 2, 0.0, 1.0))
        on_bed = (reach > low[None, :] - BASE_CUT_MM[-1] - 1e-6).sum(axis=0)
    return (contact, np.maximum(base, contact), overhang, pins_down, pins_up, holes_down, float(area.sum()),
            low - h.min(axis=0), on_bed)


def _choose(mesh, pin_directions=(), hole_openings=(), pin_tips=()):
    """The best candidate -> (down (3,), flat contact mm^2, estimated base mm^2, pins_down, pins_up, holes_down) and
    the piece's convex hull."""
    hull = mesh.convex_hull
    downs, _ = _candidate_downs(hull)
    extra = [np.eye(3), -np.eye(3)]
    # a pin straight up, or a hole opening straight up, is a candidate of its own
    for d in list(pin_directions) + list(hole_openings):
        d = np.asarray(d, float)
        extra.append(-d[None] / max(np.linalg.norm(d), 1e-12))
    downs = np.concatenate([downs] + extra)
    contact, base, overhang, pins_down, pins_up, holes_down, total, height, on_bed = _scores(
        mesh, downs, pin_directions, hole_openings, pin_tips)
    index = np.arange(len(downs))
    # a tall piece on a small base topples or wobbles: the base's side should be at least a quarter of the height
    unstable = base < np.maximum(2 * MIN_BED_MM2, (height / TALL_RATIO) ** 2)
    cost = (overhang - base) / max(total, 1e-12) - PIN_UP_WEIGHT * pins_up
    # a flat face within a few per cent of the best is as good as it: ties go to the candidate listed first
    cost = np.round(cost / 0.02)
    # a pin reaching the bed is worse than a wobbly base: the piece would stand on it, and a base cut would shave it
    best = np.lexsort((index, cost, pins_down + holes_down, unstable, on_bed))[0]
    return (downs[best], contact[best], base[best], int(pins_down[best]), int(pins_up[best]),
            int(holes_down[best])), hull


def _orient(mesh, pin_directions=(), hole_openings=(), down=None, hull_points=None):
    """print_orientation's rotation, and the piece's convex-hull vertices (all its extreme points). down: the
    assembled direction to put on the bed, when already chosen; hull_points: those vertices, when known."""
    if down is None:
        (down, *_), hull = _choose(mesh, pin_directions, hole_openings)
        hull_points = hull.vertices.view(np.ndarray)
    elif hull_points is None:
        hull_points = hull_points_of(mesh)
    rot = trimesh.geometry.align_vectors(np.asarray(down, float), [0.0, 0.0, -1.0])
    # Then turn about z so that the footprint's bounding rectangle is smallest.
    pts = hull_points @ rot[:3, :3].T
    t2d, _ = trimesh.bounds.oriented_bounds_2D(pts[:, :2])
    spin = np.eye(4)
    spin[:2, :2] = t2d[:2, :2]
    if np.linalg.det(spin[:2, :2]) < 0:
        spin[1, :2] *= -1  # a mirror would print the piece's mirror image; flipping one row keeps the box aligned
    return spin @ rot, hull_points


def print_orientation(mesh, pin_directions=(), hole_openings=()):
    """(4, 4) rotation that gives the piece a stable base (a large flat face down when it has one), no pin pointing
    into the bed nor hole opening onto it, the least overhang and pins up. Deterministic for the same mesh."""
    return _orient(mesh, pin_directions, hole_openings)[0]


def bed_contact(vertices, faces, transform=None):
    """mm^2 of the mesh on the bed after `transform` (4, 4): its section FIRST_SLICE_MM above its lowest point, where
    the slicer cuts the first layer (geometry.section_area: the engine's slice needed the piece's solid, ~2 ms a
    piece to build, where the section itself takes a tenth of that). GeometryError, as the engine gave, for a mesh
    without triangles or with non-finite coordinates once placed (a broken file or transform). The mesh must be
    closed and outward-wound (check.piece_bed_contact refuses one that is not); a mirroring transform turns its
    triangles inside out, which the area's sign undoes."""
    from .geometry import section_area

    v = np.asarray(vertices, float)
    sign = 1.0
    if transform is not None:
        m = np.asarray(transform, float)
        v = v @ m[:3, :3].T + m[:3, 3]
        sign = -1.0 if np.linalg.det(m[:3, :3]) < 0 else 1.0
    if not len(faces):
        raise GeometryError("piece on the bed: the mesh encloses no volume (empty solid from 0 triangles)")
    if not np.all(np.isfinite(v)):
        raise GeometryError("piece on the bed: the mesh has non-finite vertex coordinates")
    return sign * section_area(v, faces, float(v[:, 2].min()) + FIRST_SLICE_MM)


def plan_pose(mesh, pin_directions=(), hole_openings=(), down=None, pin_tips=()):
    """The piece's Pose: orientation and how deep a base cut it needs (base_cut applies it). down (3,): the assembled
    direction to put on the bed, when the caller has chosen it (a dowel on its side); pin_tips: per pin direction,
    (centre of its tip (3,) mm, radius mm) (joint_directions)."""
    from .geometry import solid_of

    hull_points = None
    if down is None:
        (down, contact, _, pins_down, pins_up, holes_down), hull = _choose(mesh, pin_directions, hole_openings,
                                                                           pin_tips)
        hull_points = hull.vertices.view(np.ndarray)
    else:
        down = np.asarray(down, float) / max(float(np.linalg.norm(down)), 1e-300)
        pins_down = pins_up = holes_down = 0
    rot, hull_points = _orient(mesh, down=down, hull_points=hull_points)
    footprint = _hull_area(trimesh.transform_points(hull_points, rot)[:, :2])
    target = max(BASE_TARGET[0], BASE_TARGET[1] * footprint)
    solid = solid_of(mesh, "piece").transform(rot[:3, :])  # the label stage engraves the same solid
    lowest = float(solid.bounding_box()[2])
    depth, area = 0.0, float(solid.slice(lowest + FIRST_SLICE_MM).area())
    if area < target:
        for d in BASE_CUT_MM + DEEP_CUT_MM:
            if d in DEEP_CUT_MM and area >= MIN_BED_MM2:
                break  # deeper than a few layers only to reach the least a first layer holds on to
            a = float(solid.slice(lowest + d + FIRST_SLICE_MM).area())  # a cut's flat and the first layer above it
            if a > area:
                depth, area = d, a
            if a >= target:
                break
    return Pose(rot, np.asarray(down, float), depth, area, len(pin_directions), pins_up, pins_down, holes_down)


def dowel_pose(mesh, axis):
    """A loose dowel laid flat, its axis (3,) horizontal, as makers print them (the layers run along the dowel, so it
    does not snap at a layer line, and it prints round across its whole length) -> Pose, with the shallow base cut a
    round side needs to hold on the bed. The side put down is the perpendicular to the axis nearest to the assembled
    -z (or -y), so the choice is the same for the same dowel."""
    axis = np.asarray(axis, float) / max(float(np.linalg.norm(axis)), 1e-300)
    for ref in ((0.0, 0.0, -1.0), (0.0, -1.0, 0.0)):
        down = np.asarray(ref) - float(np.dot(ref, axis)) * axis
        if np.linalg.norm(down) > 0.1:
            break
    return plan_pose(mesh, down=down)


def lay_dowels_flat(dowels, joints, what="dowel"):
    """Loose dowels [(name, Trimesh in assembled mm)], one per joint of `joints` in the same order, each with the
    flat its dowel_pose asks for cut along its side -> ([(name, Trimesh)], {name: Pose})."""
    out, poses = [], {}
    for (name, mesh), j in zip(dowels, joints, strict=True):
        pose = dowel_pose(mesh, j.direction)
        cut, _ = base_cut(mesh, pose, f"{what} {name}")
        out.append((name, cut))
        poses[name] = pose
    return out, poses


def base_cut(mesh, pose, what="piece"):
    """The piece (Trimesh, assembled mm) with the flat its pose asks for cut off its bed side -> (Trimesh, mm^3
    removed). Unchanged when the pose needs no cut."""
    if pose.base_cut_mm <= 0:
        return mesh, 0.0
    from .errors import GeometryError
    from .geometry import from_trimesh, kept_bodies, to_trimesh, trim

    solid = from_trimesh(mesh, what)
    down = np.asarray(pose.down, float)
    lowest = float((np.asarray(mesh.vertices) @ down).max())
    kept = trim(solid, -down, pose.base_cut_mm - lowest, f"{what} (base cut)")
    # a speck the flat parts from a sharp edge near the bed goes; a piece cut in two is refused. The engine's solid
    # (status checked by trim) is closed and outward by its guarantee, so its body count is all there is to ask:
    # trimesh's closed test of the same mesh cost ~8 ms a piece
    one = kept_bodies(kept, 1, float(solid.volume()), 0.0)
    if one is None:
        bodies = len(kept.decompose())
        raise GeometryError(f"{what} (base cut): " + (f"the mesh has {bodies} separate bodies (expected one solid)"
                                                      if bodies else "the mesh has no triangles"))
    return to_trimesh(one), float(solid.volume()) - float(one.volume())


def joint_directions(joints):
    """{piece id: [(3,) pin directions]}, {piece id: [(3,) directions its holes open towards]} and {piece id:
    [(centre of each pin's tip (3,) mm, radius mm)]}, the last in the order of the first: a pin leaves its piece along
    the joint's direction, the hole it enters opens back against it; a dowel's two holes open towards each other."""
    from .grid import piece_id

    pins, openings, tips = {}, {}, {}
    for j in joints or ():
        d = np.asarray(j.direction, float)
        if j.style == "pin":
            pins.setdefault(piece_id(j.pin_cell), []).append(d)
            tips.setdefault(piece_id(j.pin_cell), []).append((np.asarray(j.center, float) + float(j.length) * d,
                                                               float(j.radius)))
        elif j.style == "dowel":
            openings.setdefault(piece_id(j.pin_cell), []).append(d)
        if j.style in ("pin", "dowel"):
            openings.setdefault(piece_id(j.hole_cell), []).append(-d)
    return pins, openings, tips


def _resting(points, rot):
    """Translate the rotated piece so that it is centred on the origin in xy and rests on z = 0. points: the piece's
    vertices, or just its convex-hull vertices (the same extremes). -> (4, 4), extents (2,)"""
    pts = trimesh.transform_points(points, rot)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    move = np.eye(4)
    move[:3, 3] = [-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]]
    return move @ rot, hi[:2] - lo[:2]


def layout(parts, plate, spacing, pin_directions=None, margin=0.0, poses=None, hole_openings=None):
    """Pack parts onto as few plates as fit, `margin` mm clear of the plate's edges and the packed group centred on
    the plate. parts: list of (name, Trimesh) in assembled mm; plate (w, d) mm; pin_directions, hole_openings:
    {name: [(3,) unit vectors of its pins, of its holes' openings]}; poses: {name: Pose} already planned (their
    rotation is kept). -> (list of Placement, list of Plate)."""
    pin_directions = pin_directions or {}
    hole_openings = hole_openings or {}
    poses = poses or {}
    plate = np.asarray(plate, float)
    inner = plate - 2.0 * float(margin)
    oriented, extents, areas = [], [], []
    for name, mesh in parts:
        pose = poses.get(name)
        down = None if pose is None else pose.down
        rot, hull_points = _orient(mesh, pin_directions.get(name, ()), hole_openings.get(name, ()), down=down)
        place, ext = _resting(hull_points, rot)
        oriented.append(place)
        extents.append(ext)
        hull2d = trimesh.transform_points(hull_points, place)[:, :2]
        areas.append(_hull_area(hull2d))
    extents = np.array(extents)
    fits = np.all(np.sort(extents, axis=1)[:, ::-1] <= np.sort(inner)[::-1] + 1e-9, axis=1)
    if not fits.all():
        need = np.sort(extents[~fits], axis=1)[:, ::-1].max(axis=0) + 2.0 * float(margin)
        raise SpecError(f"output.plate: piece {parts[int(np.argmin(fits))][0]} does not fit on the plate "
                        f"with output.margin {float(margin):g} mm (got {plate.tolist()}, expected at least "
                        f"[{need[0]:.1f}, {need[1]:.1f}] mm)")
    placements, plates = [None] * len(parts), []
    remaining = list(range(len(parts)))
    while remaining:
        bounds, inserted = _pack(extents[remaining], inner, spacing)
        if not np.any(inserted):
            inserted = np.zeros(len(remaining), bool)
            inserted[0] = True
            bounds = np.array([[[0, 0], extents[remaining[0]]]]) + spacing / 2.0
        chosen = [remaining[i] for i in np.flatnonzero(inserted)]
        moves = packing.roll_transform(bounds, extents[chosen])
        # the boxes' real extents on the plate, then the shift that centres the group on the plate
        placed = [trimesh.transform_points(np.array([[0, 0, 0], [*extents[i], 0]], float) - [*extents[i] / 2, 0],
                                           _move2(m2)) for i, m2 in zip(chosen, moves, strict=True)]
        lo = np.min([p.min(axis=0)[:2] for p in placed], axis=0)
        hi = np.max([p.max(axis=0)[:2] for p in placed], axis=0)
        shift = (plate - (hi - lo)) / 2.0 - lo
        index = len(plates) + 1
        for i, m2 in zip(chosen, moves, strict=True):
            m3 = _move2(m2)
            m3[:2, 3] += shift
            placements[i] = Placement(parts[i][0], index, m3 @ oriented[i], areas[i])
        fill = sum(areas[i] for i in chosen) / float(np.prod(plate))
        plates.append(Plate(index, tuple(parts[i][0] for i in chosen), round(fill, 4)))
        remaining = [r for j, r in enumerate(remaining) if not inserted[j]]
    return placements, plates


def _move2(m2):
    """The packer's (3, 3) planar transform as a (4, 4) one."""
    m3 = np.eye(4)
    m3[:2, :2] = m2[:2, :2]
    m3[:2, 3] = m2[:2, 2]
    return m3


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
    frontier = _frontier(free, count)
    for i in order:
        a, b = grown[i]
        # a part fits a free rectangle either way round when that one's shorter and longer sides are at least its own
        short, long = min(a, b) - slack, max(a, b) - slack
        if not any(r1 >= short and r2 >= long for r1, r2 in frontier):
            continue  # most parts, once a plate is nearly full: at 1024 pieces ~23k of them, each a dozen numpy calls
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
        frontier = _frontier(free, count)
    return bounds[inserted], inserted


def _frontier(free, count):
    """The (shorter, longer) sides of the first `count` free rectangles (rows x, y, w, h) that no other one exceeds in
    both -> list of pairs: a part fits some free rectangle exactly when it fits one of these."""
    if not count:
        return []
    w, h = free[:count, 2], free[:count, 3]
    r1, r2 = np.minimum(w, h), np.maximum(w, h)
    order = np.lexsort((-r2, -r1))
    r1, r2 = r1[order], r2[order]
    # by the shorter side, longest first: a rectangle counts when its longer side beats every one before it
    keep = r2 > np.r_[-np.inf, np.maximum.accumulate(r2)[:-1]]
    return list(zip(r1[keep].tolist(), r2[keep].tolist(), strict=True))


def _hull_area(points):
    """Area of the 2D convex hull of (n, 2) points (scipy calls a 2D hull's area its volume)."""
    return float(ConvexHull(points).volume)


def check_plate(spec, tiling, fmap):
    """Refuse a plate smaller than the largest piece before any mesh is built, naming the size needed."""
    plate = np.sort(np.asarray(spec.output.plate, float))[::-1]
    t = np.linspace(0, 1, 5)
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    cells = list(tiling.cells.values())
    pts = fmap.evaluate(np.concatenate([c.box[0] + grid * (c.box[1] - c.box[0]) for c in cells]))
    pts = pts.reshape(len(cells), len(grid), 3)

    def footprint(p, exact):
        # a box along the principal axes that fits proves the piece fits; only a misfit needs trimesh's smallest box
        # (about 10 ms a piece)
        if exact:
            ext = trimesh.bounds.oriented_bounds(p)[1]
        else:
            q = p - p.mean(axis=0)
            ext = np.ptp(q @ np.linalg.svd(q, full_matrices=False)[2].T, axis=0)
        return np.sort(ext)[::-1][:2] + 2 * spec.output.spacing + 2 * spec.output.margin

    if all(np.all(footprint(p, False) <= plate + 1e-9) for p in pts):
        return
    need = np.max([footprint(p, True) for p in pts], axis=0)
    if np.any(need > plate + 1e-9):
        raise SpecError(f"output.plate: the largest piece needs about {need[0]:.0f} x {need[1]:.0f} mm with "
                        f"output.spacing and output.margin (got {list(spec.output.plate)}, expected at least "
                        f"[{np.ceil(need[0]):.0f}, {np.ceil(need[1]):.0f}])", source=spec.source)


def plan_poses(pieces, joints, workers=None):
    """{piece id: layout.Pose}: how each piece is printed, planned before labels and base cuts. workers: a
    volpuzzle.workers.Workers that plans some of them (the same poses)."""
    from .workers import MeshRef, map_pieces

    pins, openings, tips = joint_directions(joints)
    items = [(MeshRef(p.mesh), pins.get(p.id, ()), openings.get(p.id, ()), tips.get(p.id, ())) for p in pieces]
    poses = map_pieces(workers, _pose_one, items, what="layout")
    return {p.id: pose for p, pose in zip(pieces, poses, strict=True)}


def _pose_one(_shared, item):
    """plan_pose of one item (MeshRef, pin directions, hole openings, pin tips), wherever it runs."""
    ref, pins, openings, tips = item
    return plan_pose(ref.mesh, pins, openings, pin_tips=tips)


def base_cuts(pieces, poses, workers=None):
    """Each piece with the flat cut its pose asks for -> (pieces, mm^3 removed in all). workers: a
    volpuzzle.workers.Workers that cuts some of them (the same cuts)."""
    import dataclasses

    from .workers import MeshRef, map_pieces

    cut = [p for p in pieces if poses.get(p.id) is not None and poses[p.id].base_cut_mm > 0]
    items = [(MeshRef(p.mesh), poses[p.id], p.id) for p in cut]
    done = map_pieces(workers, _cut_one, items, what="layout")
    by_id = {p.id: r for p, r in zip(cut, done, strict=True)}
    out, removed = [], 0.0
    for p in pieces:
        if p.id not in by_id:
            out.append(p)
            continue
        ref, v = by_id[p.id]
        removed += v
        out.append(dataclasses.replace(p, mesh=ref.mesh, volume=p.volume - v, triangles=int(len(ref.mesh.faces))))
    return out, removed


def _cut_one(_shared, item):
    """base_cut of one item (MeshRef, Pose, piece id), wherever it runs -> (MeshRef, mm^3 removed)."""
    from .workers import MeshRef

    ref, pose, pid = item
    mesh, v = base_cut(ref.mesh, pose, pid)
    return MeshRef(mesh), v


def print_entry(piece, pose, placement):
    """report.json "print" of a piece: its pose, the (4, 4) transform to its plate, its bed contact there."""
    if pose is None or placement is None:
        return None
    entry = pose.to_report()
    entry["plate_transform"] = np.round(placement.transform, 6).tolist()
    from .check import piece_bed_contact

    # on the transform as stored, so that the printability check measures this very placement (once)
    entry["bed_contact_mm2"] = round(piece_bed_contact(piece.mesh, entry["plate_transform"]), 2)
    return entry


def plates_and_preview(spec, pieces, dowels, joints, colors, pins=None, texture=None, poses=None, steps=None,
                       step_pictures=None):
    """Plates and preview as writers for the export stage. -> (placements, plates, {relative path: writer}).
    step_pictures: the steps' pictures as step_pictures_ahead began them, else they are drawn with the rest."""
    from .workers import MeshRef, Remote

    pin_dirs, openings, _ = joint_directions(joints)
    parts = [(p.id, p.mesh) for p in pieces] + list(dowels)
    rgb = {p.id: c for p, c in zip(pieces, colors, strict=True)}
    placements, plates = layout(parts, spec.output.plate, spec.output.spacing, pin_dirs, margin=spec.output.margin,
                                poses=poses, hole_openings=openings)
    meshes = dict(parts)
    # the plates and pictures as plain functions of plain data (workers.Remote), which the export may write in a
    # worker while this process writes the pieces: lib3mf writes one file at a time in a process, and at 1024 pieces
    # the puzzle's 3MF and its plates' were ~7 s of it
    extras = {}
    for pl in plates:
        on = [place for place in placements if place.plate == pl.index]
        extras[pl.file] = Remote(_write_plate, [(place.name, MeshRef(meshes[place.name]), place.transform,
                                                 rgb.get(place.name, (200, 200, 200))) for place in on],
                                 [(pins or {}).get(place.name) for place in on],
                                 None if texture is None else [texture.get(place.name) for place in on])
    refs = [MeshRef(p.mesh) for p in pieces]
    names = [p.id for p in pieces]
    index = {p.id: k for k, p in enumerate(pieces)}
    on_plate = [(index[pl.name], pl.transform) for pl in placements if pl.plate == 1 and pl.name in index]
    extras["preview.png"] = Remote(_write_preview, refs, names, np.asarray(colors), pins, texture, on_plate,
                                   tuple(spec.output.plate), spec.name, steps)
    if steps:
        extras["steps"] = (Remote(_write_steps, refs, names, colors, steps) if step_pictures is None
                           else partial(_save_steps, step_pictures))
    return placements, plates, extras


def step_pictures_ahead(workers, pieces, colors, steps):
    """A worker begins drawing the assembly steps' pictures now (workers.Prefetch of preview.step_pictures), while
    this process lays out the plates and judges the folder: at 1024 pieces they are ~8 s of the export's work, which
    waited for them. pieces: final (as the files store them). -> Prefetch, or None without workers or steps."""
    if workers is None or not steps:
        return None
    from .workers import MeshRef

    return workers.prefetch(_step_pictures, [MeshRef(p.mesh) for p in pieces], [p.id for p in pieces],
                            np.asarray(colors), steps)


def _step_pictures(refs, names, colors, steps):
    from .preview import step_pictures

    return step_pictures([r.mesh for r in refs], names, colors, steps)


def _save_steps(pictures, path):
    """The steps' pictures begun by step_pictures_ahead written into the folder `path`."""
    from .preview import save_pictures

    save_pictures(path, pictures.result())


def _write_plate(path, items, materials, colors):
    """A plate's 3MF: items [(name, MeshRef, (4, 4) transform to the plate, rgb)]; materials and colors as write_3mf
    takes them (one entry per item)."""
    from .io.threemf import write_3mf

    objs = [(name, ref.mesh.vertices @ transform[:3, :3].T + transform[:3, 3], ref.mesh.faces, rgb, None)
            for name, ref, transform, rgb in items]
    write_3mf(path, objs, materials=materials, colors=colors)


def _write_preview(path, refs, names, colors, pins, texture, on_plate, plate, title, steps):
    """preview.png of the pieces (workers.MeshRef, in mm): the puzzle pulled apart along its plan, its first plate."""
    from .preview import plan_offsets, render_preview

    meshes = [r.mesh for r in refs]
    # pins a shade darker than their piece, so that they stand out
    shaded = []
    for pid, mesh, c in zip(names, meshes, colors, strict=True):
        flag = (pins or {}).get(pid)
        if texture is None and flag is None:
            shaded.append(np.asarray(c, np.uint8))
            continue
        if texture is not None:
            from .texture import face_colors

            tri = np.array(face_colors(c, texture[pid]), np.uint8)
        else:
            tri = np.tile(np.asarray(c, np.uint8), (len(mesh.faces), 1))
        if flag is not None:
            tri[flag.astype(bool)] = (tri[flag.astype(bool)] * 0.55).astype(np.uint8)
        shaded.append(tri)
    offsets = plan_offsets(meshes, names, steps) if steps else None
    render_preview(path, meshes, shaded, title=title, offsets=offsets, plate=(on_plate, tuple(plate)))


def _write_steps(path, refs, names, colors, steps):
    """One picture per assembly step into the folder `path` (preview.step_pictures)."""
    from .preview import save_pictures

    save_pictures(path, _step_pictures(refs, names, colors, steps))
