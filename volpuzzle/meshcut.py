"""Mesh mode (paper section 5): cage pieces intersected with the mesh Mp, fragments merged by their largest contact,
and joints placed on the real contact patches between the final pieces.

Order: build the cage pieces WITHOUT pins and holes, intersect_pieces, merge_fragments, then place_joints on the
merged pieces, and only then add pins and cut holes (add_joints). Intersecting after the pins would clip a pin where
the mesh is thin, and a fragment handed to a neighbour could carry half a joint with it.

Contacts. Two pieces cut from neighbouring cells share the cells' common face exactly: compose tessellates a shared
face once, and the engine cuts both copies by the same mesh triangles, so the shared patch has the same vertices on
both sides (up to rounding, which vertex keys at a nanometre absorb). A triangle of one piece whose three vertices
all belong to the other lies on their contact; the sum of their areas is the contact's area (it equals
(area A + area B - area (A u B)) / 2, which costs a Boolean per pair).
A touch along an edge or at a point has no area and is no contact: merging across it would weld a non-manifold solid.

Joints (the paper's Fig. 15). On each contact patch the pin goes where the patch leaves the most wall: the patch
point farthest from the patch's boundary (the mesh's surface and the edges where a third piece begins). Its
direction is the sliding direction of the assembly split that parts the two pieces, so that a block slides off all
its pins at once, as long as that stays within MAX_TILT_DEG of the patch there. The pin's room (hole, clearance and
wall) is checked against the real pieces, cropped around the patch, instead of against the whole mesh.
"""

from dataclasses import dataclass

import numpy as np

from .errors import GeometryError
from .geometry import check_status, cylinder, unique_pairs
from .joint import MAX_TILT_DEG, MIN_LENGTH, MIN_RADIUS, outer_radius, wall
from .progress import warn

__all__ = ["intersect_pieces", "merge_fragments", "contacts", "Contact", "PinSize", "place_joints", "add_joints",
           "joint_graph_problem", "plan_splits", "compose_in_mesh"]

MAX_PINS = 3  # pins and holes per piece, as in the paper
SLIVER_SHARE = 0.002  # of a piece's volume: what a face clearance may cut off it as slivers
NEAR_CONTACT = 0.5  # a fragment's contact this share of its widest one may win by other merits
_KEY = 1e6  # vertex keys: mm rounded to a nanometre
_NUDGE = 1e-6 * np.array([0.6180339887, 0.4142135624, 0.7320508076])  # of the model's size, see compose_in_mesh


def intersect_pieces(pieces_bodies, mesh_manifold, min_volume=1e-9):
    """{id: Manifold} cage pieces (mm) and the mesh as a Manifold -> {id: body ∩ mesh}. A cell that misses the mesh
    (empty or below min_volume mm^3) gives no piece."""
    check_status(mesh_manifold, "mesh model", "the mesh solid")
    out = {}
    for pid, body in pieces_bodies.items():
        check_status(body, pid, "the cage piece")
        cut = check_status(body ^ mesh_manifold, pid, "intersecting the piece with the mesh")
        if not cut.is_empty() and cut.volume() > min_volume:
            out[pid] = cut
    return out


# --- contacts -------------------------------------------------------------------------------------------------------
def _vertex_ids(meshes):
    """One integer per distinct vertex position over all meshes -> list of (n_i,) int arrays."""
    keys = np.concatenate([np.round(np.asarray(m.vertices) * _KEY).astype(np.int64) for m in meshes])
    inv = _row_ranks(keys)
    out, n = [], 0
    for m in meshes:
        out.append(inv[n:n + len(m.vertices)])
        n += len(m.vertices)
    return out


def _row_ranks(keys):
    """keys (n, 3) int64 -> (n,) each row's rank among the distinct rows, as np.unique(axis=0, return_inverse=True)
    gives it, from one lexsort: 3x faster (0.30 -> 0.10 CPU s at 260k rows) than unique's rows as one record."""
    if not len(keys):
        return np.zeros(0, np.int64)
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
    rows = keys[order]
    rank = np.cumsum(np.r_[True, np.any(rows[1:] != rows[:-1], axis=1)]) - 1
    out = np.empty(len(keys), np.int64)
    out[order] = rank
    return out


def _shared_faces(meshes, ids=None):
    """{(i, j): (k,) bool mask over mesh i's faces lying on mesh j} for i != j with a positive shared area."""
    ids = _vertex_ids(meshes) if ids is None else ids
    boxes = np.array([m.bounds for m in meshes])  # (n, 2, 3)
    span = float(np.max(boxes[:, 1] - boxes[:, 0])) if len(meshes) else 1.0
    eps = 1e-6 * max(span, 1.0)
    out = {}
    for i, mi in enumerate(meshes):
        for j in range(len(meshes)):
            if i == j or np.any(boxes[i, 0] > boxes[j, 1] + eps) or np.any(boxes[j, 0] > boxes[i, 1] + eps):
                continue
            on = np.isin(ids[i], ids[j])
            tri = on[np.asarray(mi.faces)].all(axis=1)
            if tri.any() and float(mi.area_faces[tri].sum()) > 0.0:
                out[(i, j)] = tri
    return out


def _pair_areas(meshes):
    """{(i, j): mm^2} for i < j: the mean of the two sides' shared areas (they agree up to rounding)."""
    masks = _shared_faces(meshes)
    out = {}
    for (i, j), tri in masks.items():
        if i < j:
            back = masks.get((j, i))
            a = float(meshes[i].area_faces[tri].sum())
            b = float(meshes[j].area_faces[back].sum()) if back is not None else 0.0
            out[(i, j)] = 0.5 * (a + b)
    return out


@dataclass(frozen=True, eq=False)
class Contact:
    """The patch where piece `a` touches piece `b`: triangles (k, 3, 3) mm of a's surface there, facing out of a
    into b; area in mm^2; boundary (m, 2, 3) mm, the patch's border edges."""

    a: str
    b: str
    area: float
    triangles: np.ndarray
    boundary: np.ndarray


def contacts(pieces):
    """{id: trimesh} final pieces -> list of Contact, one per touching pair (a < b), largest first."""
    names = sorted(pieces)
    meshes = [pieces[k] for k in names]
    masks = _shared_faces(meshes)
    out = []
    for (i, j), tri in masks.items():
        if i > j:
            continue
        m = meshes[i]
        faces = np.asarray(m.faces)[tri]
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        uniq, count = unique_pairs(edges)
        border = uniq[count == 1]
        v = np.asarray(m.vertices)
        out.append(Contact(names[i], names[j], float(m.area_faces[tri].sum()), v[faces], v[border]))
    out.sort(key=lambda c: (-c.area, c.a, c.b))
    return out


