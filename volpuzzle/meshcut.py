"""Mesh mode clean-up (paper section 5): cage pieces intersected with the mesh Mp, fragments merged, joints kept
inside the mesh.

Recommended order in the pipeline: build the cage pieces WITHOUT pins and holes, intersect_pieces, merge_fragments,
then keep_joints_inside(joints of the surviving pieces), and only then add pins and cut holes into the merged pieces.
Intersecting after the pins would clip a pin where the mesh is thin and leave a half hole open to the outside, and a
fragment handed to a neighbour could carry half a joint with it.
"""

from dataclasses import replace

import numpy as np

from .errors import GeometryError

__all__ = ["intersect_pieces", "merge_fragments", "keep_joints_inside"]


def _check(m, what, step):
    import manifold3d

    status = m.status()
    if status != manifold3d.Error.NoError:
        raise GeometryError(f"{what}: the geometry engine failed at {step} (status {status.name})")
    return m


def intersect_pieces(pieces_bodies, mesh_manifold, min_volume=1e-9):
    """{id: Manifold} cage pieces (mm) and the mesh as a Manifold -> {id: body ∩ mesh}. A cell that misses the mesh
    (empty or below min_volume mm^3) gives no piece."""
    _check(mesh_manifold, "mesh model", "the mesh solid")
    out = {}
    for pid, body in pieces_bodies.items():
        _check(body, pid, "the cage piece")
        cut = _check(body ^ mesh_manifold, pid, "intersecting the piece with the mesh")
        if not cut.is_empty() and cut.volume() > min_volume:
            out[pid] = cut
    return out


def _touch(frag, other, grow):
    """Volume of `other` within `grow` mm of `frag`: frag's thin shell, approximated by the union of frag shifted
    by +-grow along x, y, z (manifold3d has no offset), intersected with other."""
    lo1, hi1 = np.asarray(frag.bounding_box()).reshape(2, 3)
    lo2, hi2 = np.asarray(other.bounding_box()).reshape(2, 3)
    if np.any(lo1 - grow > hi2) or np.any(lo2 > hi1 + grow):
        return 0.0
    total = 0.0
    for k in range(3):
        for s in (-grow, grow):
            d = [0.0, 0.0, 0.0]
            d[k] = s
            inter = frag.translate(d) ^ other
            if inter.status().name == "NoError" and not inter.is_empty():
                total += inter.volume()
    return total


def merge_fragments(pieces, min_fraction=0.05, grow=None):
    """{id: Manifold} -> ({id: Manifold}, merge records). A piece that falls apart keeps its largest body and gives
    every other body to the neighbour it touches most; a piece under min_fraction of the mean volume is given away
    whole the same way. Total volume is kept; ids stay the cells'. A part that touches nobody -> GeometryError.

    Records: {"from": id, "to": id, "volume_mm3": v, "reason": "fragment" | "small piece"}.
    grow: how far (mm) a part reaches to find its neighbours; default 0.2% of the model's size.
    """
    pieces = dict(pieces)
    if not pieces:
        return {}, []
    if grow is None:
        lo = np.min([np.asarray(p.bounding_box())[:3] for p in pieces.values()], axis=0)
        hi = np.max([np.asarray(p.bounding_box())[3:] for p in pieces.values()], axis=0)
        grow = max(1e-3, 2e-3 * float(np.max(hi - lo)))
    records = []
    loose = []  # (from id, body, reason)
    for pid in sorted(pieces):
        bodies = pieces[pid].decompose()
        if len(bodies) <= 1:
            continue
        bodies = sorted(bodies, key=lambda b: -b.volume())
        pieces[pid] = bodies[0]
        loose += [(pid, b, "fragment") for b in bodies[1:]]
    from .check import closed_problem
    from .geometry import to_trimesh

    def give_away(src, body, reason):
        scores = {pid: _touch(body, other, grow) for pid, other in pieces.items() if pid != src}
        ranked = sorted((k for k in scores if scores[k] > 0), key=lambda k: (-scores[k], k))
        if not ranked:
            raise GeometryError(
                f"{src}: a {reason} of {body.volume():.4g} mm^3 touches no other piece, so it cannot be merged "
                "(the mesh has a part that lies in one cell alone; use a finer grid or model.repair)")
        for best in ranked:
            merged = _check(pieces[best] + body, best, f"merging a {reason} of {src}")
            # A part that meets this neighbour only along an edge or at a point (all cells of a sphere cage meet at
            # its centre) would weld into a non-manifold solid no slicer accepts: try the next neighbour.
            if len(merged.decompose()) == 1 and closed_problem(to_trimesh(merged)) is None:
                break
        else:
            if reason == "small piece":
                # Small but whole: better printed on its own than welded into a solid no slicer accepts.
                pieces[src] = body
                records.append({"from": src, "to": None, "volume_mm3": float(body.volume()),
                                "reason": "small piece kept: it meets its neighbours only along an edge or a point"})
                return False
            raise GeometryError(
                f"{src}: a {reason} of {body.volume():.4g} mm^3 meets its neighbours ({', '.join(ranked)}) only along "
                "an edge or at a point, so merging it would not give one closed solid (use a different grid or cage)")
        pieces[best] = merged
        records.append({"from": src, "to": best, "volume_mm3": float(body.volume()), "reason": reason})
        return True

    for src, body, reason in loose:
        give_away(src, body, reason)
    # Pieces too small to print on their own go whole, the smallest first and one at a time, so that a small piece
    # still finds its face neighbours (which may be small too, and grow by taking it).
    mean = sum(p.volume() for p in pieces.values()) / len(pieces)
    kept = set()
    while len(pieces) > 1:
        small = [k for k in pieces if k not in kept and pieces[k].volume() < min_fraction * mean]
        if not small:
            break
        pid = min(small, key=lambda k: (pieces[k].volume(), k))
        if not give_away(pid, pieces.pop(pid), "small piece"):
            kept.add(pid)
    return pieces, records


