"""assembly: the order in which the pieces come apart (and go together), and its replay on the real meshes.

Why groups and not single pieces. A straight pin lets its two pieces part only along its axis, and once R has made the
cut faces bumpy a piece cannot slide along a face it shares with a neighbour either: it can only move away from every
neighbour still present. If every step removed ONE piece, a piece with a joint to the rest would have to have exactly
one neighbour left at its removal (the one the joint goes to, behind it), so every face of the grid would be counted by
exactly one removal with one neighbour, and the grid's face graph would need n - 1 edges: it would have to be a tree.
Any grid with a cycle (2 x 2 x 1 and up) then has pieces without any joint, which simply fall out.

So the plan is a binary tree of splits instead (as a burr puzzle is built): the current block of cells is cut by one
grid plane into two blocks, and the upper block leaves the lower one along the plane's axis. Every face crossing the
split is normal to that axis in parameter space; in mm the block slides along the split's mean normal
(split_directions), and volpuzzle.joint.place_joints points every pin of the split that way, on every crossing face
with room. The plan also names, per split, the face that best holds it (the widest, plus those parallel to it within
`max_angle_deg`): placed first, they keep the joint graph connected. with_joints records what was placed. Assembled,
each step joins one finished block onto another: a single piece is a block of one.

Pins always sit on the face's lower cell: pulling the upper block off the lower one pulls the hole off the pin, and
each cell keeps at most one pin per max face and one hole per min face, three of each at most.

Which plane cuts a block. Without more to go on, the middle of its longest axis. Given what a face can hold (holds,
from volpuzzle.joint), plan_assembly keeps that plain plan only when every split's faces hold a pin along its
direction; else _PlanSearch picks, block by block, the cuts whose whole tree of splits leaves the fewest faces without
one: on a curved shell, cutting round a ring before across it keeps each split's faces within a few degrees of its
direction (the duck went from 50 to 54 of its 56 contacts pinned).

A periodic axis is a closed ring with no outer side. It is cut first, into two halves at the face opposite the seam:
the halves part across both cuts at once (a torus halved through its axis: its pins cross the middle face and the
seam, all parallel). An odd ring count still halves, one half a cell longer. After that the halves are open blocks.

verify_disassembly replays the plan on the real meshes: each block is swept along the mean direction of its joints to
the other block, and manifold3d's intersection volume with every piece of the other block must stay below a tiny
fraction of the piece volume (a sample at which the hulls of the two pieces' slabs are apart, or their surfaces do
not meet while neither box holds the other, needs no Boolean). A failed split is replaced by any other plane split
(or single piece) that works; a block with none is welded and its pieces are named, with the grid at which no piece
turns more than a half turn (bend_grid) when that is another.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .errors import GeometryError
from .geometry import boxes_nested, is_ok, kernel_arrays
from .grid import AXES, piece_id
from .joint import joint_graph, joints_by_cell
from .progress import warn

DEFAULT_MAX_ANGLE_DEG = 1.0  # pins of a split within this of each other still slide together (2 asin(c / L) ~ 2.9 deg)


@dataclass(frozen=True)
class Step:
    """One disassembly step: the cells `moving` leave the cells `fixed` along sign * axis (parameter space).

    moving and fixed together are the block present at that moment (other blocks were taken apart separately);
    joints: face numbers (into tiling.faces) crossing the split that carry a joint; ring_cut: the split also cuts a
    periodic seam, so the two halves part across two faces at once; slide: the mm direction (3,) in which moving
    leaves when the plan chose it (mesh mode, and the volume plan search: the pins point along it), the way the
    replay takes a split that no joint crosses.
    """

    moving: tuple
    fixed: tuple
    axis: int
    sign: int
    joints: tuple
    ring_cut: bool = False
    slide: tuple | None = None

    @property
    def direction(self):
        """'+u' .. '-w': how `moving` leaves (disassembly)."""
        return ("+" if self.sign > 0 else "-") + AXES[self.axis]


@dataclass(frozen=True)
class AssemblyPlan:
    """faces_with_joints: ((face number in tiling.faces, pin_side 'lower' | 'upper'), ...); steps: Step tuple in
    DISASSEMBLY order (reversed, it is the assembly: each block built before it is joined); assembly_order: cell
    indices in the order they are first placed."""

    faces_with_joints: tuple
    steps: tuple
    assembly_order: tuple

    @property
    def order(self):
        """(moving cells, axis, sign) per disassembly step."""
        return [(s.moving, s.axis, s.sign) for s in self.steps]


# ---------------------------------------------------------------------------------------------------------------------
# Planning in parameter space


def _face_key(f):
    return (int(f.axis), tuple(f.lower), tuple(f.upper), f.seam is not None)


def _face_normals(tiling, fmap, numbers):
    """Unit mm normals (k, 3) at the centres of the given faces (along +axis of the lower cell) and their areas (k,)."""
    if fmap is None or not numbers:
        return None, None
    uvw, dpar = [], []
    for n in numbers:
        f = tiling.faces[n]
        box = tiling.cells[f.lower].box
        p = box.mean(axis=0)
        p[f.axis] = box[1, f.axis]
        uvw.append(p)
        b, c = [x for x in range(3) if x != f.axis]
        dpar.append((box[1, b] - box[0, b]) * (box[1, c] - box[0, c]))
    _, jac = fmap.evaluate_with_jacobian(np.array(uvw))
    out, area = [], []
    orient = int(getattr(fmap, "orientation", 1) or 1)
    for n, j, dp in zip(numbers, jac, dpar, strict=True):
        a = tiling.faces[n].axis
        b, c = (a + 1) % 3, (a + 2) % 3
        nrm = np.cross(j[:, b], j[:, c])
        det = float(np.dot(j[:, a], nrm))
        s = np.sign(det) if abs(det) > 1e-12 else orient
        size = float(np.linalg.norm(nrm))
        out.append(s * nrm / size if size > 1e-12 else np.zeros(3))
        area.append(size * dp)
    return np.array(out), np.array(area)


SEARCH_CELLS = 64  # tilings up to this many cells get the plan search (holds)
TURN_FACES = 4  # a split of at most this many faces may turn its pins off its mean normal to hold more of them
MAX_TURN_DEG = 20.0  # how far: within the 30 deg a pin may lean, so that the mean normal's own faces still can
SEARCH_SPLITS = 400  # the search tries every plane when blocks x planes are at most this many, else middle cuts


def plan_assembly(tiling, fmap=None, max_angle_deg=DEFAULT_MAX_ANGLE_DEG, holds=None):
    """The tree of splits and the faces that carry joints -> AssemblyPlan.

    fmap (optional, volpuzzle.mapping.Map or anything with evaluate_with_jacobian): used to pick the widest crossing
    face for a split's joint and to add joints on crossing faces whose normals are within max_angle_deg of it.
    holds (optional, with fmap): holds(face number, unit mm direction (3,) from its lower cell to its upper one) ->
    whether that face holds a pin along it (volpuzzle.joint). Where the plain plan (each block cut at the middle of
    its longest axis) leaves a face that cannot hold a pin along its split's sliding direction, and the tiling has at
    most SEARCH_CELLS cells, each block is cut where its whole tree of splits leaves the fewest such faces instead
    (_PlanSearch), and each step records its direction as slide.
    """
    grid = tiling.grid
    faces = list(tiling.faces)
    by_cells = {}
    for n, f in enumerate(faces):
        by_cells.setdefault(frozenset((tuple(f.lower), tuple(f.upper))), []).append(n)
    cos_max = np.cos(np.radians(max_angle_deg))
    jointed = []
    steps = []  # built as assembly (post-order), reversed at the end

    def crossing(moving, fixed):
        return [n for n, _ in parted_faces(tiling, moving, fixed)]

    def choose(cands, axis, lo_cells, moving=(), prefer_seam=False):
        """Faces (numbers) of one split that get a joint: the best one, plus parallel ones when F is known.
        Normals are compared as seen from the fixed block (a seam face has the moving block on its lower side)."""
        if not cands:
            return []
        mids = []
        for n in cands:
            f = faces[n]
            c = np.array(f.lower, float)
            others = [x for x in range(3) if x != axis]
            mids.append(sum(abs(c[x] - lo_cells[x]) for x in others))
        normals, area = _face_normals(tiling, fmap, cands)
        if normals is None:
            key = [(-(prefer_seam and faces[n].seam is not None), m) for n, m in zip(cands, mids, strict=True)]
            best = min(range(len(cands)), key=lambda k: key[k])
            return [cands[best]]
        mv = set(moving)
        flip = np.array([-1.0 if tuple(faces[n].lower) in mv else 1.0 for n in cands])
        normals = normals * flip[:, None]
        # the widest face, ties to the middle: a collapsed face (a pole) cannot hold a pin. On a ring the seam is
        # preferred, so that the joints cross it as the paper's periodic puzzles do.
        seam = np.array([faces[n].seam is not None for n in cands], float)
        score = area / max(float(area.max()), 1e-300) - 1e-3 * np.array(mids) + (0.5 * seam if prefer_seam else 0.0)
        best = int(np.argmax(score))
        ok = [n for k, n in enumerate(cands)
              if area[k] > 0.25 * area[best] and float(normals[k] @ normals[best]) >= cos_max]
        return sorted(set(ok) | {cands[best]})

    def longest(cells):
        """The axis a block is cut across without a search: the most cells, then the longest in mm."""
        idx = np.array(cells)
        spans = [len(np.unique(idx[:, x])) for x in range(3)]
        if fmap is not None:
            # physical length of the block along each axis breaks ties between equal counts
            c = tiling.cells[tuple(cells[0])].box.mean(axis=0)
            _, jac = fmap.evaluate_with_jacobian(c[None])
            lo = np.array([tiling.breaks[x][idx[:, x].min()] for x in range(3)])
            hi = np.array([tiling.breaks[x][idx[:, x].max() + 1] for x in range(3)])
            size = np.linalg.norm(jac[0], axis=0) * (hi - lo)
        else:
            size = np.array([0.0, 1e-9, 2e-9])  # w, then v, then u
        return max(range(3), key=lambda x: (spans[x], size[x]))

    def split(cells, open_axes):
        """Assembly steps for the block `cells` (a list of indices); open_axes: periodic axes already cut."""
        if len(cells) == 1:
            return
        idx = np.array(cells)
        ring = [a for a in tiling.periodic if a not in open_axes and grid[a] > 1
                and len(np.unique(idx[:, a])) == grid[a]]
        if ring:
            a = max(ring, key=lambda x: grid[x])
            p = grid[a] // 2
            fixed = [c for c in cells if c[a] < p]
            moving = [c for c in cells if c[a] >= p]
            cand = [n for n in crossing(moving, fixed) if faces[n].axis == a]
            mid_lo = [float(np.mean(idx[:, x])) for x in range(3)]
            chosen = choose(cand, a, mid_lo, moving, prefer_seam=True)
            jointed.extend(chosen)
            split(fixed, open_axes | {a})
            split(moving, open_axes | {a})
            steps.append(Step(tuple(sorted(moving)), tuple(sorted(fixed)), a, +1, tuple(chosen), True))
            return
        if search is not None:
            a, p = search.cut(cells)
            fixed, moving = [c for c in cells if c[a] < p], [c for c in cells if c[a] >= p]
        else:
            a = longest(cells)
            fixed, moving = _halves(cells, a)
        cand = [n for n in crossing(moving, fixed) if faces[n].seam is None]
        mid_lo = [float(np.mean(idx[:, x])) for x in range(3)]
        chosen = choose(cand, a, mid_lo)
        jointed.extend(chosen)
        split(fixed, open_axes)
        split(moving, open_axes)
        slide = search.slide(moving, fixed) if search is not None else None
        steps.append(Step(tuple(sorted(moving)), tuple(sorted(fixed)), a, +1, tuple(chosen), False,
                          None if slide is None else tuple(float(x) for x in slide)))

    cells = sorted(tiling.cells)
    search = None
    split(cells, frozenset())
    if holds is not None and fmap is not None and len(cells) <= SEARCH_CELLS:
        # the plain plan stands where each of its splits' faces holds a pin along it; else the search replaces it
        search = _PlanSearch(tiling, fmap, holds, longest)
        if any(search.lost(s.moving, s.fixed, turn=False)[0] for s in steps if not s.ring_cut):
            jointed.clear()
            steps.clear()
            split(cells, frozenset())
    order = []
    # placement order: the fixed block first, then the moving one, recursively
    tree = {frozenset(s.moving) | frozenset(s.fixed): s for s in steps}

    def walk(block):
        s = tree.get(frozenset(block))
        if s is None:
            order.extend(sorted(block))
            return
        walk(s.fixed)
        walk(s.moving)

    walk(cells)
    faces_with_joints = tuple((n, "lower") for n in sorted(set(jointed)))
    return AssemblyPlan(faces_with_joints, tuple(reversed(steps)), tuple(order))


class _PlanSearch:
    """Where each open block of a tiling is cut (an axis and a grid plane across it), so that the whole tree of
    splits below it leaves the fewest faces unable to hold a pin along their split's sliding direction (the
    area-weighted mean normal of the split's whole surface, as split_directions gives it); among equals the most
    even cuts, then the plan without a search (the middle of the longest axis) as often as it can.

    A split's direction suits the faces near its middle; on a curved block, the faces at its ends lean by up to the
    block's bend (the duck's half ring, cut across u, leaned 24 deg off its end faces). Cutting the other way first
    leaves smaller blocks, whose splits bend less. Blocks are memoized, each scored once per cut: every plane is
    tried while the sub-blocks are few (SEARCH_SPLITS), else only the middle one of each axis."""

    def __init__(self, tiling, fmap, holds, longest, k=7):
        self.tiling, self.holds, self.longest = tiling, holds, longest
        self.faces = list(tiling.faces)
        self._normals = _face_normal_grids(tiling, fmap, range(len(self.faces)), k)
        self._by_cell = {}
        for n, f in enumerate(self.faces):
            self._by_cell.setdefault(tuple(f.lower), []).append(n)
        self._memo, self._lost = {}, {}
        counts = [int(x) for x in tiling.grid]
        boxes = int(np.prod([n * (n + 1) // 2 for n in counts]))
        self.every_plane = boxes * sum(n - 1 for n in counts) <= SEARCH_SPLITS

    def lost(self, moving, fixed, turn=True):
        """(faces across the split that cannot hold a pin along its sliding direction, that direction (3,) from fixed
        to moving or None). The direction is the mean normal of the split's surface; where that loses a face of a
        split of at most TURN_FACES faces, the directions within MAX_TURN_DEG of it that keep every normal of the
        surface ahead (the block still leaves without touching) are tried, and the one holding the most wins (turn
        False: the mean normal only)."""
        key = (frozenset(moving), frozenset(fixed), turn)
        if key in self._lost:
            return self._lost[key]
        mv, fx = set(moving), set(fixed)
        across, normals = [], []
        for c in list(mv) + list(fx):
            for n in self._by_cell.get(c, ()):
                up = tuple(self.faces[n].upper)
                if (c in mv and up in fx) or (c in fx and up in mv):
                    sign = 1.0 if up in mv else -1.0
                    across.append((n, sign))
                    normals.append(sign * self._normals[n])
        d = leave_direction(np.concatenate(normals)) if normals else None
        if d is None:
            self._lost[key] = (len(across), None)
            return self._lost[key]

        held = [self.holds(n, sign * d) for n, sign in across]
        out = (held.count(False), d)
        if out[0] and turn and len(across) <= TURN_FACES:
            unit = np.concatenate(normals)
            unit = unit / np.maximum(np.linalg.norm(unit, axis=1), 1e-300)[:, None]
            faces = [m.sum(axis=0) / max(float(np.linalg.norm(m.sum(axis=0))), 1e-300) for m in normals]
            # the faces the mean normal loses are tried first: a direction holding none of them cannot do better
            order = sorted(range(len(across)), key=lambda i: held[i])
            for e in sorted(list(_cap(d, MAX_TURN_DEG)) + faces, key=lambda e: -float(e @ d)):
                if float((unit @ e).min()) <= 0.0 or float(e @ d) < np.cos(np.radians(MAX_TURN_DEG)) - 1e-9:
                    continue
                got = 0
                for i in order:  # stops as soon as it cannot beat the best so far
                    n, sign = across[i]
                    got += not self.holds(n, sign * e)
                    if got >= out[0]:
                        break
                if got < out[0]:
                    out = (got, e)
                    if got == 0:
                        break
        self._lost[key] = out
        return out

    def best(self, cells):
        """((faces lost, uneven cells, cuts off the plain plan) of the block's best tree, (axis, plane)), the plane
        being the least index of the moving part along axis; axis -1 for a single cell."""
        key = frozenset(cells)
        if key in self._memo:
            return self._memo[key]
        idx = np.array(cells)
        out = None
        default = None
        for a in range(3):
            vals = np.unique(idx[:, a])
            if len(vals) < 2:
                continue
            if default is None:
                default = self.longest(cells)
                plain = np.unique(idx[:, default])
                plain = (default, int(plain[len(plain) // 2]))
            for p in (vals[1:] if self.every_plane else [vals[len(vals) // 2]]):
                fixed = [c for c in cells if c[a] < p]
                moving = [c for c in cells if c[a] >= p]
                lo, hi = self.best(fixed)[0], self.best(moving)[0]
                cut = (a, int(p))
                cost = (self.lost(moving, fixed)[0] + lo[0] + hi[0], abs(len(moving) - len(fixed)) + lo[1] + hi[1],
                        int(cut != plain) + lo[2] + hi[2])
                if out is None or cost < out[0]:
                    out = (cost, cut)
        self._memo[key] = out if out is not None else ((0, 0, 0), (-1, 0))
        return self._memo[key]

    def cut(self, cells):
        """(axis, plane) to cut the block across: cells with index >= plane along axis move."""
        return self.best(sorted(tuple(c) for c in cells))[1]

    def slide(self, moving, fixed):
        """The direction (3,) from fixed to moving that the split's pins point along, or None."""
        return self.lost(moving, fixed)[1]


def leave_direction(normals):
    """The unit direction (3,) in which a block leaves a split whose surface has the area-weighted normals (m, 3)
    (from fixed to moving), or None when they cancel out: their mean, which bumps cannot tilt the way they tilt the
    normal at one point, unless some of the surface then faces away from it (min dot <= 0, so the block would drag
    through the other one). Then the direction that keeps the whole surface furthest ahead (the largest least
    cosine to its normals) instead: a half pipe bent along its length, halved through its bend, has a mean normal
    that leans toward the outside of the bend (more area there) and drives the inner half through the outer one's
    rims, while straight out of the trough (its plane of symmetry) every normal is ahead."""
    normals = np.asarray(normals, float)
    total = normals.sum(axis=0)
    size = float(np.linalg.norm(total))
    if size < 1e-12:
        return None
    d = total / size
    lengths = np.linalg.norm(normals, axis=1)
    unit = normals[lengths > 1e-12] / lengths[lengths > 1e-12, None]
    if float((unit @ d).min()) > 0.0:
        return d
    # the largest least cosine: a coarse search over the sphere, then caps ever smaller round the best (the least
    # cosine is concave over the cap where it is positive, so the refinement converges to its one maximum)
    cands = np.concatenate([_directions(2048), d[None]])
    best = cands[int(np.argmax((cands @ unit.T).min(axis=1)))]
    angle = 4.0
    for _ in range(12):
        cands = np.concatenate([_cap(best, angle), best[None]])
        best = cands[int(np.argmax((cands @ unit.T).min(axis=1)))]
        best = best / np.linalg.norm(best)
        angle *= 0.5
    return best if float((unit @ best).min()) > float((unit @ d).min()) else d


def _cap(d, angle_deg, count=48):
    """count unit vectors (count, 3) spread evenly over the cap of half-angle angle_deg round the unit d."""
    i = np.arange(count) + 0.5
    z = 1.0 - (1.0 - np.cos(np.radians(angle_deg))) * i / count
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    local = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    e1 = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    return local @ np.array([e1, e2, d])


def joint_faces(tiling, plan):
    """[(Face, pin_side)] of the plan: what the joint stage should build."""
    return [(tiling.faces[n], side) for n, side in plan.faces_with_joints]


def with_joints(plan, tiling, joints):
    """The plan with the faces that carry the placed joints (volpuzzle.joint.place_joints): faces_with_joints and
    each step's joints list them, so the plan says what was built."""
    import dataclasses

    keys = {(int(j.axis), tuple(j.pin_cell), tuple(j.hole_cell), bool(j.across_seam)) for j in joints}
    numbers = [n for n, f in enumerate(tiling.faces) if _face_key(f) in keys]
    jointed = set(numbers)
    steps = [dataclasses.replace(s, joints=tuple(n for n, _ in parted_faces(tiling, s.moving, s.fixed) if n in jointed))
             for s in plan.steps]
    return dataclasses.replace(plan, faces_with_joints=tuple((n, "lower") for n in numbers), steps=tuple(steps))


def joint_graph_connected(tiling, plan):
    """True when the jointed faces join every cell into one."""
    parts, _ = joint_graph(list(tiling.cells), [(tuple(tiling.faces[n].lower), tuple(tiling.faces[n].upper))
                                                for n, _ in plan.faces_with_joints])
    return len(parts) <= 1


def step_problems(tiling, plan):
    """Sentences naming every step that breaks the joint rule (empty when the plan is sound): the block must be the
    union of moving and fixed, every face between them normal to the step's axis with moving on the step's side (or a
    seam face of a ring cut), at least one joint across, and every jointed face across along the step's axis."""
    jointed = {n for n, _ in plan.faces_with_joints}
    out = []
    for k, s in enumerate(plan.steps):
        mv, fx = set(s.moving), set(s.fixed)
        name = f"step {k + 1} ({len(mv)} piece(s) {s.direction})"
        if mv & fx:
            out.append(f"{name}: moving and fixed share cells")
        joints_across = 0
        for n, f in enumerate(tiling.faces):
            lo, up = tuple(f.lower), tuple(f.upper)
            if not ((lo in mv and up in fx) or (lo in fx and up in mv)):
                continue
            if f.axis != s.axis:
                out.append(f"{name}: moving slides along face {piece_id(lo)}|{piece_id(up)} (axis {AXES[f.axis]})")
                continue
            moving_upper = up in mv
            if f.seam is None and moving_upper != (s.sign > 0):
                out.append(f"{name}: moving would push into {piece_id(lo if moving_upper else up)}")
            if f.seam is not None and not s.ring_cut:
                out.append(f"{name}: crosses the seam at {piece_id(lo)}|{piece_id(up)} without a ring cut")
            if n in jointed:
                joints_across += 1
        if joints_across == 0:
            out.append(f"{name}: no joint holds the two blocks together")
    return out


def _halves(cells, a):
    """The block `cells` cut across axis a at its middle -> (fixed: below the cut, moving: above it)."""
    vals = np.unique(np.array(cells)[:, a])
    p = vals[len(vals) // 2]
    return [c for c in cells if c[a] < p], [c for c in cells if c[a] >= p]


def _face_normal_grids(tiling, fmap, numbers, k=7):
    """Per face number, area-weighted mm normals (k * k, 3) on a k x k grid over the face, from its lower cell to its
    upper one (one evaluation of F for all of them)."""
    numbers = list(numbers)
    if not numbers:
        return []
    s = (np.arange(k) + 0.5) / k
    uvw = np.zeros((len(numbers), k * k, 3))
    for i, n in enumerate(numbers):
        f = tiling.faces[n]
        box = tiling.cells[tuple(f.lower)].box
        a = f.axis
        b, c = (a + 1) % 3, (a + 2) % 3
        uvw[i, :, a] = box[1, a]
        uvw[i, :, b] = box[0, b] + np.repeat(s, k) * (box[1, b] - box[0, b])
        uvw[i, :, c] = box[0, c] + np.tile(s, k) * (box[1, c] - box[0, c])
    _, jac = fmap.evaluate_with_jacobian(uvw.reshape(-1, 3))
    jac = jac.reshape(len(numbers), k * k, 3, 3)
    orient = float(getattr(fmap, "orientation", 1) or 1)
    out = []
    for i, n in enumerate(numbers):
        a = tiling.faces[n].axis
        b, c = (a + 1) % 3, (a + 2) % 3
        out.append(np.cross(jac[i, :, :, b], jac[i, :, :, c]) * orient)
    return out


def parted_faces(tiling, moving, fixed):
    """The faces between the cells `moving` and `fixed` (indices), ascending -> list of (face number, +1 when its
    upper cell is the moving one, else -1). Every such face touches a cell of the smaller side, so only those cells'
    faces are looked at: a scan of every face of the tiling per split grows as n^2."""
    mv, fx = {tuple(c) for c in moving}, {tuple(c) for c in fixed}
    out = []
    for n in sorted({n for c in min(mv, fx, key=len) for n in tiling.face_numbers(c)}):
        f = tiling.faces[n]
        lo, up = tuple(f.lower), tuple(f.upper)
        if (lo in mv and up in fx) or (lo in fx and up in mv):
            out.append((n, 1 if up in mv else -1))
    return out


def _split_normals(tiling, fmap, step, k=7):
    """Area-weighted mm normals (m, 3) over every face crossing the step's split, oriented from fixed to moving."""
    parted = parted_faces(tiling, step.moving, step.fixed)
    grids = _face_normal_grids(tiling, fmap, [n for n, _ in parted], k)
    return (np.concatenate([g * sign for g, (_, sign) in zip(grids, parted, strict=True)]) if grids
            else np.zeros((0, 3)))


def split_directions(tiling, fmap, plan):
    """Per step, the mm direction in which its moving block should leave: the step's slide when the plan search chose
    one, else leave_direction of the whole split surface -> list of (direction (3,), min_dot) in plan.steps order;
    min_dot = least cosine between it and the surface's normals (> 0: the block can leave along it without touching
    the other block)."""
    out = []
    for step in plan.steps:
        ns = _split_normals(tiling, fmap, step)
        # the plan's direction, when it chose one
        d = leave_direction(ns) if step.slide is None else np.asarray(step.slide, float)
        if d is None or float(np.linalg.norm(d)) < 1e-12:
            out.append((np.zeros(3), -1.0))
            continue
        d = d / float(np.linalg.norm(d))
        unit = ns / np.maximum(np.linalg.norm(ns, axis=1), 1e-300)[:, None]
        out.append((d, float((unit @ d).min())))
    return out


# ---------------------------------------------------------------------------------------------------------------------
# Replaying the plan on the real meshes


def _as_manifold(mesh, pid):
    from .check import piece_solid

    solid = piece_solid(mesh, pid)
    if isinstance(solid, str):
        raise GeometryError(f"assembly check: {solid}")
    return solid


_APART_SLACK = 1e-6  # mm kept from a proved gap: far above the engine's rounding of it


def _overlap(a, b):
    inter = a ^ b
    if not is_ok(inter):
        raise GeometryError(f"assembly check: intersection failed (status {inter.status().name})")
    return float(inter.volume())


def _directions(n=256):
    """n unit vectors spread evenly over the sphere (a Fibonacci lattice) plus the six axis directions."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    return np.concatenate([np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1), np.eye(3), -np.eye(3)])


_DIRS = _directions()


def _chunk_extents(verts, faces, chunks=8):
    """(chunks, 2, k) least and greatest projections onto _DIRS of `chunks` parts of a closed mesh that together
    cover its solid: the piece cut into slabs across its longest principal axis, each part being the corners of
    every triangle that reaches into its slab. A slab of the solid lies in the convex hull of the surface inside it
    (its cut faces are bounded by that surface), so two pieces whose parts are pairwise apart along some direction
    cannot overlap; parts fit a long curved piece far tighter than one hull."""
    v = np.asarray(verts, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    c = v - v.mean(axis=0)
    axis = np.linalg.svd(c[:: max(1, len(c) // 2000)], full_matrices=False)[2][0]
    s = v @ axis
    ts = s[f]
    cuts = np.linspace(float(s.min()), float(s.max()), chunks + 1)
    # slabs k with cuts[k] <= hi and lo <= cuts[k + 1] hold the triangle; each corner joins every slab of its
    # triangles, a run from k0 to k1
    first = np.clip(np.searchsorted(cuts[1:], ts.min(axis=1), side="left"), 0, chunks - 1)
    last = np.clip(np.searchsorted(cuts[:-1], ts.max(axis=1), side="right") - 1, 0, chunks - 1)
    k0 = np.full(len(v), chunks, dtype=np.int64)
    k1 = np.full(len(v), -1, dtype=np.int64)
    for j in range(3):
        np.minimum.at(k0, f[:, j], first)
        np.maximum.at(k1, f[:, j], last)
    used = k1 >= 0
    n_k = np.where(used, k1 - k0 + 1, 0)
    vid = np.repeat(np.arange(len(v)), n_k)
    kid = np.repeat(k0, n_k) + (np.arange(len(vid)) - np.repeat(np.cumsum(n_k) - n_k, n_k))
    order = np.argsort(kid, kind="stable")
    vid, kid = vid[order], kid[order]
    bounds = np.flatnonzero(np.r_[True, kid[1:] != kid[:-1], True])
    out = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        lo = np.full(len(_DIRS), np.inf)
        hi = np.full(len(_DIRS), -np.inf)
        for c0 in range(a, b, 8192):  # blocks keep a large piece's projections small
            proj = v[vid[c0:min(b, c0 + 8192)]] @ _DIRS.T
            lo = np.minimum(lo, proj.min(axis=0))
            hi = np.maximum(hi, proj.max(axis=0))
        out.append((lo, hi))
    return np.array(out)


def piece_extents(mesh):
    """_chunk_extents of a closed trimesh, made once per mesh (geometry.memo): the build's overlap check and the
    assembly replay test the same pieces. -> (chunks, 2, k)"""
    from .geometry import memo

    return memo(mesh, "extents", lambda: _chunk_extents(mesh.vertices, mesh.faces))


def parts_apart(ea, eb, shift=None, margin=0.0) -> bool:
    """Whether two solids are proved disjoint by their parts' extents (ea, eb: piece_extents, the second solid moved
    by shift (3,) mm): every part of the one lies more than margin mm from every part of the other along one of the
    directions (see _chunk_extents)."""
    move = 0.0 if shift is None else _DIRS @ np.asarray(shift, float)
    lo_b, hi_b = eb[:, 0, :] + move, eb[:, 1, :] + move
    apart = ((ea[:, None, 1, :] + margin < lo_b[None, :, :]) | (hi_b[None, :, :] + margin < ea[:, None, 0, :]))
    return bool(apart.any(axis=2).all())


class _Solids(dict):
    """{piece id: Manifold}, each made on first use (_as_manifold, shared through check.piece_solid): the sweeps ask
    for Booleans only where the boxes, the parts' extents and the surfaces leave a doubt, and at 1024 pieces none
    did, so building every piece's solid up front was ~2 s of this process for nothing."""

    def __init__(self, meshes):
        super().__init__()
        self._meshes = meshes

    def __missing__(self, pid):
        solid = self[pid] = _as_manifold(self._meshes[pid], pid)
        return solid


class _Scene:
    """Pieces with their vertices, faces, boxes, volumes (of their meshes) and manifolds (made when a Boolean needs
    them); counts the Booleans. apart: check.pairs_apart of the pieces, {frozenset of two ids: mm their surfaces stand
    apart at least}."""

    def __init__(self, pieces, apart=None, kernel=False):
        from .check import signed_volume

        self.apart = dict(apart or {})
        self.kernel = kernel  # whether _check_kernels.surfaces_meet spares Booleans (_unmet)
        self.ids = sorted(pieces)
        self.verts, self.faces, self.box, self.vol, self._meshes = {}, {}, {}, {}, {}
        self._extents = {}
        for pid in self.ids:
            mesh = pieces[pid]
            mesh = getattr(mesh, "mesh", mesh)
            self._meshes[pid] = mesh
            self.verts[pid], self.faces[pid] = kernel_arrays(mesh)
            self.box[pid] = np.array([self.verts[pid].min(axis=0), self.verts[pid].max(axis=0)])
            self.vol[pid] = abs(signed_volume(self.verts[pid], self.faces[pid]))
        self.man = _Solids(self._meshes)
        self.booleans = 0

    def extents(self, pid):
        """piece_extents of a piece, kept by the scene: the sweep asks it of each pair it tests (~18k times at 1024
        pieces), and each look-up through geometry.memo hashes the mesh."""
        ext = self._extents.get(pid)
        if ext is None:
            ext = self._extents[pid] = piece_extents(self._meshes[pid])
        return ext

    def _may_meet(self, pm_id, pf_id, ts, d, lim):
        """Bool per offset in ts: whether moving pm_id by t * d might make it overlap pf_id by more than lim.
        False is a proof: the boxes share at most lim, or every part of the one lies apart from every part of the
        other along one of _DIRS (_assembly_kernels.parts_meet)."""
        from ._assembly_kernels import parts_meet

        blo = self.box[pm_id][0] + ts[:, None] * d
        bhi = self.box[pm_id][1] + ts[:, None] * d
        common = np.clip(np.minimum(bhi, self.box[pf_id][1]) - np.maximum(blo, self.box[pf_id][0]), 0.0, None)
        out = np.prod(common, axis=1) > lim
        if not out.any():
            return out
        return parts_meet(self.extents(pm_id), self.extents(pf_id), _DIRS @ d, ts, out)

    def _near_pairs(self, moving, fixed, ts, d, lim):
        """(a, b) index pairs into moving and fixed, in row order, whose boxes may share more than lim (m, f) at
        some offset t * d, t from ts.min() to ts.max(): the moving box swept over the whole travel."""
        bm = np.array([self.box[p] for p in moving])  # (m, 2, 3)
        bf = np.array([self.box[p] for p in fixed])
        ends = np.stack([float(ts.min()) * d, float(ts.max()) * d])
        lo = bm[:, 0] + ends.min(axis=0)
        hi = bm[:, 1] + ends.max(axis=0)
        out = []
        step = max(1, (1 << 20) // max(len(fixed), 1))
        for a0 in range(0, len(moving), step):  # blocks of rows keep the (m, f, 3) arrays small
            sl = slice(a0, a0 + step)
            common = np.clip(np.minimum(hi[sl, None], bf[None, :, 1]) - np.maximum(lo[sl, None], bf[None, :, 0]),
                             0.0, None)
            a, b = np.nonzero(np.prod(common, axis=2) > lim[sl])
            out.extend(zip((a + a0).tolist(), b.tolist(), strict=True))
        return out

    def samples(self, moving, fixed, d, fine):
        """Offsets (mm along unit d) at which `moving` is tested against `fixed`: every `fine` mm from 0.05 over the
        first pin lengths, then coarser until moving is past every fixed piece (none when it already is)."""
        pm = np.concatenate([self.verts[p] @ d for p in moving])
        pf = np.concatenate([self.verts[p] @ d for p in fixed])
        total = float(pf.max() - pm.min()) + 0.1
        if total <= 0:
            return np.zeros(0)
        near = min(total, 3.0 * fine * 4 + 2.0)
        return np.array(list(np.arange(0.05, near, fine)) + list(np.arange(near, total + 2.0, max(2.0, total / 15))))

    def sweep_clear(self, moving, fixed, d, fine, limit_frac):
        """True when `moving` (ids) can travel along unit d (3,) until it is past every fixed piece, sampled every
        `fine` mm over the first pin length and coarser beyond; else (False, (moving id, fixed id, mm)).

        A sample of a pair is measured with a Boolean only where their boxes and their parts' extents (see
        _chunk_extents) cannot rule an overlap out; the samples are taken in order of travel, so the first
        collision found is the earliest."""
        d = np.asarray(d, dtype=float)
        ts = self.samples(moving, fixed, d, fine)
        if len(ts) == 0:
            return True, None
        lim_m = limit_frac * np.array([self.vol[p] for p in moving])
        lim_f = limit_frac * np.array([self.vol[p] for p in fixed])
        todo = []
        # All pairs at once: the box swept over the whole travel holds the box at every sample, so a pair whose swept
        # box shares at most the limit with the fixed box fails _may_meet at every sample too (most pairs of a large
        # block are far apart; one at a time in Python they cost more than the Booleans)
        for a, b in self._near_pairs(moving, fixed, ts, d, np.minimum(lim_m[:, None], lim_f[None, :])):
            pm_id, pf_id = moving[a], fixed[b]
            lim = min(float(lim_m[a]), float(lim_f[b]))
            meet = self._may_meet(pm_id, pf_id, ts, d, lim)
            # surfaces g apart come no closer than g - t after a travel t, and solids whose surfaces never meet stay
            # apart: a pair the face gaps proved apart needs no Boolean over its first g of travel
            meet &= ts >= self.apart.get(frozenset((pm_id, pf_id)), 0.0) - _APART_SLACK
            for k in np.flatnonzero(meet):
                todo.append((int(k), a, b, lim))
        todo.sort()
        moved = {}
        for k, a, b, lim in self._unmet(todo, moving, fixed, ts, d):
            t = float(ts[k])
            pm_id, pf_id = moving[a], fixed[b]
            if (a, k) not in moved:
                moved[(a, k)] = self.man[pm_id].translate(tuple(t * d))
            self.booleans += 1
            if _overlap(moved[(a, k)], self.man[pf_id]) > lim:
                return False, (pm_id, pf_id, t)
        return True, None

    def _unmet(self, todo, moving, fixed, ts, d):
        """The samples (k, a, b, lim) of sweep_clear, in order, less those at which surfaces_meet proves the two
        pieces' surfaces apart while neither box holds the other: two connected solids whose surfaces do not meet
        lie apart or one inside the other (check.pairs_apart), so the Boolean would find 0 there. At 1024 pieces
        11,379 Booleans (~0.45 ms each) all found 0: a pin slides out of its hole, faces part."""
        if not todo or not self.kernel:
            return todo
        from ._check_kernels import surfaces_meet

        asked = {}
        for k, a, b, _lim in todo:
            asked.setdefault((a, b), []).append(k)
        apart = set()
        for (a, b), ks in asked.items():
            pm, pf = moving[a], fixed[b]
            shifts = np.ascontiguousarray(ts[ks][:, None] * d[None, :])
            meet = surfaces_meet(self.verts[pm], self.faces[pm], self.verts[pf], self.faces[pf], shifts, _TOUCH_MM)
            for k, met, shift in zip(ks, meet, shifts, strict=True):
                if not met and not boxes_nested(self.box[pm] + shift, self.box[pf]):
                    apart.add((k, a, b))
        return [t for t in todo if t[:3] not in apart]


_TOUCH_MM = 1e-6  # surfaces this near count as meeting (the Boolean decides): far above the rounding of 300 mm
_KERNEL_MIN_PIECES = 256  # from here on surfaces_meet is used even where numba must compile it (~4 s) first


def _direction(joints, moving_cells, fixed_cells):
    """Unit mm direction in which moving leaves fixed through the joints across (pin out of hole), or None."""
    mv = set(moving_cells)
    fx = set(fixed_cells)
    ds = []
    for j in joints:
        pc, hc = tuple(j.pin_cell), tuple(j.hole_cell)
        if hc in mv and pc in fx:
            ds.append(np.asarray(j.direction, float))
        elif pc in mv and hc in fx:
            ds.append(-np.asarray(j.direction, float))
    if not ds:
        return None, []
    d = np.mean(ds, axis=0)
    n = float(np.linalg.norm(d))
    return (d / n if n > 1e-9 else None), ds


def _across(joints, moving_cells, fixed_cells):
    mv, fx = set(moving_cells), set(fixed_cells)
    return [j for j in joints if (tuple(j.pin_cell) in mv and tuple(j.hole_cell) in fx)
            or (tuple(j.hole_cell) in mv and tuple(j.pin_cell) in fx)]


def _candidates(block, planned, max_tries, groups=True):
    """Splits (moving, fixed, axis, sign) of a block to try, at most max_tries of them: the planned one, then every
    grid-plane split either way, then single pieces (only single pieces when groups is False). A generator: the
    planned split mostly works, and listing every single-piece split of a large block first costs block^2."""
    def every():
        if planned is not None and (groups or len(planned.moving) == 1):
            yield tuple(planned.moving), tuple(planned.fixed), planned.axis, planned.sign
        idx = np.array(block)
        for a in range(3 if groups else 0):
            vals = np.unique(idx[:, a])
            for p in vals[1:]:
                hi = tuple(c for c in block if c[a] >= p)
                lo = tuple(c for c in block if c[a] < p)
                yield hi, lo, a, +1
                yield lo, hi, a, -1
        for c in block:
            yield (c,), tuple(x for x in block if x != c), -1, 0

    seen = set()
    for m, f, a, s in every():
        if len(seen) >= max_tries:
            return
        key = frozenset(m)
        if key not in seen:
            seen.add(key)
            yield m, f, a, s


_REMOTE_MIN_PIECES = 16  # a smaller block is quicker taken apart here than shipped to a worker


def verify_disassembly(pieces, joints, plan, limit_frac=1e-4, fine=None, max_tries=24, groups=True, workers=None,
                       apart=None):
    """Replay the plan on the real meshes -> dict.

    pieces: {id: trimesh mesh in mm} (or a list of compose.Piece); joints: volpuzzle.joint.Joint list (the ones built);
    plan: AssemblyPlan. A block leaves along the mean mm direction of its joints to the other block (the centroid
    difference when none cross) and is swept until it is past the other block; every sample must overlap each other
    piece by at most limit_frac of the smaller piece volume. Keys: assembly_order (ids, every piece once), steps (in
    assembly order: kind 'place' | 'join', piece (id or None), pieces (the block moved), into (ids of the other block
    that it joins through joints), onto (all ids of the other block), direction (3,) of travel when assembling, axis
    ('+w' style, of the removal, None off-plan), joints ([pin id, hole id])), welded, stuck (ids), booleans,
    blocks_in_workers, seconds. groups=False allows only one piece at a time (then any grid with a cycle of jointed
    faces is welded).
    workers: the build's volpuzzle.workers.Workers, or None: once a block has come apart, its moving part (of at
    least _REMOTE_MIN_PIECES pieces) is taken apart in a worker that has started while this process takes the fixed
    part apart. A block's replay depends only on its own pieces, so the result is the same wherever it runs.
    apart: check.pairs_apart of these very meshes, whose gaps spare the Booleans over each pair's first gap of
    travel (the same steps, fewer Booleans).
    """
    t0 = time.perf_counter()
    if not isinstance(pieces, dict):
        pieces = {p.id: p.mesh for p in pieces}
    joints = list(joints or [])
    if fine is None:
        lengths = [float(j.length) for j in joints] or [2.0]
        fine = max(0.25, min(1.0, min(lengths) / 3.0))
    replay = _Replay(_Scene(pieces, apart, _use_kernel(len(pieces))), joints, plan, limit_frac, fine, max_tries,
                     groups, workers, 0 if workers is None else workers.size)
    steps = replay.take_apart([replay.cell_of[pid] for pid in replay.scene.ids])
    order = []
    for s in steps:
        for p in s["pieces"]:
            if p not in order:
                order.append(p)
    return {"assembly_order": order, "steps": steps, "welded": bool(replay.stuck), "stuck": sorted(replay.stuck),
            "booleans": replay.booleans, "blocks_in_workers": replay.remote_blocks,
            "seconds": round(time.perf_counter() - t0, 3)}


def _use_kernel(pieces):
    """Whether the replay of a puzzle of `pieces` pieces spares Booleans with surfaces_meet: from _KERNEL_MIN_PIECES
    on, or once numba has it compiled or cached (the steps are the same either way)."""
    from . import precompile

    return pieces >= _KERNEL_MIN_PIECES or precompile.usable("volpuzzle._check_kernels", "surfaces_meet")


def _replay_block(meshes, joints, plan, limit_frac, fine, max_tries, groups, block, apart=None, kernel=False):
    """take_apart of one block in a worker process -> (steps, stuck ids, Booleans). meshes: {id: workers.MeshRef}
    of the block's pieces only; apart, kernel: _Scene's, of those pieces."""
    scene = _Scene({pid: ref.mesh for pid, ref in meshes.items()}, apart, kernel)
    replay = _Replay(scene, joints, plan, limit_frac, fine, max_tries, groups)
    steps = replay.take_apart(block)
    return steps, replay.stuck, replay.booleans


class _Replay:
    """The recursive replay of verify_disassembly over one _Scene; `free` worker slots of `pool` take moving blocks."""

    def __init__(self, scene, joints, plan, limit_frac, fine, max_tries, groups, pool=None, free=0):
        self.scene, self.joints, self.plan = scene, joints, plan
        self.limit_frac, self.fine, self.max_tries, self.groups = limit_frac, fine, max_tries, groups
        self.pool, self.free = pool, free
        self.cell_of = {pid: tuple(int(x) for x in pid[1:].split("-")) for pid in scene.ids}
        self.planned = {frozenset(s.moving) | frozenset(s.fixed): s for s in plan.steps}
        self._joints_of = joints_by_cell(joints)
        self.stuck = []
        self.booleans_remote = 0
        self.remote_blocks = 0

    @property
    def booleans(self):
        return self.scene.booleans + self.booleans_remote

    def centroid(self, cells):
        return np.mean([self.scene.verts[piece_id(c)].mean(axis=0) for c in cells], axis=0)

    def take_apart(self, block):
        """Assembly steps for block (list of cells), or the steps of its parts that worked plus stuck pieces."""
        scene, joints = self.scene, self.joints
        block = sorted(tuple(c) for c in block)
        if len(block) == 1:
            return [{"kind": "place", "piece": piece_id(block[0]), "pieces": [piece_id(block[0])], "into": [],
                     "onto": [], "direction": None, "axis": None, "joints": []}]
        step = self.planned.get(frozenset(block))
        for moving, fixed, a, s in _candidates(block, step, self.max_tries, self.groups):
            # _across of the joints of the moving cells only (in list order): all joints per block is quadratic
            mine = sorted({k for c in moving for k in self._joints_of.get(tuple(c), ())})
            across = _across([joints[k] for k in mine], moving, fixed)
            d, _ = _direction(across, moving, fixed)
            if d is None:
                if across:
                    continue  # pins pointing against each other: this split cannot part
                known = step is not None and step.slide is not None and set(moving) == set(step.moving)
                d = np.asarray(step.slide, float) if known else self.centroid(moving) - self.centroid(fixed)
                n = float(np.linalg.norm(d))
                if n < 1e-9:
                    continue
                d = d / n
            ok, _ = scene.sweep_clear([piece_id(c) for c in moving], [piece_id(c) for c in fixed], d, self.fine,
                                      self.limit_frac)
            if not ok:
                continue
            join = {"kind": "join", "piece": piece_id(moving[0]) if len(moving) == 1 else None,
                    "pieces": [piece_id(c) for c in moving],
                    "into": sorted({piece_id(j.pin_cell if tuple(j.pin_cell) in set(fixed) else j.hole_cell)
                                    for j in across}),
                    "onto": [piece_id(c) for c in fixed],
                    "direction": [float(x) for x in -d],
                    "axis": (("+" if s > 0 else "-") + AXES[a]) if a >= 0 else None,
                    "joints": [[piece_id(j.pin_cell), piece_id(j.hole_cell)] for j in across]}
            # a single piece is slid on directly; a block of several is built apart first
            if len(moving) == 1:
                return self.take_apart(fixed) + [join]
            remote = self._submit(moving) if min(len(moving), len(fixed)) >= _REMOTE_MIN_PIECES else None
            first = self.take_apart(fixed)
            return first + (self._result(remote, moving) if remote is not None else self.take_apart(moving)) + [join]
        self.stuck.extend(piece_id(c) for c in block)
        return [{"kind": "place", "piece": piece_id(c), "pieces": [piece_id(c)], "into": [], "onto": [],
                 "direction": None, "axis": None, "joints": [], "stuck": True} for c in block]

    def _submit(self, block):
        """A worker's future for take_apart(block), or None when no worker slot is free."""
        if self.pool is None or self.free <= 0:
            return None
        from .workers import MeshRef

        # as MeshRefs, the worker finds the very meshes the checks sent it, with the solids it built of them then
        meshes = {piece_id(c): MeshRef(self.scene._meshes[piece_id(c)]) for c in block}
        apart = {pair: g for pair, g in self.scene.apart.items() if pair <= meshes.keys()}
        fut = self.pool.submit(_replay_block, meshes, self.joints, self.plan, self.limit_frac, self.fine,
                               self.max_tries, self.groups, list(block), apart, self.scene.kernel)
        if fut is None:  # no worker has started yet (or the pool is shut)
            return None
        self.free -= 1
        return fut

    def _result(self, fut, block):
        """The worker's take_apart(block); done here instead when the worker died (the same function either way)."""
        import concurrent.futures

        try:
            steps, stuck, booleans = fut.result()
        except concurrent.futures.process.BrokenProcessPool:
            self.pool = None  # no more work to a broken pool
            return self.take_apart(block)
        finally:
            self.free += 1
        self.stuck.extend(stuck)
        self.booleans_remote += booleans
        self.remote_blocks += 1
        return steps


# ---------------------------------------------------------------------------------------------------------------------
# Words for report.md


def _vec(d):
    return "(" + ", ".join(f"{x:.2f}" for x in d) + ")"


def _names(ids):
    return ", ".join(ids)


def steps_in_words(result):
    """Numbered sentences for report.md, one per assembly step (list of str)."""
    lines = []
    placed_any = False
    for k, s in enumerate(result["steps"], start=1):
        if s["kind"] == "place":
            if s.get("stuck"):
                lines.append(f"{k}. Place {s['piece']} (stuck: this piece cannot be taken out again).")
            elif not placed_any:
                lines.append(f"{k}. Place {s['piece']} on the table.")
            else:
                lines.append(f"{k}. Separately, place {s['piece']} on the table to start a new block.")
            placed_any = True
            continue
        what = s["piece"] if s["piece"] else "the block " + _names(s["pieces"])
        onto = _names(s["onto"]) if len(s["onto"]) <= 4 else f"the block of {len(s['onto'])} pieces with {s['onto'][0]}"
        axis = ""
        if s["axis"]:
            # the removal went along axis; assembling travels the other way
            axis = f" along {('-' if s['axis'][0] == '+' else '+')}{s['axis'][1]}"
        line = f"{k}. Slide {what} onto {onto}{axis} (mm direction {_vec(s['direction'])})"
        pins = []
        for pin, hole in s["joints"]:
            pins.append(f"the pin of {pin} enters {hole}")
        if pins:
            line += " so that " + "; ".join(pins)
        lines.append(line + ".")
    if result.get("welded"):
        lines.append(f"Warning: the puzzle is welded: {_names(result['stuck'])} cannot be taken apart.")
    return lines


MAX_BEND_DEG = 180.0  # the most a block may turn along one axis and still slide off its neighbours (see bend_grid)


def bend_grid(tiling, fmap, max_bend_deg=MAX_BEND_DEG, lines=3, samples=16):
    """The grid (tuple of 3) with more cells along every axis whose cells' parameter lines turn by more than
    max_bend_deg, so that none does (the other axes unchanged), or None when no cell turns that far.

    Why a half turn. A piece that turns further along an axis wraps round something: a piece of a coiled spring that
    spans one and a half turns lies over its own next turn, so no straight slide lifts it off the piece below, nor
    pulls the piece inside it inward. An arc of at most a half turn lies wholly ahead of the plane of its end face and
    wholly on one side of its chord: it slides off its neighbour along that face's normal, and its inner layer leaves
    toward the arc's centre. The spring of G+Smo (three turns) is welded at 2 x 2 x 2 and builds at 6 x 2 x 2.
    Turning is measured on lines x lines lines per axis across the whole domain, samples per cell."""
    grid = [int(g) for g in tiling.grid]
    out = list(grid)
    fr = (np.arange(lines) + 0.5) / lines
    for a in range(3):
        b, c = [x for x in range(3) if x != a]
        brk = np.asarray(tiling.breaks[a], float)
        t = np.concatenate([np.linspace(brk[k], brk[k + 1], samples) for k in range(len(brk) - 1)])
        lo = [float(tiling.breaks[x][0]) for x in range(3)]
        hi = [float(tiling.breaks[x][-1]) for x in range(3)]
        uvw = np.zeros((lines, lines, len(t), 3))
        uvw[..., a] = t
        uvw[..., b] = (lo[b] + fr * (hi[b] - lo[b]))[:, None, None]
        uvw[..., c] = (lo[c] + fr * (hi[c] - lo[c]))[None, :, None]
        _, jac = fmap.evaluate_with_jacobian(uvw.reshape(-1, 3))
        tan = jac[:, :, a].reshape(lines * lines, len(brk) - 1, samples, 3)
        tan = tan / np.maximum(np.linalg.norm(tan, axis=-1), 1e-300)[..., None]
        cos = np.clip(np.einsum("lksi,lksi->lks", tan[:, :, 1:], tan[:, :, :-1]), -1.0, 1.0)
        turn = np.degrees(np.arccos(cos)).sum(axis=2)  # (lines, cells along a)
        if float(turn.max()) > max_bend_deg + 1e-6:
            out[a] = max(grid[a], int(np.ceil(float(turn.sum(axis=1).max()) / max_bend_deg - 1e-6)))
    return tuple(out) if out != grid else None


def replay_assembly(plan, pieces, joints, allow=(), randomized=False, tiling=None, fmap=None, workers=None,
                    apart=None):
    """Disassembly replayed on the real meshes, reversed (workers, apart: see verify_disassembly). -> dict with
    assembly_order, steps, words, welded, stuck.
    A welded puzzle fails the build unless joints.allow has 'welded' (then it is a warning); with tiling and fmap
    the message names the grid at which no cell bends more than a half turn (bend_grid), when that is another."""

    if plan is None:
        return {"assembly_order": [p.id for p in pieces], "steps": [], "words": [], "welded": False, "stuck": []}
    res = verify_disassembly(pieces, joints, plan, workers=workers, apart=apart)
    if res["welded"]:
        stuck = ", ".join(res["stuck"][:6]) + (f" and {len(res['stuck']) - 6} more" if len(res["stuck"]) > 6 else "")
        if "welded" not in tuple(allow):
            finer = bend_grid(tiling, fmap) if tiling is not None and fmap is not None else None
            bent = [AXES[x] for x in range(3) if finer is not None and finer[x] != tiling.grid[x]]
            tries = (f"grid {list(finer)}, whose cells turn at most {MAX_BEND_DEG:g} deg along {', '.join(bent)}"
                     if finer is not None else "another grid (more pieces along a curved axis)") + (
                ", a smaller randomize.amplitude, another randomize.seed" if randomized else "")
            raise GeometryError(f"assembly: the puzzle is welded: {stuck} cannot be taken out along their pins "
                                f"(got {len(res['stuck'])} stuck pieces, expected none; try {tries}, or "
                                f"joints.allow: [welded])")
        warn(f"the puzzle is welded: {stuck} cannot be taken out along their pins")
    return {"assembly_order": res["assembly_order"], "steps": res["steps"], "words": steps_in_words(res),
            "welded": bool(res["welded"]), "stuck": list(res["stuck"])}