# --- fragments ------------------------------------------------------------------------------------------------------
def merge_fragments(pieces, min_fraction=0.05):
    """{id: Manifold} -> ({id: Manifold}, merge records). Every piece keeps its largest body; every other body (a
    fragment) and every piece under min_fraction of the mean volume joins a piece it touches: among its contacts at
    least NEAR_CONTACT of its widest, the one whose piece then spans the fewest cells, a piece before another
    fragment, then the widest. Contacts are summed over what has merged so far, so a fragment that touches only
    another fragment follows it, and a ring of fragments (a torus, a knot) finds its piece too. Total volume is kept;
    ids stay the cells'. A fragment that touches nothing (only at edges or points, or not at all) -> GeometryError;
    a small piece that touches nothing stays a piece of its own.

    Records: {"from": id, "to": id, "volume_mm3": v, "reason": "fragment" | "small piece"}, and "to" None with
    "speck dropped" for bodies below a thousandth of a mm^3.
    """
    from .geometry import to_trimesh

    if not pieces:
        return {}, []
    bodies, slivers = [], []  # (cell id, Manifold)
    total = sum(p.volume() for p in pieces.values())
    for pid in sorted(pieces):
        parts = sorted(pieces[pid].decompose(), key=lambda b: -b.volume())
        for k, b in enumerate(parts):
            # a speck the engine leaves where the mesh grazes a cut (far below a printed layer) touches nothing
            if k > 0 and b.volume() < min(1e-3, 1e-9 * total):
                slivers.append({"from": pid, "to": None, "volume_mm3": float(b.volume()), "reason": "speck dropped"})
            else:
                bodies.append((pid, b))
    vols = np.array([b.volume() for _, b in bodies])
    per_cell = {}
    for k, (pid, _) in enumerate(bodies):
        per_cell.setdefault(pid, []).append(k)
    mean = float(vols.sum()) / len(per_cell)
    # anchor: a cell's largest body, strong when the cell is big enough to be printed on its own
    strong = {ks[0] for pid, ks in per_cell.items() if vols[ks].sum() >= min_fraction * mean}
    weak = {ks[0] for pid, ks in per_cell.items()} - strong
    if not strong:
        strong = {max(weak, key=lambda k: vols[k])}
        weak -= strong
    areas = _pair_areas([to_trimesh(b) for _, b in bodies])

    # clusters of bodies; a cluster is settled when it holds a strong anchor
    members = {k: [k] for k in range(len(bodies))}
    touch = {k: {} for k in range(len(bodies))}
    for (i, j), a in areas.items():
        touch[i][j] = touch[i].get(j, 0.0) + a
        touch[j][i] = touch[j].get(i, 0.0) + a
    settled = {k: k in strong for k in range(len(bodies))}
    solid = {k: b for k, (_, b) in enumerate(bodies)}
    banned = set()
    while True:
        best = None
        for c in members:
            if settled[c]:
                continue
            open_ = {o: a for o, a in touch[c].items() if (c, o) not in banned}
            widest = max(open_.values(), default=0.0)
            for o, a in open_.items():
                # Among the contacts nearly as wide as its widest, a fragment joins the piece that then spans the
                # fewest cells, a piece rather than another fragment. A piece spread over many cells reaches round
                # its neighbours and locks them in: a knot cut 2 x 2 x 1 leaves two arcs in every cell, and arcs
                # chained arc to arc by the widest contact gave pieces that no straight slide takes apart.
                span = len({bodies[k][0] for k in members[o] + members[c]})
                key = (a >= NEAR_CONTACT * widest, -span, settled[o], a, -min(members[o]), -min(members[c]))
                if best is None or key > best[0]:
                    best = (key, c, o)
        if best is None:
            break
        _, c, o = best
        merged = check_status(solid[o] + solid[c], bodies[min(members[o])][0], "merging a fragment")
        if not _one_manifold_solid(merged):
            # the two also meet along an edge or at a point somewhere (four cells around a cage edge cut a tube into
            # quarters; diagonal quarters touch along the edge): welded, that is no solid a slicer takes
            banned.add((c, o))
            continue
        solid[o] = merged
        del solid[c]
        members[o] += members.pop(c)
        settled[o] = settled[o] or settled[c]
        for x, a in touch.pop(c).items():
            if x == o:
                continue
            touch[x].pop(c, None)
            touch[x][o] = touch[x].get(o, 0.0) + a
            touch[o][x] = touch[o].get(x, 0.0) + a
        touch[o].pop(c, None)
        settled.pop(c)

    out, records = {}, []
    for c, ks in sorted(members.items(), key=lambda kv: bodies[min(kv[1])][0]):
        anchors = [k for k in ks if k in strong] or [k for k in ks if k in weak]
        if not anchors:
            k = ks[0]
            pid = bodies[k][0]
            if any(touch[c].values()):
                raise GeometryError(
                    f"{pid}: a fragment of {vols[ks].sum():.4g} mm^3 meets every piece it touches also along an edge "
                    "or at a point, so merging it would not give one closed solid; use a different grid or cage")
            raise GeometryError(
                f"{pid}: a fragment of {vols[ks].sum():.4g} mm^3 touches no other piece (it meets them only along an "
                "edge or at a point, or not at all), so it cannot be merged; use a different grid or cage")
        name = bodies[anchors[0]][0]
        for k in ks:
            if k != anchors[0]:
                records.append({"from": bodies[k][0], "to": name, "volume_mm3": float(vols[k]),
                                "reason": "small piece" if k in weak else "fragment"})
        out[name] = solid[c]
    records = sorted(records + slivers, key=lambda r: (r["from"], -r["volume_mm3"]))
    return out, records


def _one_manifold_solid(m):
    """True when the Manifold is one body whose surface is still 2-manifold once stored as STL and 3MF store it
    (float32 vertices, equal ones merged, collapsed triangles dropped, as export.printable does): two parts that
    also touch along a line would share an edge among four triangles there."""
    from .geometry import to_trimesh, weld

    if len(m.decompose()) != 1:
        return False
    t = to_trimesh(m)
    v32, inverse = np.unique(np.asarray(t.vertices, np.float32), axis=0, return_inverse=True)
    _, f = weld(v32.astype(np.float64), inverse.reshape(-1)[np.asarray(t.faces)], 0.0)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, count = unique_pairs(edges)
    return bool(len(f)) and bool(np.all(count == 2))


# --- joints ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PinSize:
    """The wanted pin (mm) and how far it may shrink on a small contact."""

    radius: float
    length: float
    clearance: float
    axial_clearance: float
    shape: str = "cylinder"
    style: str = "pin"
    min_radius: float = MIN_RADIUS
    min_length: float = MIN_LENGTH


def _reach(size, radius):
    """Radius of the hole a pin of `radius` makes (a snap pin swells)."""
    return outer_radius(radius, size.shape) + size.clearance


def _outside(env, solids):
    """True when some of `env` lies outside the union of `solids` (more than a polygon's rounding)."""
    rest = env
    for s in solids:
        rest = rest - s
        if rest.is_empty():
            return False
    return rest.volume() > 1e-5 * env.volume()