# --- joints ---------------------------------------------------------------------------------------------------------
def _frame(direction):
    n = np.asarray(direction, float)
    n = n / np.linalg.norm(n)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(helper, n)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1), n


def _joint_reach(j):
    """(radius, back, front) of everything a joint puts into its pieces: the hole with its clearance reaches
    length + axial clearance into the hole piece, the pin's base reaches base_depth back into the pin piece."""
    swell = 1.15 if getattr(j, "shape", "cylinder") == "snap" else 1.0
    r = j.radius * swell + j.clearance
    back = max(float(getattr(j, "base_depth", 0.0) or 0.0), 0.0)
    front = j.length + j.axial_clearance
    return r, back, front


def _envelope(center, direction, r, back, front, segments=24):
    """The joint's room as a Manifold cylinder from `back` behind the face to `front` in front of it (mm)."""
    import manifold3d

    e1, e2, n = _frame(direction)
    m = np.zeros((3, 4))
    m[:, 0], m[:, 1], m[:, 2], m[:, 3] = e1, e2, n, center
    cyl = manifold3d.Manifold.cylinder(back + front, r, -1.0, segments).translate([0.0, 0.0, -back])
    return _check(cyl.transform(m), "joint", "the joint's envelope")


def _fits(solid, center, direction, r, back, front, wall):
    """True when the joint's room grown by `wall` lies inside `solid` (a Manifold): nothing of it is left over
    after subtracting the solid. Exact up to the polygon, and needs no ray tests."""
    env = _envelope(center, direction, r + wall, back + wall, front + wall)
    rest = env - solid
    return rest.is_empty() or rest.volume() <= 1e-6 * env.volume()


def keep_joints_inside(joints, mesh, wall=1.5, max_shift=None, steps=6):
    """Joints whose pin or hole would break through the mesh's surface (deep cavities, the paper's Fig. 15) are moved
    along their face until they are inside with `wall` mm around them, or dropped.

    joints: iterable of joint.Joint (mm); mesh: the closed trimesh (or its Manifold) in mm. -> (kept joints, records) with records
    {"pin_piece", "hole_piece", "action": "kept"|"moved"|"dropped", "distance": mm moved}; only moved and dropped
    joints are recorded. max_shift: farthest move in mm (default 3 joint radii).
    """
    import manifold3d

    from .geometry import from_trimesh
    from .joint import piece_id

    solid = mesh if isinstance(mesh, manifold3d.Manifold) else from_trimesh(mesh, "mesh model")
    kept, records = [], []
    for j in joints:
        r, back, front = _joint_reach(j)
        c0 = np.asarray(j.center, float)
        d = np.asarray(j.direction, float)
        limit = float(max_shift) if max_shift is not None else 3.0 * (r + wall)
        # every trial below meets only the mesh near this joint: cut it out once
        reach = limit + r + wall + max(back, front) + wall
        local = solid ^ manifold3d.Manifold.cube([2 * reach] * 3, True).translate(c0)
        if _fits(local, c0, d, r, back, front, wall):
            kept.append(j)
            continue
        e1, e2, _ = _frame(d)
        found = None
        # rings of candidate centres on the face plane, nearest first
        for k in range(1, steps + 1):
            dist = limit * k / steps
            n_ang = max(8, int(np.ceil(2 * np.pi * k)))
            for a in np.linspace(0, 2 * np.pi, n_ang, endpoint=False):
                c = c0 + dist * (np.cos(a) * e1 + np.sin(a) * e2)
                if _fits(local, c, d, r, back, front, wall):
                    found = (c, dist)
                    break
            if found:
                break
        rec = {"pin_piece": piece_id(j.pin_cell), "hole_piece": piece_id(j.hole_cell)}
        if found:
            kept.append(replace(j, center=found[0]))
            records.append({**rec, "action": "moved", "distance": float(found[1])})
        else:
            records.append({**rec, "action": "dropped", "distance": 0.0})
    return kept, records