def _crop(solid, lo, hi):
    import manifold3d

    box = manifold3d.Manifold.cube(list(np.asarray(hi) - np.asarray(lo))).translate(list(lo))
    return check_status(solid ^ box, "joint", "cropping a piece around a contact")


def _samples(tris, rng, spacing):
    """Points (n, 3) spread over triangles (k, 3, 3) about `spacing` apart, their corners and centres included."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    n = int(min(20000, max(200, area.sum() / spacing ** 2)))
    pick = rng.choice(len(tris), size=n, p=area / area.sum()) if area.sum() > 0 else np.zeros(0, int)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    pts = a[pick] + u[:, None] * (b - a)[pick] + v[:, None] * (c - a)[pick]
    return np.concatenate([pts, tris.mean(axis=1), tris.reshape(-1, 3)])


def _edge_points(edges, spacing):
    """Points (n, 3) along edges (m, 2, 3) at most `spacing` apart."""
    if len(edges) == 0:
        return np.zeros((0, 3))
    length = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1)
    k = np.maximum(1, np.ceil(length / spacing).astype(int))
    idx = np.repeat(np.arange(len(edges)), k + 1)
    t = np.concatenate([np.linspace(0.0, 1.0, kk + 1) for kk in k])
    return edges[idx, 0] + t[:, None] * (edges[idx, 1] - edges[idx, 0])


def _seg_distance(p0, p1, q0, q1):
    """Least distance between segments p0p1 and q0q1 (3,)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f = d1 @ d1, d2 @ d2, d2 @ r
    c, b = d1 @ r, d1 @ d2
    den = a * e - b * b
    s = np.clip((b * f - c * e) / den, 0.0, 1.0) if den > 1e-12 else 0.0
    t = (b * s + f) / e if e > 1e-12 else 0.0
    if t < 0.0:
        t, s = 0.0, np.clip(-c / a, 0.0, 1.0) if a > 1e-12 else 0.0
    elif t > 1.0:
        t, s = 1.0, np.clip((b - c) / a, 0.0, 1.0) if a > 1e-12 else 0.0
    return float(np.linalg.norm((p0 + s * d1) - (q0 + t * d2)))


@dataclass(frozen=True)
class _Option:
    """A pin that fits one contact: centre, direction out of the pin piece, sizes, base depth (mm)."""

    pin: str
    hole: str
    center: np.ndarray
    direction: np.ndarray
    radius: float
    length: float
    base: float
    reach: float
    wall: float

    def segment(self):
        return (self.center - (self.base + self.wall) * self.direction,
                self.center + (self.length + self.wall) * self.direction)


class _Patch:
    """One contact's candidate pin centres, ranked by their distance to the patch's border, with local normals."""

    def __init__(self, contact, rng):
        tris = contact.triangles
        nrm = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        size = float(np.sqrt(contact.area))
        spacing = float(np.clip(size / 60.0, 0.1, 1.0))
        from scipy.spatial import cKDTree

        self.points = _samples(tris, rng, spacing)
        border = _edge_points(contact.boundary, 0.5 * spacing)
        self.clear = (cKDTree(border).query(self.points)[0] if len(border)
                      else np.full(len(self.points), np.inf))
        self.centroids = tris.mean(axis=1)
        self.normals = nrm  # area-weighted (k, 3): |n| = 2 area
        self.tree = cKDTree(self.centroids)
        self.widest = float(self.clear.max()) if len(self.clear) else 0.0
        self.spacing = spacing

    def normal_at(self, p, radius):
        """Unit area-weighted normal of the patch within `radius` of p (out of piece a)."""
        near = self.tree.query_ball_point(p, max(radius, 2 * self.spacing))
        if not near:
            near = [int(self.tree.query(p)[1])]
        n = self.normals[near].sum(axis=0)
        return n / max(float(np.linalg.norm(n)), 1e-300)

    def spots(self, need, count=10):
        """Up to `count` centres (3,) with at least `need` mm to the border, widest first, spread apart."""
        order = np.argsort(-self.clear)
        order = order[self.clear[order] >= need]
        pts, clear = self.points[order], self.clear[order]
        out = []
        alive = np.ones(len(order), bool)
        while len(out) < count:
            left = np.flatnonzero(alive)
            if not len(left):
                break
            i = left[0]
            out.append((pts[i], float(clear[i])))
            alive &= np.linalg.norm(pts - pts[i], axis=1) > 0.5 * clear
        return out


def _sizes(size, room):
    """(radius, length) pairs to try, largest first, for a spot `room` mm from the patch's border."""
    radii = []
    r = float(size.radius)
    while r >= size.min_radius - 1e-9:
        radii.append(round(r, 2))
        r *= 0.75
    if not radii or radii[-1] > size.min_radius:
        radii.append(float(size.min_radius))
    lengths = sorted({round(float(size.length), 2), round(max(size.min_length, 0.55 * size.length), 2),
                      float(size.min_length)}, reverse=True)
    out = []
    for r in radii:
        if _reach(size, r) + wall(r) > room + 1e-9:
            continue
        out += [(r, L) for L in lengths if L <= size.length + 1e-9]
    return out


def _fit(patch, crops, contact, size, p, d, r, L, pin_a):
    """Whether a pin of radius r and length L at p along d (out of the pin piece) fits its two pieces with its
    clearance and wall -> (base depth, None) or (None, why)."""
    R, w = _reach(size, r), wall(r)
    rel = patch.points - p
    t = rel @ d
    radial = np.linalg.norm(rel - t[:, None] * d, axis=1)
    near = t[radial <= R + w]
    lo, hi = (float(near.min()), float(near.max())) if len(near) else (0.0, 0.0)
    base = round(max(0.5, 1.5 * max(-lo, 0.0) + 0.3), 4)
    front = L + size.axial_clearance
    a_solid, b_solid = (crops[contact.a], crops[contact.b]) if pin_a else (crops[contact.b], crops[contact.a])
    if _outside(cylinder(p, d, R + w, -(base + w), front + w, "joint", 24), [a_solid, b_solid]):
        return None, "the pin's hole with its wall would break out of the two pieces"
    if _outside(cylinder(p, d, R + w, max(hi, 0.0) + 1e-3, front + w, "joint", 24), [b_solid]):
        return None, f"the hole piece is too thin for a {L:g} mm pin with its wall"
    if _outside(cylinder(p, d, r + w, -(base + w), min(lo, 0.0) - 1e-3, "joint", 24), [a_solid]):
        return None, "the pin piece is too thin for the pin's base"
    return base, None


def _try(patch, contact, crops, size, direction, pin_a, placed=(), memo=None, max_tests=48):
    """The best fitting _Option on one contact with the pin in piece a (pin_a) or in b, clear of the joints `placed`
    (_Option list) by their reach and a wall, or (None, why)."""
    d = np.asarray(direction, float)
    if not pin_a:
        d = -d
    pin, hole = (contact.a, contact.b) if pin_a else (contact.b, contact.a)
    cos_max = np.cos(np.radians(MAX_TILT_DEG))
    need = _reach(size, size.min_radius) + wall(size.min_radius)
    spots = patch.spots(need)
    if not spots:
        return None, (f"no room: the widest spot of the {contact.area:.0f} mm^2 contact is {patch.widest:.2f} mm from "
                      f"its edge, a {size.min_radius:g} mm pin with clearance and wall needs {need:.2f} mm")
    tests, why = 0, None
    good = []
    upright = -1.0
    for p, room in spots:
        n = patch.normal_at(p, room)  # out of a
        cos = float(n @ d) if pin_a else float(-n @ d)
        upright = max(upright, cos)
        if cos >= cos_max:
            good.append((p, room))
    if not good:
        lean = float(np.degrees(np.arccos(np.clip(upright, -1.0, 1.0))))
        return None, (f"the sliding direction of the split between {contact.a} and {contact.b} stands at least "
                      f"{np.floor(lean * 10) / 10:g} deg off the contact wherever a pin has room, more than the "
                      f"{MAX_TILT_DEG:g} deg a straight pin may lean")
    trials = [(p, r, L) for r, L in _sizes(size, good[0][1]) for p, room in good[:5]
              if _reach(size, r) + wall(r) <= room + 1e-9]
    for p, r, L in trials:
        if tests >= max_tests:
            break
        R, w = _reach(size, r), wall(r)
        seg = (p - (0.5 + w) * d, p + (L + size.axial_clearance + w) * d)  # the base is at least 0.5 mm deep
        clash = next((o for o in placed if _seg_distance(*seg, *o.segment()) < R + o.reach + max(w, o.wall)), None)
        if clash is not None:
            why = why or f"every spot with room would meet the joint between {clash.pin} and {clash.hole}"
            continue
        tests += 1
        key = (pin_a, tuple(np.round(p, 6)), r, L, tuple(np.round(d, 9)))
        if memo is None or key not in memo:
            result = _fit(patch, crops, contact, size, p, d, r, L, pin_a)
            if memo is not None:
                memo[key] = result
        else:
            result = memo[key]
        base, reason = result
        if reason is not None:
            why = reason
            continue
        got = _Option(pin, hole, p, d, r, L + size.axial_clearance, base, R, w)
        if any(_seg_distance(*got.segment(), *o.segment()) < R + o.reach + max(w, o.wall) for o in placed):
            continue
        return _Option(pin, hole, p, d, r, L, base, R, w), None
    return None, why or "no spot holds the pin with its wall"


def place_joints(pieces, cells, size, plan=True, seed=0):
    """Joints on the contacts of the final pieces -> (list of joint.Joint, contact records, AssemblyPlan or None).

    pieces: {id: Manifold} the merged pieces, without joints (mm); cells: {id: cell index}; size: PinSize;
    plan: True to point every pin along the slide of its split in plan_splits (then the plan is returned too),
    False to point it along its patch's normal.

    Contacts are taken in the order of a maximum spanning tree of their areas first (so the joint graph stays
    connected whenever it can), then by area. Each gets one pin where it fits with its clearance and wall, at most
    MAX_PINS pins and MAX_PINS holes per piece, no two joints within a wall of each other. Records, one per contact:
    {"pieces": [a, b], "area_mm2", "widest_mm" (the patch's largest distance from its edge), "room" (a pin of the
    smallest size fits there), "pinned", "reason" (why not, or None), "radius_mm", "length_mm"}.
    """
    import networkx as nx

    from .geometry import to_trimesh
    from .joint import Joint

    meshes = {k: to_trimesh(v) for k, v in pieces.items()}
    found = contacts(meshes)
    assembly, dir_of = plan_splits(meshes, found, cells) if plan else (None, {})
    g = nx.Graph()
    for c in found:
        g.add_edge(c.a, c.b, weight=c.area)
    tree = {frozenset(e) for e in nx.maximum_spanning_edges(g, data=False)} if found else set()
    rng = np.random.default_rng(seed)
    depth = size.length + size.axial_clearance + 2 * wall(size.radius) + 2.0 * _reach(size, size.radius) + 1.0
    prepared = []  # per contact: patch, crops, planned direction (or None), direction to try first
    for c in found:
        patch = _Patch(c, rng)
        d_plan = dir_of.get((c.a, c.b))
        d = d_plan
        if d is None or not np.any(d):
            d_plan, d = None, patch.normal_at(patch.points[int(np.argmax(patch.clear))], patch.widest)
        lo = c.triangles.reshape(-1, 3).min(axis=0) - depth
        hi = c.triangles.reshape(-1, 3).max(axis=0) + depth
        crops = {k: _crop(pieces[k], lo, hi) for k in (c.a, c.b)}
        prepared.append((patch, crops, d_plan, np.asarray(d, float) / np.linalg.norm(d), {}))

    def run(first, tilt_ok=frozenset()):
        """Place the contacts, those numbered in `first` first, then the spanning tree's, then by area; those in
        tilt_ok may take a pin along their own normal when their split slides too far off them."""
        order = sorted(range(len(found)), key=lambda i: (i not in first, frozenset((found[i].a, found[i].b)) not in
                                                           tree, -found[i].area, found[i].a, found[i].b))
        pins = {k: 0 for k in pieces}
        holes = {k: 0 for k in pieces}
        placed, records = [], {}
        for i in order:
            c = found[i]
            patch, crops, d_plan, d, memo = prepared[i]
            rec = {"pieces": [c.a, c.b], "area_mm2": round(c.area, 3), "widest_mm": round(patch.widest, 3)}
            # the pin goes into the piece with fewer pins (then fewer holes), the other way if that one is full
            roles = sorted((True, False), key=lambda pa: (pins[c.a if pa else c.b] + holes[c.b if pa else c.a],
                                                          pins[c.a if pa else c.b], not pa))

            def attempt(d, c=c, roles=roles, patch=patch, crops=crops, memo=memo):
                """The first role that is not full and whose pin fits clear of the joints placed so far."""
                why = None
                for pin_a in roles:
                    pin, hole = (c.a, c.b) if pin_a else (c.b, c.a)
                    if pins[pin] >= MAX_PINS or holes[hole] >= MAX_PINS:
                        full = pin if pins[pin] >= MAX_PINS else hole
                        why = why or f"{full} already has {MAX_PINS} {'pins' if full == pin else 'holes'}"
                        continue
                    got, reason = _try(patch, c, crops, size, d, pin_a, placed, memo)
                    if got is not None:
                        return got, None
                    why = why or reason
                return None, why

            option, why = attempt(d)
            if option is None and i in tilt_ok and d_plan is not None and why and "deg off" in why:
                # the split's slide stands too far off this contact, which the joint graph needs: a pin along the
                # contact's own normal holds the piece; the disassembly replay looks for another way apart
                option, _ = attempt(patch.normal_at(patch.points[int(np.argmax(patch.clear))], patch.widest))
                if option is not None:
                    why = None
                    rec["off_plan"] = True
            # room: a pin fits the contact at all, whatever the other joints, the counts and the slide say
            room = option is not None or _try(patch, c, crops, size, d, roles[0], (), memo)[0] is not None
            if not room and d_plan is not None and why and "deg off" in why:
                normal = patch.normal_at(patch.points[int(np.argmax(patch.clear))], patch.widest)
                room = _try(patch, c, crops, size, normal, roles[0], (), memo)[0] is not None
            rec.update(room=room, pinned=option is not None, reason=why)
            if option is not None:
                pins[option.pin] += 1
                holes[option.hole] += 1
                placed.append(option)
                rec.update(radius_mm=option.radius, length_mm=option.length)
            records[i] = rec
        return placed, [records[i] for i in range(len(found))]

    def parts(placed):
        h = nx.Graph()
        h.add_nodes_from(pieces)
        h.add_edges_from((o.pin, o.hole) for o in placed)
        return {k: n for n, comp in enumerate(nx.connected_components(h)) for k in comp}

    first = set()
    placed, records = run(first)
    # A joint placed early can take the only room a later bridge had: put the unpinned contacts that would join
    # two parts of the joint graph first and try again, keeping the best outcome.
    for _ in range(3):
        part = parts(placed)
        if len(set(part.values())) <= 1:
            break
        bridges = {i for i, c in enumerate(found) if part[c.a] != part[c.b] and records[i]["room"]}
        if not bridges - first:
            break
        first |= bridges
        again, again_records = run(first)
        if (len(set(parts(again).values())), -len(again)) < (len(set(part.values())), -len(placed)):
            placed, records = again, again_records
    part = parts(placed)
    if len(set(part.values())) > 1:
        # last resort for the bridges whose split slides too far off them: pins along their own normals
        bridges = frozenset(i for i, c in enumerate(found) if part[c.a] != part[c.b])
        again, again_records = run(first | bridges, bridges)
        if len(set(parts(again).values())) < len(set(part.values())):
            placed, records = again, again_records
    joints = []
    nan = np.full(3, np.nan)
    nan.setflags(write=False)
    for o in placed:
        center, direction = np.array(o.center, float), np.array(o.direction, float)
        center.setflags(write=False)
        direction.setflags(write=False)
        joints.append(Joint(
            pin_cell=tuple(cells[o.pin]), hole_cell=tuple(cells[o.hole]), axis=int(np.argmax(np.abs(o.direction))),
            across_seam=False, center=center, direction=direction, radius=float(o.radius), length=float(o.length),
            clearance=float(size.clearance), axial_clearance=float(size.axial_clearance), shape=size.shape,
            style=size.style, space="physical", uvw_pin=nan, uvw_hole=nan, base_depth=float(o.base)))
    return joints, records, assembly


def joint_graph_problem(piece_ids, joints, records):
    """None when every piece has a joint and the joint graph (pieces, joints) is one part, else one line naming the
    piece left out and why its contacts took no pin."""
    import networkx as nx

    from .grid import piece_id

    g = nx.Graph()
    g.add_nodes_from(piece_ids)
    for j in joints:
        g.add_edge(piece_id(j.pin_cell), piece_id(j.hole_cell))
    parts = sorted(nx.connected_components(g), key=lambda p: (-len(p), min(p)))
    if len(parts) <= 1:
        return None
    loose = sorted(parts[1:], key=lambda p: (len(p), min(p)))[0]
    name = min(loose, key=lambda k: (g.degree(k), k))
    mine = [r for r in records if (r["pieces"][0] in loose) != (r["pieces"][1] in loose)]
    what = "has no joint" if g.degree(name) == 0 else f"and {len(loose) - 1} more hold to the rest by no joint"
    if not mine:
        return f"{name}: the piece {what}: it touches no other piece over an area (try a different grid or cage)"
    best = max(mine, key=lambda r: r["widest_mm"])
    other = best["pieces"][1] if best["pieces"][0] in loose else best["pieces"][0]
    return (f"{name}: the piece {what}: its widest contact, with {other}, takes no pin ({best['reason']}); "
            "try a smaller joints.radius, a coarser grid or different splits")


def add_joints(pieces, cells, joints):
    """{id: Manifold} merged pieces -> {id: Manifold} with their pins added and holes cut."""
    from .geometry import boolean
    from .joint import cell_joints, hole_solid, pieces_joints, pin_solid

    out = {}
    touching = cell_joints(joints)
    for pid, body in pieces.items():
        for j, role in pieces_joints(touching.get(tuple(cells[pid]), ()), cells[pid]):
            if role == "pin":
                body = boolean(body, pin_solid(j), "union", pid)
            else:
                body = boolean(body, hole_solid(j, cells[pid]), "difference", pid)
        out[pid] = body
    return out


# --- face clearance -------------------------------------------------------------------------------------------------
def set_back_faces(cut, cells, shrunk, merges, clearance):
    """{id: Manifold} merged pieces (cut by the mesh, joints not yet added) -> ({id: Manifold}, mm^3 taken): every
    face a piece shares with another set back by half of `clearance`, as compose sets back a volume's cut faces.

    cells: {cell id: Manifold} the cage cells as cut (faces not set back); shrunk: the same cells composed with the
    face clearance. A piece made of one cell is that piece within its shrunk cell. A piece that took in fragments of
    other cells keeps, besides each member cell's shrunk part, the layer between two of its own parts that touch
    (over their contact: where both parts, moved by the clearance across it, overlap), so it stays one solid;
    should it still come apart, it is left as it was (its neighbours then keep their half of the gap)."""
    from .geometry import boolean, kept_bodies

    members = {pid: [pid] for pid in cut}
    for r in merges:
        if r.get("to") in members and r.get("from") in cells and r["from"] not in members[r["to"]]:
            members[r["to"]].append(r["from"])
    out, taken = {}, 0.0
    for pid, body in cut.items():
        what = f"{pid} (face clearance)"
        keep = shrunk[members[pid][0]]
        for x in members[pid][1:]:
            keep = boolean(keep, shrunk[x], "union", what)
        if len(members[pid]) > 1:
            parts = {x: boolean(body, cells[x], "intersection", what) for x in members[pid]}
            names = members[pid]
            for i, x in enumerate(names):
                for y in names[i + 1:]:
                    n = _contact_direction(parts[x], parts[y])
                    if n is None:
                        continue
                    # each part moved by the clearance across the common face: where both moved copies overlap is
                    # the column over their contact only (not over x's faces towards other pieces), a clearance on
                    # either side, so it overlaps both shrunk cells instead of meeting them face to face (coincident
                    # faces leave slivers that float32 files turn into non-manifold edges)
                    reach = (boolean(parts[x].translate(list(clearance * n)),
                                     parts[y].translate(list(-clearance * n)), "intersection", what))
                    # the parts reach their cells' own faces sideways, so the column would fill the half clearance
                    # of a third piece across the faces that run through the contact: the shrunk cells, moved the
                    # same way (twice as far, to overlap the column), keep it half a clearance back from those
                    reach = boolean(reach, boolean(shrunk[x].translate(list(2.0 * clearance * n)),
                                                   shrunk[y].translate(list(-2.0 * clearance * n)), "intersection",
                                                   what), "intersection", what)
                    keep = boolean(keep, reach, "union", what)
        new = kept_bodies(boolean(body, keep, "intersection", what), len(body.decompose()), float(body.volume()),
                          SLIVER_SHARE)
        if new is None:
            warn(f"output.face_clearance: piece {pid} would come apart with its faces set back (a thin "
                 f"neck along a cut face); it keeps its faces, its neighbours their half of the gap")
            new = body
        taken += float(body.volume()) - float(new.volume())
        out[pid] = new
    return out, taken


def _contact_direction(a, b):
    """Mean unit normal (3,) of the patch where Manifolds a and b touch, from a into b, or None when they do not."""
    from .geometry import to_trimesh

    ma, mb = to_trimesh(a), to_trimesh(b)
    masks = _shared_faces([ma, mb])
    tri = masks.get((0, 1))
    if tri is None:
        return None
    n = (ma.face_normals[tri] * ma.area_faces[tri][:, None]).sum(axis=0)
    size = float(np.linalg.norm(n))
    return n / size if size > 0 else None


def compose_in_mesh(stages, joint_spec, tolerance, jobs, timer, progress, face_clearance=0.0, workers=None):
    """Mesh mode: cage pieces without joints, each intersected with the mesh, fragments merged, joints placed on the
    final contacts, the faces between pieces set back by half of face_clearance each (set_back_faces), then pins and
    holes. -> (list of compose.Piece, joints, AssemblyPlan or None, report dict; its "face_clearance_mm3" is the
    volume the clearance took). workers: the build's volpuzzle.workers.Workers, shared by the cage's compose."""
    from .compose import Piece, compose
    from .geometry import from_trimesh, solid_of, to_trimesh

    tiling, model = stages.tiling, stages.model
    with timer("compose", progress):
        bodies = compose(tiling, stages.fmap, [], tolerance, jobs=jobs, progress=progress.piece, workers=workers)
        # Meshes often have vertices and edges exactly on a cage's mid-plane (a symmetric part centred in its cage).
        # The engine then splits the two sides by a perturbation that leaves them pinched along those edges, and
        # merging them welds a non-manifold solid. A shift far below print resolution moves them off the cuts.
        solid = solid_of(model.mesh, "mesh model").translate(list(_NUDGE * float(np.max(model.mesh.extents))))
        cut = intersect_pieces({p.id: from_trimesh(p.mesh, p.id) for p in bodies}, solid)
        cut, merges = merge_fragments(cut)
    cells = {p.id: tuple(p.cell) for p in bodies}
    joints, records, plan = [], [], None
    with timer("joint", progress):
        if joint_spec is not None and joint_spec.style != "none":
            size = pin_size(joint_spec, model.mesh)
            joints, records, plan = place_joints(cut, cells, size)
            problem = joint_graph_problem(sorted(cut), joints, records)
            if problem and "loose" not in joint_spec.allow:
                raise GeometryError(problem)
    pieces = []
    taken = 0.0
    with timer("compose", progress):
        if face_clearance > 0:
            # the contacts, merges and joints above need the faces closed (they are found where pieces touch):
            # the faces are set back only now, before the pins and holes, which keep their own clearances
            shrunk = compose(tiling, stages.fmap, [], tolerance, jobs=jobs, face_clearance=face_clearance,
                             workers=workers)
            cut, taken = set_back_faces(cut, {p.id: from_trimesh(p.mesh, p.id) for p in bodies},
                                        {p.id: from_trimesh(p.mesh, p.id) for p in shrunk}, merges, face_clearance)
        jointed = add_joints(cut, cells, joints)
        for pid in sorted(cut, key=lambda k: cells[k]):
            mesh = to_trimesh(jointed[pid])
            pieces.append(Piece(pid, cells[pid], mesh, float(mesh.volume), float(cut[pid].volume()),
                                int(len(mesh.faces))))
    report = {"cells_without_piece": sorted(set(cells) - set(cut)), "merged": merges, "contacts": records,
              "contacts_touching": len(records), "contacts_with_room": sum(1 for r in records if r["room"]),
              "contacts_pinned": sum(1 for r in records if r["pinned"]), "face_clearance_mm3": taken}
    return pieces, joints, plan, report


def pin_size(joint_spec, mesh):
    """The wanted PinSize: the spec's radius and length, else about 2.5% of the model's largest side (1.2 to 4
    mm) and 2.5 radii long (at least 3 mm)."""
    from .joint import DEFAULT_AXIAL_CLEARANCE, DEFAULT_CLEARANCE

    side = float(np.max(mesh.extents))
    r = joint_spec.radius if joint_spec.radius is not None else float(np.clip(round(0.025 * side, 1), 1.2, 4.0))
    length = joint_spec.length if joint_spec.length is not None else float(np.clip(round(2.5 * r, 1), 3.0, 10.0))
    c = joint_spec.clearance if joint_spec.clearance is not None else DEFAULT_CLEARANCE
    ac = joint_spec.axial_clearance if joint_spec.axial_clearance is not None else DEFAULT_AXIAL_CLEARANCE
    lo_r, lo_l = float(joint_spec.min_radius), float(joint_spec.min_length)
    return PinSize(float(r), float(length), float(c), float(ac), joint_spec.shape or "cylinder",
                   joint_spec.style or "pin", min(lo_r, float(r)), min(lo_l, float(length)))


def _contact_normals(c):
    """Unit normals (k, 3) of a contact's triangles (out of c.a) and their areas (k,)."""
    t = c.triangles
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    size = np.linalg.norm(n, axis=1)
    keep = size > 1e-12
    return n[keep] / size[keep, None], 0.5 * size[keep]


EXACT_PLAN_PIECES = 8  # blocks up to this many pieces get the exact search over all their splits (3^n / 2 of them)


class _ExactPlan:
    """The split tree of a small block that pins the most contacts: every split (moving, fixed) of every sub-block is
    scored by the contacts across it whose mean normal lies within MAX_TILT_DEG of one sliding direction d (and no
    triangle across faces more than 120 deg against d), the best tree is found over all sub-blocks at once, then its
    splits are swept for real; a split that does not slide is banned and the tree found again, within the budget of
    sweeps. A heuristic split (plan_splits' candidates) pins only what the mean of all normals across it happens to
    suit: a knot's fragments give contacts on all three cut planes within one block."""

    def __init__(self, normals, scene, centre, slides):
        from .assembly import _DIRS

        self.keys = list(normals)
        self.ids = sorted({k for pair in self.keys for k in pair} | set(centre))
        where = {k: i for i, k in enumerate(self.ids)}
        self.ends = np.array([[where[a], where[b]] for a, b in self.keys], dtype=np.int64).reshape(-1, 2)
        means, self.areas = [], []
        for k in self.keys:
            n, w = normals[k]
            m = (n * w[:, None]).sum(axis=0)
            means.append(m / max(float(np.linalg.norm(m)), 1e-12))
            self.areas.append(float(w.sum()))
        self.areas = np.array(self.areas)
        means = np.array(means).reshape(-1, 3)
        self.means = means
        self.dirs = np.concatenate([_DIRS, means, -means])
        self.cosines = means @ self.dirs.T  # (contacts, directions)
        # per contact, the least and greatest n . d over its triangles for every direction (oriented a -> b), but for
        # the smallest that together hold a thousandth of its area: slivers where the mesh meets a cut face point
        # anywhere (0.005 mm^2 of a 1,667 mm^2 contact on the fandisk faced 164 deg off), and sweep no volume
        proj = []
        for k in self.keys:
            n, w = normals[k]
            order = np.argsort(w)
            keep = order[np.cumsum(w[order]) > 1e-3 * w.sum()]
            proj.append(n[keep] @ self.dirs.T)
        self.lo = np.array([p.min(axis=0) for p in proj]).reshape(len(self.keys), -1)
        self.hi = np.array([p.max(axis=0) for p in proj]).reshape(len(self.keys), -1)
        self.cos_tilt = float(np.cos(np.radians(MAX_TILT_DEG)))
        self.scene, self.centre, self.slides = scene, centre, slides
        self._split = {}
        self._failed = {}  # (block, moving) -> directions (3,) along which it was swept and did not slide

    def score(self, block, moving):
        """(pinnable contacts, their area, what `directions` needs or () when nothing crosses), or None when every
        direction meets a triangle across head on. block, moving: sets of ids."""
        key = (frozenset(block), frozenset(moving))
        if key in self._split:
            return self._split[key]
        inb = np.array([k in block for k in self.ids])
        mov = np.array([k in moving for k in self.ids])
        a, b = self.ends[:, 0], self.ends[:, 1]
        idx = np.flatnonzero(inb[a] & inb[b] & (mov[a] != mov[b]))
        if not len(idx):
            self._split[key] = (0, 0.0, ())
            return self._split[key]
        into = mov[b[idx]]  # the contact's normal (a -> b) points into the moving part
        sign = np.where(into, 1.0, -1.0)
        low = np.where(into[:, None], self.lo[idx], -self.hi[idx]).min(axis=0)
        means = self.means[idx] * sign[:, None]
        areas = self.areas[idx]
        within = (self.cosines[idx] * sign[:, None]) >= self.cos_tilt
        count = np.where(low > -0.5, within.sum(axis=0), -1)
        failed = self._failed.get(key)
        if failed:  # what did not slide, and its neighbours within 12 deg, make way for the next best
            count = np.where((self.dirs @ np.array(failed).T).max(axis=1) > np.cos(np.radians(12.0)), -1, count)
        if count.max() < 0:
            self._split[key] = None
            return None
        area = within.T.astype(float) @ areas
        ranked = np.lexsort((area, count))[::-1]
        best = int(ranked[0])
        self._split[key] = (int(count[best]), float(area[best]), (ranked, count, within, means, areas, low))
        return self._split[key]

    def directions(self, block, moving):
        """Up to 3 unit directions (3,) along which `moving` leaves `block` pinning as many contacts as score says,
        the most upright first; () when nothing crosses."""
        got = self.score(block, moving)
        if got is None or not got[2]:
            return ()
        ranked, count, within, means, areas, low = got[2]
        best = int(ranked[0])
        ds = []
        failed = np.array(self._failed.get((frozenset(block), frozenset(moving)), np.zeros((0, 3)))).reshape(-1, 3)
        # the centre of the pinned contacts' normals leaves every pin most upright, when it still holds them all;
        # then other directions that pin as many, should the first not slide
        for k in ranked[:8]:
            if count[k] != count[best] or len(ds) >= 3:
                break
            sel = within[:, k]
            d = self.dirs[k]
            if sel.any():
                m = (means[sel] * areas[sel, None]).sum(axis=0)
                m = m / max(float(np.linalg.norm(m)), 1e-12)
                # n . m >= n . e - |m - e| for the nearest listed direction e: a bound, not the triangles again
                near = int(np.argmax(self.dirs @ m))
                tri_low = float(low[near]) - float(np.linalg.norm(m - self.dirs[near]))
                if np.all(means[sel] @ m >= self.cos_tilt) and tri_low > -0.5:
                    d = m
            if all(float(d @ e) < 0.999 for e in ds) and not np.any(failed @ d > np.cos(np.radians(12.0))):
                ds.append(d)
        return tuple(ds)

    def free_direction(self, moving, fixed, budget):
        """A direction along which `moving`, touching `fixed` over no area, slides off it, or None."""
        from .assembly import _DIRS

        d0 = np.mean([self.centre[k] for k in moving], axis=0) - np.mean([self.centre[k] for k in fixed], axis=0)
        d0 = d0 / max(float(np.linalg.norm(d0)), 1e-12)
        for d in [d0] + [_DIRS[i] for i in np.argsort(-(_DIRS @ d0))[:11]]:
            if self.slides(moving, fixed, d, budget):
                return d
        return None

    def plan(self, block, budget):
        """[(moving, fixed, d), ...] taking `block` (sorted ids) apart, pre-order, or None."""
        ids = tuple(block)
        full = (1 << len(ids)) - 1
        banned, memo = set(), {}

        def members(mask):
            return frozenset(ids[i] for i in range(len(ids)) if mask >> i & 1)

        def best(mask):
            if mask in memo:
                return memo[mask]
            if mask & (mask - 1) == 0:
                memo[mask] = ((0, 0.0, 0), ())
                return memo[mask]
            low_bit = mask & -mask
            rest = mask & ~low_bit
            out = None
            sub = rest
            while True:  # every split: `fixed` holds the lowest piece, `moving` is a non-empty part of the rest
                mv = sub
                fx = mask & ~mv
                if mv and (mask, mv) not in banned:
                    sc = self.score(members(mask), members(mv))
                    if sc is not None:
                        a, b = best(fx), best(mv)
                        if a is not None and b is not None:
                            total = (sc[0] + a[0][0] + b[0][0], sc[1] + a[0][1] + b[0][1],
                                     min(bin(mv).count("1"), bin(fx).count("1")) + a[0][2] + b[0][2])
                            if out is None or total > out[0]:
                                out = (total, ((mask, mv),) + a[1] + b[1])
                if sub == 0:
                    break
                sub = (sub - 1) & rest
            memo[mask] = out
            return out

        for _ in range(4 * budget[0]):  # each round sweeps at least once or bans a split
            if budget[0] <= 0:
                return None
            got = best(full)
            if got is None:
                return None
            steps, failed = [], False
            for mask, mv in got[1]:
                moving, fixed = sorted(members(mv)), sorted(members(mask & ~mv))
                ds = self.directions(members(mask), members(mv))
                crosses = bool(self.score(members(mask), members(mv))[2])
                if crosses and not ds:
                    d = None
                elif ds:
                    d = next((d for d in ds if self.slides(moving, fixed, d, budget)), None)
                else:
                    d = self.free_direction(moving, fixed, budget)
                if d is None:
                    if ds:  # the split may still slide another way, pinning fewer
                        key = (members(mask), members(mv))
                        self._failed.setdefault(key, []).extend(ds)
                        self._split.pop(key, None)
                    else:
                        banned.add((mask, mv))
                    for m in [m for m in memo if m & mask == mask]:  # only the blocks holding this one change
                        del memo[m]
                    failed = True
                    break
                steps.append((moving, fixed, d))
            if not failed:
                return steps
        return None


def plan_splits(meshes, found, cells, fine=0.75, max_sweeps=4):
    """The plan of splits on the final pieces' contact graph -> (assembly.AssemblyPlan, {(a, b): unit (3,) along
    which b leaves a}).

    A block of pieces is cut in two and the moving part leaves along a direction d that as many contacts across as
    possible stand within MAX_TILT_DEG of (each takes a pin along d), with no triangle across facing more than 120
    deg against d (it would block the slide at once). A block of up to EXACT_PLAN_PIECES pieces takes the best of
    all its split trees (_ExactPlan); a larger one is cut between its pieces sorted along each contact's normal and
    the three axes, the cut losing the fewest pins first, then the most even, and its halves planned again. A split
    counts only when its block really slides off, swept every `fine` mm as assembly.verify_disassembly does.
    meshes: {id: trimesh}; found: contacts(meshes); cells: {id: cell index}. Every Step records its d as `slide`.
    """
    from .assembly import AssemblyPlan, Step, _Scene

    scene = _Scene(meshes)
    centre = {k: np.asarray(m.centroid, float) for k, m in meshes.items()}
    normals = {(c.a, c.b): _contact_normals(c) for c in found}

    def parts(block):
        import networkx as nx

        g = nx.Graph()
        g.add_nodes_from(block)
        g.add_edges_from(k for k in normals if k[0] in block and k[1] in block)
        return sorted((sorted(p) for p in nx.connected_components(g)), key=lambda p: (-len(p), p))

    def crossing(block, moving):
        """Normals (k, 3) and areas (k,) of the contacts across, facing from the fixed part into the moving one."""
        ns, ws, pairs = [], [], []
        for (a, b), (n, w) in normals.items():
            if a in block and b in block and ((a in moving) != (b in moving)):
                ns.append(n if b in moving else -n)
                ws.append(w)
                pairs.append((a, b))
        return ns, ws, pairs

    def unit(d):
        return d / max(float(np.linalg.norm(d)), 1e-12)

    def candidates(block):
        """(moving, fixed, d) splits of a block, the most promising first."""
        comps = parts(block)
        if len(comps) > 1:  # pieces that only touch at edges or points part freely
            moving = comps[-1]
            fixed = [k for k in block if k not in moving]
            return [(moving, fixed, unit(np.mean([centre[k] for k in moving], axis=0)
                                         - np.mean([centre[k] for k in fixed], axis=0)))]
        axes = [np.eye(3)[k] for k in range(3)]
        for k, (n, w) in normals.items():
            if k[0] in block and k[1] in block:
                axes.append(unit((n * w[:, None]).sum(axis=0)))
        cands, seen = [], set()
        for ax in axes:
            order = sorted(block, key=lambda k: (float(centre[k] @ ax), k))
            for cut in range(1, len(order)):
                moving = frozenset(order[cut:])
                if moving in seen or frozenset(order[:cut]) in seen:
                    continue
                seen.add(moving)
                ns, ws, _ = crossing(block, moving)
                if not ns:
                    continue
                # the direction that leaves the most contacts across within the pins' tilt, so each can take a
                # pin along it (a triangle facing head on against it blocks at once; gentler ones the sweep judges)
                got = exact.score(block, moving)
                if got is None or not got[2]:
                    continue
                key = (got[0] - len(ns), min(cut, len(order) - cut), got[1])
                cands.append((key, sorted(moving), sorted(order[:cut]), block, moving))
        cands.sort(key=lambda c: c[0], reverse=True)
        return [(m, f, exact.directions(b, mv)[0]) for _, m, f, b, mv in cands[:max_sweeps]]

    # each sweep costs Booleans on the whole pieces: a few per piece in all
    budget = [2 * len(meshes) + 4]

    swept = {}

    def slides(moving, fixed, d, budget=budget):
        # the contacts say nothing of parts that hook round each other away from them (a knot): sweep for real
        key = (tuple(moving), tuple(fixed), tuple(np.round(d, 9)))
        if key not in swept:
            budget[0] -= 1
            swept[key] = scene.sweep_clear(moving, fixed, d, fine, 1e-4)[0]
        return swept[key]

    exact = _ExactPlan(normals, scene, centre, slides)

    def split(block, strict=True):
        """[(moving, fixed, d), ...] taking the block apart, or None when strict and no order of splits found
        within the budget slides (a split whose halves cannot be taken apart further is given up for the next)."""
        if len(block) == 1:
            return []
        if strict and len(block) <= EXACT_PLAN_PIECES:
            got = exact.plan(sorted(block), [3 * len(block) + 6])
            if got is not None:
                return got
        cands = candidates(set(block))
        for moving, fixed, d in cands[:max_sweeps]:
            if budget[0] <= 0 or not slides(moving, fixed, d):
                continue
            lo = split(fixed)
            hi = split(moving) if lo is not None else None
            if lo is not None and hi is not None:
                return [(moving, fixed, d)] + lo + hi
        if strict:
            return None
        # nothing slides: the best split on contacts alone, so the plan is complete; the replay will name the pieces
        if cands:
            moving, fixed, d = cands[0]
        else:
            k = sorted(block)[-1]
            moving, fixed = [k], [x for x in block if x != k]
            d = unit(centre[k] - np.mean([centre[x] for x in fixed], axis=0))
        return [(moving, fixed, d)] + split(fixed, False) + split(moving, False)

    blocks = split(sorted(meshes))
    if blocks is None:
        budget[0] = len(meshes)
        blocks = split(sorted(meshes), strict=False)
    steps, dir_of = [], {}
    for moving, fixed, d in blocks:
        _, _, pairs = crossing(set(moving) | set(fixed), set(moving))
        for a, b in pairs:
            dir_of[(a, b)] = d if b in moving else -d
        axis = int(np.argmax(np.abs(d)))
        steps.append(Step(tuple(sorted(tuple(cells[k]) for k in moving)), tuple(sorted(tuple(cells[k]) for k in fixed)),
                          axis, 1 if d[axis] >= 0 else -1, (), slide=tuple(float(x) for x in d)))
    order = tuple(sorted(tuple(cells[k]) for k in meshes))
    return AssemblyPlan((), tuple(steps), order), dir_of
