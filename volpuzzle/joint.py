"""joint: a pin (or dowel) on every shared face with room for one, each placed on its own face.

This module owns a joint's geometry: its sizes (outer radius, clearance, wall), where it crosses its face, the way it
points, and its solids. pipeline.py only calls place_joints.

Who gets a pin. A face along axis a joins its `lower` cell (pin) to its `upper` cell (hole), also across a periodic
seam (the last cell along a carries the pin), so every cell has at most one pin on each of its three max faces and
one hole on each of its three min faces: at most three of each, as in the paper. Every face whose two pieces hold a
pin with its clearance and wall gets one; a face without one is reported with the reason (Layout.contacts).

Which way it points. With an assembly plan (volpuzzle.assembly) every face belongs to the one split of the plan that
parts its two cells, and all pins of a split are parallel to that split's sliding direction (the mean normal of its
whole cut surface, or a direction within assembly.MAX_TURN_DEG of it that the plan found to hold more of its faces), so
a block slides off all its pins at once. A pin therefore leans against its own face by up to MAX_TILT_DEG; without a
plan it stands normal to its face. place_planned_joints hands the plan search _Setup.holds, so that the plan's cuts
are the ones whose faces can hold pins along their splits.

Why 30 degrees. A straight pin leaning by t meets its face in an ellipse 1/cos t longer than the pin is wide (1.15 at
30 deg), and the lip of its hole is a wedge of 90 - t degrees of material; at 30 deg that wedge is 60 deg, which a
printer lays down without a support and which does not break off when the pin goes in, and the pin's base has to
reach back only reach * tan t (0.58 radii) to stay attached. Beyond about 35-40 deg the lip turns into a knife edge
thinner than two extrusion lines on a 1 mm pin.

Where on the face. Each face is sampled on a 13 x 13 grid of points; a point is usable at a size when the pin's
footprint (widened by its lean) keeps a wall to every edge of the face in both pieces, also at the bottom of its hole,
and both pieces are deep enough for their part of the joint and a wall; a point chosen is then measured against the
cells' real side faces too (_Sides), which a curved or narrowing cell brings closer than its line lengths say. Inside a
piece every joint is a cylinder (a pin's base, reaching back behind the face; a hole, reaching in) and two of them must
keep a wall between them. Faces
are placed one at a time, the plan's own faces first (they hold the puzzle together), each at its roomiest usable
point that keeps apart from the joints already placed in its two pieces; where none is left at the asked size the pin
shrinks, down to min_radius and min_length (default MIN_RADIUS, MIN_LENGTH: still printable).

Space. 'physical' (default): the joint is a straight cylinder in mm, so radius, length and clearances hold in the
printed object. 'domain': the pin is built in the parameter domain and composed with the piece through F, as the paper
does; it is sized by the Jacobian at the face point, so it is right only to first order and is distorted where F bends
(the paper's Fig. 16 problem).
"""

import math
from dataclasses import dataclass, field, fields
from typing import NamedTuple

import numpy as np

from .errors import GeometryError, SpecError
from .geometry import check_status
from .grid import AXES, frame_from_direction, piece_id
from .spec import JOINT_ALLOW, JointSpec

CIRCLE_TOL = 0.02  # mm: largest distance between a joint's polygon and its circle
SNAP_SWELL = 1.15  # widest radius of a snap pin, in pin radii
# The joint defaults have one home, spec.JointSpec (what a spec without the key gets); named here for the stage.
DEFAULT_CLEARANCE = JointSpec.clearance  # mm, radial
DEFAULT_AXIAL_CLEARANCE = JointSpec.axial_clearance  # mm, at the pin's tip
MIN_RADIUS = JointSpec.min_radius  # mm: the smallest pin a pin shrinks to (2 mm across: four lines of a 0.4 mm nozzle)
MIN_LENGTH = JointSpec.min_length  # mm: the shortest pin that still holds its piece
DEFAULT_MAX_RADIUS = 2.5  # mm: a derived radius stops growing here; larger pins only when asked
MAX_TILT_DEG = 30.0  # the most a straight pin may lean against its face (see the module docstring)
SIDE_WALL = 0.5  # the share of a wall kept, measured on the real side faces (see _Sides)
_COS_TILT = float(np.cos(np.radians(MAX_TILT_DEG)))
ALLOW = JOINT_ALLOW  # what joints.allow may accept: pieces without a joint, pieces that cannot come out


def wall(radius):
    """mm of material kept between two joints in a piece, and between a joint and a face's edge."""
    return max(0.8, 0.4 * radius)




def outer_radius(radius, shape):
    """The widest radius of a pin of this shape (a snap pin swells), mm."""
    return radius * (SNAP_SWELL if shape == "snap" else 1.0)


def _cyclic(a):
    """The other two axes in cyclic order, so that J_a . (J_b x J_c) = det J."""
    return (a + 1) % 3, (a + 2) % 3


def _readonly(a):
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Joint:
    """One joint across a shared face. Lengths in mm of the printed object.

    center (3,): where the pin's axis crosses the face; direction (3,): unit vector along which the pin leaves
    pin_cell into hole_cell; uvw_pin (3,): the parameter of that crossing on the pin cell's face; uvw_hole (3,): the
    same point on the hole cell's face (differs across a seam); base_depth: how far the pin (and the hole's opening)
    reaches back behind the face so that it stays attached on a curved face; jacobian_pin / jacobian_hole (3, 3):
    dF/duvw at uvw_pin / uvw_hole, for the domain-space solids; tilt_deg: the angle between direction and the face's
    normal there; shrunk: smaller than asked, to fit its face.
    """

    pin_cell: tuple
    hole_cell: tuple
    axis: int
    across_seam: bool
    center: np.ndarray
    direction: np.ndarray
    radius: float
    length: float
    clearance: float
    axial_clearance: float
    shape: str
    style: str
    space: str
    uvw_pin: np.ndarray
    uvw_hole: np.ndarray
    base_depth: float
    jacobian_pin: np.ndarray = None
    jacobian_hole: np.ndarray = None
    tilt_deg: float = 0.0
    shrunk: bool = False

    @property
    def outer_radius(self):
        """The pin's widest radius, mm."""
        return outer_radius(self.radius, self.shape)

    @property
    def reach(self):
        """The hole's widest radius (pin and clearance), mm."""
        return self.outer_radius + self.clearance

    @property
    def wall(self):
        return wall(self.radius)

    @property
    def segments(self):
        """Circle segments for pin and hole alike (same count keeps the radial gap uniform)."""
        r = self.reach
        n = int(np.ceil(np.pi / np.arccos(max(1.0 - CIRCLE_TOL / r, -1.0))))
        return int(max(16, 4 * int(np.ceil(n / 4))))

    @property
    def hole_depth(self):
        return self.length + self.axial_clearance

    def to_report(self):
        """The joint as SPEC section 5 lists it."""
        return {
            "pin_piece": piece_id(self.pin_cell),
            "hole_piece": piece_id(self.hole_cell),
            "axis": AXES[self.axis],
            "center_mm": [round(float(x), 4) for x in self.center],
            "direction": [round(float(x), 6) for x in self.direction],
            "radius_mm": float(self.radius),
            "length_mm": float(self.length),
            "clearance_mm": float(self.clearance),
            "axial_clearance_mm": float(self.axial_clearance),
            "style": self.style,
            "shape": self.shape,
            "space": self.space,
            "across_seam": bool(self.across_seam),
            "tilt_deg": round(float(self.tilt_deg), 2),
            "shrunk": bool(self.shrunk),
        }


def pieces_joints(joints, cell_index):
    """The joints touching one cell -> list of (joint, role), role 'pin' (add pin_solid) or 'hole' (subtract
    hole_solid(joint, cell_index)); with style dowel both cells of a joint get role 'hole'."""
    idx = tuple(cell_index)
    out = []
    for j in joints:
        if j.pin_cell == idx:
            out.append((j, "hole" if j.style == "dowel" else "pin"))
        if j.hole_cell == idx:
            out.append((j, "hole"))
    return out


def gap_volume(joint):
    """mm^3 the joint leaves empty between its pieces: hole volume beyond the face less the pin (or dowel) volume."""
    r, c, length, ac = joint.radius, joint.clearance, joint.length, joint.axial_clearance
    hole = np.pi * (r + c) ** 2 * (length + ac)
    if joint.style == "dowel":
        return 2 * hole
    return hole - np.pi * r ** 2 * length


def piece_joints_report(joints, cell_index):
    """A piece's joints for its report.json entry: [{role 'pin' | 'hole', with (the other piece), axis, radius_mm,
    length_mm, shrunk}]."""
    idx = tuple(cell_index)
    return [{"role": role, "with": piece_id(j.hole_cell if tuple(j.pin_cell) == idx else j.pin_cell),
             "axis": AXES[j.axis], "radius_mm": float(j.radius), "length_mm": float(j.length), "shrunk": bool(j.shrunk)}
            for j, role in pieces_joints(joints, idx)]


# ---------------------------------------------------------------------------------------------------------------------
# Measuring the cells


@dataclass(frozen=True, eq=False)
class _Geometry:
    """lengths: {cell: (3, G, G)} mm length of the cell's parameter lines along each axis a, on a G x G grid of the
    other two (cyclic) fractions _GRID, each line as a polyline of 8 chords."""

    lengths: dict


_GRID = np.linspace(0.0, 1.0, 7)
_AFTER = [[_cyclic(a)[k] for a in range(3)] for k in (0, 1)]  # the axes b, c after each axis a (_cyclic)


def _lens_at(cell_lengths, idx, fr):
    """Lengths (n, 3) mm of cell idx's parameter lines along each axis through fractions fr (n, 3), bilinear in the
    grid: the three axes at once (a face's points ask for all three)."""
    return _lens_at_faces(cell_lengths.lengths[idx][None], np.asarray(fr, dtype=float)[None])[0]


def _center_len(cell_lengths, idx, a):
    return float(_lens_at(cell_lengths, idx, np.full((1, 3), 0.5))[0, a])


def _measure(tiling, fmap):
    cells = list(tiling.cells.values())
    t = np.linspace(0.0, 1.0, 9)
    g = _GRID
    ng = len(g)
    pts = []
    for cell in cells:
        lo, hi = cell.box
        for a in range(3):
            b, c = _cyclic(a)
            fr = np.zeros((ng, ng, 9, 3))
            fr[..., a] = t[None, None, :]
            fr[..., b] = g[:, None, None]
            fr[..., c] = g[None, :, None]
            pts.append(lo + fr.reshape(-1, 3) * (hi - lo))
    xyz = fmap.evaluate(np.concatenate(pts)).reshape(len(cells), 3, ng, ng, 9, 3)
    seg = np.linalg.norm(np.diff(xyz, axis=4), axis=-1).sum(axis=4)  # (cells, 3, ng, ng)
    return _Geometry({cell.index: seg[n] for n, cell in enumerate(cells)})


def _face_sides(cell_lengths, faces):
    """(faces,) mm: the shorter in-face side of each face through its centre, in either of its cells; and (2 faces,)
    mm: the depth of both its cells across it at their centres."""
    n = len(faces)
    axes = np.array([f.axis for f in faces])
    fr = np.full((2, n, 2, 3), 0.5)  # (lower | upper cell, face, face centre | cell centre, uvw fractions)
    fr[0, np.arange(n), 0, axes] = 1.0
    fr[1, np.arange(n), 0, axes] = 0.0
    lens = [_lens_at_faces(np.stack([cell_lengths.lengths[getattr(f, end)] for f in faces]), fr[k])
            for k, end in enumerate(("lower", "upper"))]  # (faces, 2, 3) each
    bc = np.array([_cyclic(a) for a in axes])
    rows = np.arange(n)[:, None]
    side = np.minimum(lens[0][rows, 0, bc].min(axis=1), lens[1][rows, 0, bc].min(axis=1))
    depth = np.stack([lens[0][np.arange(n), 1, axes], lens[1][np.arange(n), 1, axes]], axis=1).ravel()
    return side, depth


def _round_down(x, step=0.1):
    return round(float(np.floor(x / step + 1e-9) * step), 6)


def default_sizes(tiling, fmap, _lengths=None):
    """(radius, length) mm from the typical face and cell: radius 12% of the median face's short side, between
    MIN_RADIUS and DEFAULT_MAX_RADIUS; length 2 radii, at most 35% of the median cell depth, at least MIN_LENGTH;
    rounded down to 0.1 mm. Faces too small for these get smaller pins of their own (place_joints)."""
    cell_lengths = _lengths or _measure(tiling, fmap)
    if tiling.faces:
        sides, depths = _face_sides(cell_lengths, tiling.faces)
        side, depth = float(np.median(sides)), float(np.median(depths))
    else:
        side = depth = min(_center_len(cell_lengths, idx, a) for idx in tiling.cells for a in range(3))
    radius = min(max(_round_down(0.12 * side), MIN_RADIUS), DEFAULT_MAX_RADIUS)
    length = max(_round_down(min(2.0 * radius, 0.35 * depth)), MIN_LENGTH)
    return radius, length


# ---------------------------------------------------------------------------------------------------------------------
# Placement


@dataclass(frozen=True)
class _Sizes:
    radius: float
    length: float
    clearance: float
    axial_clearance: float
    style: str
    shape: str

    @property
    def reach(self):
        """Radius of the widest hole, mm."""
        return outer_radius(self.radius, self.shape) + self.clearance

    @property
    def wall(self):
        return wall(self.radius)

    @property
    def hole_depth(self):
        return self.length + self.axial_clearance

    def scaled(self, radius, length):
        return _Sizes(float(radius), float(length), self.clearance, self.axial_clearance, self.style, self.shape)


@dataclass(frozen=True)
class Layout:
    """What place_joints decided: joints (tuple of Joint) and contacts (tuple of dict, one per shared face, in
    tiling.faces order): pieces [lower, upper], axis, across_seam, room (a pin of the smallest size fits the face
    alone), pinned, reason (why not, or None), radius_mm / length_mm of its joint; sizes: the asked (radius, length)
    and the smallest (min_radius, min_length)."""

    joints: tuple
    contacts: tuple
    sizes: dict = field(default_factory=dict)


# Sample points on a face, as fractions along its two in-face axes; the centre first among equals.
_S = np.linspace(0.08, 0.92, 13)
_CAND = np.array([(sb, sc) for sb in _S for sc in _S])


@dataclass(frozen=True, eq=False)
class _FaceShape:
    """A face's sample points (k of them), whichever way its pin points: fractions and parameters in both cells
    {cell side -1 lower, +1 upper: (k, 3)}, mm points x (k, 3), the face normal nrm (k, 3) (+axis), unit in-face
    tangents of each cell {side: (k, 3, 3)} (row x: along axis x), line lengths {side: (k, 3)}, mm offsets (k, 12, 3)
    from x to a ring round it as wide as the largest pin, usable (k,) where the face is not collapsed, and dF/duvw
    {side: (k, 3, 3)}."""

    n: int
    face: object
    fr: dict
    uvw: dict
    x: np.ndarray
    nrm: np.ndarray
    tangents: dict
    lens: dict
    ring: np.ndarray
    usable: np.ndarray
    jac: dict


@dataclass(frozen=True, eq=False)
class _FaceData(_FaceShape):
    """A face's sample points with its pin's direction: the _FaceShape fields (usable now also where the pin does not
    run along the face), the pin direction d (k, 3), cos (k,) between it and the normal, and the face's bulge sag (k,)
    in mm along d over a disc of the largest pin."""

    d: np.ndarray
    cos: np.ndarray
    sag: np.ndarray


def _face_shapes(tiling, fmap, cell_lengths, reach_max):
    """_FaceShape per face of the tiling, in tiling.faces order: the evaluations of F that placement needs, made
    once, so that many pin directions can be tried on them (_directed)."""
    out = []
    orientation = int(getattr(fmap, "orientation", 1) or 1)
    k = len(_CAND)
    ring = np.stack([np.cos(np.arange(12) * np.pi / 6), np.sin(np.arange(12) * np.pi / 6)], axis=1)
    per = []
    for f in tiling.faces:
        a = f.axis
        b, c = _cyclic(a)
        low, up = tiling.cells[f.lower], tiling.cells[f.upper]
        fr = np.empty((k, 3))
        fr[:, a], fr[:, b], fr[:, c] = 1.0, _CAND[:, 0], _CAND[:, 1]
        uvw = low.box[0] + fr * (low.box[1] - low.box[0])
        if f.seam is not None:
            uvw_up = np.asarray(f.seam.map_max_to_min(uvw), dtype=float)
        else:
            uvw_up = uvw.copy()
            uvw_up[:, a] = up.box[0, a]
        fr_up = (uvw_up - up.box[0]) / (up.box[1] - up.box[0])
        per.append((f, fr, fr_up, uvw, uvw_up))
    if not per:
        return out
    n_faces = len(per)
    x, jac = fmap.evaluate_with_jacobian(np.concatenate([p[3] for p in per]))
    x, jac = x.reshape(-1, k, 3), jac.reshape(-1, k, 3, 3)
    # the upper cell sees the same points, but across a seam (and where lo + (hi - lo) rounds off hi): only those
    # are evaluated again
    again = [n for n, p in enumerate(per) if not np.array_equal(p[3], p[4])]
    jac_up = jac.copy()
    if again:
        jac_up[again] = fmap.evaluate_with_jacobian(np.concatenate([per[n][4] for n in again]))[1].reshape(-1, k, 3, 3)
    # every face at once, a group per axis (which sets the in-face axes b, c): a loop over 2816 faces was 2 s of the
    # 1024-piece build's joint stage
    uvw = np.stack([p[3] for p in per])
    boxes = np.stack([tiling.cells[p[0].lower].box for p in per])  # (faces, 2, 3)
    axes = np.array([p[0].axis for p in per])
    nrm = np.empty((n_faces, k, 3))
    usable = np.empty((n_faces, k), bool)
    rings = np.empty((n_faces, k, 12, 3))
    for a in range(3):
        sel = np.flatnonzero(axes == a)
        if not len(sel):
            continue
        b, c = _cyclic(a)
        j = jac[sel]
        across = np.cross(j[..., b], j[..., c])
        det = np.einsum("fki,fki->fk", j[..., a], across)
        sign = np.where(np.abs(det) > 1e-12, np.sign(det), orientation)
        size = np.linalg.norm(across, axis=2)
        nrm[sel] = sign[..., None] * across / np.maximum(size, 1e-300)[..., None]
        usable[sel] = size > 1e-9 * np.maximum(size.max(axis=1), 1e-300)[:, None]
        # a disc of the largest pin's footprint on the face, to measure how far the face bulges from its tangent plane
        p = np.repeat(uvw[sel][:, :, None, :], 12, axis=2)
        for ax, col in ((b, 0), (c, 1)):
            step = 1.2 * reach_max / np.maximum(np.linalg.norm(j[..., ax], axis=2), 1e-12)
            p[..., ax] += ring[None, None, :, col] * step[..., None]
        rings[sel] = np.clip(p, boxes[sel, 0][:, None, None, :], boxes[sel, 1][:, None, None, :])
    xr = fmap.evaluate(rings.reshape(-1, 3)).reshape(n_faces, k, 12, 3)
    tangents, lens = {}, {}
    for side, jj, cells, fr in ((-1, jac, [p[0].lower for p in per], np.stack([p[1] for p in per])),
                                (+1, jac_up, [p[0].upper for p in per], np.stack([p[2] for p in per]))):
        t = np.transpose(jj, (0, 1, 3, 2))  # (face, k, axis, xyz)
        tangents[side] = t / np.maximum(np.linalg.norm(t, axis=3), 1e-300)[..., None]
        lens[side] = _lens_at_faces(np.stack([cell_lengths.lengths[idx] for idx in cells]), fr)
    for n, (f, fr, fr_up, uvw_n, uvw_up) in enumerate(per):
        out.append(_FaceShape(n, f, {-1: fr, +1: fr_up}, {-1: uvw_n, +1: uvw_up}, x[n], nrm[n],
                              {-1: tangents[-1][n], +1: tangents[+1][n]}, {-1: lens[-1][n], +1: lens[+1][n]},
                              xr[n] - x[n][:, None, :], usable[n], {-1: jac[n], +1: jac_up[n]}))
    return out


def _lens_at_faces(tabs, fr):
    """_lens_at of many faces at once: tabs (faces, 3, G, G) of each face's cell, fractions fr (faces, k, 3) ->
    (faces, k, 3) mm, the same arithmetic."""
    g = len(_GRID) - 1
    x = np.clip(fr[..., _AFTER[0]], 0.0, 1.0) * g
    y = np.clip(fr[..., _AFTER[1]], 0.0, 1.0) * g
    i = np.minimum(x.astype(int), g - 1)
    j = np.minimum(y.astype(int), g - 1)
    tx, ty = x - i, y - j
    f = np.arange(len(tabs))[:, None, None]
    a = np.arange(3)[None, None, :]
    return ((1 - tx) * (1 - ty) * tabs[f, a, i, j] + tx * (1 - ty) * tabs[f, a, i + 1, j]
            + (1 - tx) * ty * tabs[f, a, i, j + 1] + tx * ty * tabs[f, a, i + 1, j + 1])


def _directed(shape, direction=None):
    """The _FaceData of a face whose pins point along the unit mm direction (3,) from its lower cell to its upper
    one (None: normal to the face at each point)."""
    k = len(shape.x)
    d = shape.nrm.copy() if direction is None else np.repeat(np.asarray(direction, float)[None], k, axis=0)
    cos = np.clip(np.einsum("ki,ki->k", d, shape.nrm), -1.0, 1.0)
    sag = np.max(np.abs(np.einsum("kri,ki->kr", shape.ring, d)), axis=1)
    base = {f.name: getattr(shape, f.name) for f in fields(_FaceShape)}
    return _FaceData(**(base | {"usable": shape.usable & (cos > 1e-6)}), d=d, cos=cos, sag=sag)


def _base(fd, s):
    """How far a pin's base (k,) reaches back behind the face: past the face's bulge, and past its lean."""
    cos = np.maximum(fd.cos, 1e-6)
    tan = np.sqrt(np.maximum(1.0 - cos * cos, 0.0)) / cos
    return np.maximum(0.5, 1.5 * fd.sag + 0.3) + s.reach * tan


def _intrusion(fd, s, side):
    """(depth (k,), way (+1 along d, -1 against it), radius) of the joint's part inside the cell on `side` (-1 lower,
    +1 upper): a hole reaches in along d; a pin's base reaches back; a dowel's hole in the lower cell reaches back."""
    if side == +1:
        return np.full(len(fd.cos), s.hole_depth), +1, s.reach
    if s.style == "dowel":
        return np.full(len(fd.cos), s.hole_depth), -1, s.reach
    return _base(fd, s), -1, s.radius


def _fits(fd, s, lean=True, limit=True):
    """(k,) bool for the points of face fd (_FaceData, or a _FaceStack of faces across one axis): at size s the joint
    keeps a wall to every edge of the face in both cells (its footprint widened by its lean, and shifted by it at the
    bottom of its hole) and a wall to each cell's far side; with lean the pin also leans at most MAX_TILT_DEG unless
    limit is False (lean False measures the face alone: a pin normal to it)."""
    a = fd.face.axis
    b, c = _cyclic(a)
    cos = np.maximum(fd.cos, 1e-6) if lean else np.ones_like(fd.cos)
    sin = np.sqrt(np.maximum(1.0 - cos * cos, 0.0))
    d = fd.d if lean else fd.nrm
    ok = fd.usable.copy()
    foot = s.reach / cos + s.wall
    for side in (-1, +1):
        depth, way, rho = _intrusion(fd, s, side)
        fr, lens = fd.fr[side], fd.lens[side]
        for x in (b, c):
            shift = depth * way * np.einsum("ki,ki->k", d, fd.tangents[side][:, x])
            ok &= (1.0 - fr[:, x]) * lens[:, x] >= foot + np.maximum(shift, 0.0) - 1e-9
            ok &= fr[:, x] * lens[:, x] >= foot + np.maximum(-shift, 0.0) - 1e-9
        ok &= lens[:, a] >= depth * cos + rho * sin + s.wall - 1e-9
    if lean and limit:
        ok &= fd.cos >= _COS_TILT - 1e-12
    return ok


class _Across(NamedTuple):
    """The one thing _fits reads of a face record: the axis it lies across."""

    axis: int


@dataclass(frozen=True, eq=False)
class _FaceStack:
    """Faces across the same axis as one: the _FaceData arrays that _fits reads, end to end (rows (N,)), and the rows of
    each face (sizes), so that one _fits call measures them all."""

    face: _Across
    usable: np.ndarray
    cos: np.ndarray
    d: np.ndarray
    nrm: np.ndarray
    sag: np.ndarray
    fr: dict
    lens: dict
    tangents: dict
    numbers: tuple
    sizes: tuple


def _stacks(data):
    """data (list of _FaceData) as one _FaceStack per axis its faces lie across."""
    out = []
    for a in range(3):
        group = [fd for fd in data if fd.face.axis == a]
        if not group:
            continue

        def cat(name, side=None, group=group):
            return np.concatenate([getattr(fd, name) if side is None else getattr(fd, name)[side] for fd in group])

        out.append(_FaceStack(_Across(a), *(cat(name) for name in ("usable", "cos", "d", "nrm", "sag")),
                              *({side: cat(name, side) for side in (-1, +1)} for name in ("fr", "lens", "tangents")),
                              tuple(fd.n for fd in group), tuple(len(fd.cos) for fd in group)))
    return out


def _fits_each(stacks, s, lean=True, limit=True):
    """{face number: _fits(face, s, lean, limit)} of every face of _stacks(data), a stack per call: placement asks this
    of every face three times, and ~8k calls of _fits on small arrays were 1.1 s of the 1024-piece build."""
    out = {}
    for st in stacks:
        ok = _fits(st, s, lean, limit)
        out.update(zip(st.numbers, np.split(ok, np.cumsum(st.sizes)[:-1]), strict=True))
    return out


def _room_score(fd):
    """(k,) mm from the point to the nearest edge of the face over both cells, times the cosine of the lean: the
    roomiest, straightest point first."""
    a = fd.face.axis
    b, c = _cyclic(a)
    room = np.full(len(fd.cos), np.inf)
    for side in (-1, +1):
        fr, lens = fd.fr[side], fd.lens[side]
        for x in (b, c):
            room = np.minimum(room, np.minimum(fr[:, x], 1.0 - fr[:, x]) * lens[:, x])
    return room * np.maximum(fd.cos, 0.0)


def _segments(fd, s, side):
    """The joint's cylinder inside the cell on `side`: from points p0 (k, 3) to p1 (k, 3), radius rho."""
    depth, way, rho = _intrusion(fd, s, side)
    p1 = fd.x + (way * depth)[:, None] * fd.d
    return fd.x, p1, rho


def _size_steps(sizes, r_min, l_min):
    """The sizes a face tries, largest first: the asked one, then radii 15% smaller each down to r_min, the length
    shrinking with the radius down to l_min."""
    out = [sizes]
    r = sizes.radius
    while r > r_min + 1e-9:
        r = max(r_min, _round_down(r * 0.85, 0.05))
        length = max(l_min, _round_down(sizes.length * r / sizes.radius, 0.05))
        out.append(sizes.scaled(r, min(length, sizes.length)))
    return out


def _largest_fit(fd, sizes, r_hi, l_min, lean=False):
    """Largest radius (0.1 mm steps) below r_hi at which some point of the face fits alone, with length l_min;
    0 if none."""
    def fits(r):
        return bool(_fits(fd, sizes.scaled(r, l_min), lean).any())

    if not fits(0.1):
        return 0.0
    lo, hi = 0.1, r_hi
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return _round_down(lo)


def _split_dirs(tiling, fmap, plan):
    """{face number: unit mm direction from its lower to its upper cell} along the sliding direction of the one
    split of the plan that parts the face's two cells."""
    from .assembly import parted_faces, split_directions

    out = {}
    for (d, _), step in zip(split_directions(tiling, fmap, plan), plan.steps, strict=True):
        if np.any(d):
            for n, sign in parted_faces(tiling, step.moving, step.fixed):
                out[n] = d if sign > 0 else -d
    return out


_SIX_FACES = tuple((ax, e) for ax in range(3) for e in (0, 1))  # a cell's faces: (axis, 0 min side | 1 max side)


class _Sides:
    """The real side faces of the cells, sampled in mm, to measure a placed joint against: _fits judges a point by the
    lengths of the cell's parameter lines, as if F ran at an even speed along them and the cell were straight; near a
    pole, where a cell narrows to a wedge, a leaning pin then broke 3.6 mm^3 into the piece beside its hole."""

    def __init__(self, tiling, fmap, count=16):
        self.tiling, self.fmap, self.count = tiling, fmap, count
        self._faces, self._clear = {}, {}
        self._shared = {}  # a face's parameter box -> its samples: two cells share a face, evaluated once
        self._cells = {}  # cell -> its faces stacked (_cell)
        g = np.linspace(0.0, 1.0, count)
        self._st = np.repeat(g, count), np.tile(g, count)
        edge = np.zeros((count, count), bool)
        edge[[0, -1], :] = edge[:, [0, -1]] = True
        self._inner = ~edge.ravel()
        self._inner.setflags(write=False)

    def _face(self, idx, axis, end):
        """Points (m, 3), unit normals (m, 3) (zero where collapsed), interior (m,) and box (2, 3) of a cell's face
        (all six of a cell evaluated at once, on first use; a face the cell beside it evaluated is taken from it)."""
        idx = tuple(idx)
        if idx not in self._faces:
            cell = self.tiling.cells[idx]
            lo, hi = cell.box
            keys = {(ax, e): cell.face_key(ax, e) for ax, e in _SIX_FACES}
            missing = [f for f in _SIX_FACES if keys[f] not in self._shared]
            if missing:
                m = self.count * self.count
                uvw = np.empty((len(missing), m, 3))
                for f, (ax, e) in enumerate(missing):
                    b, c = _cyclic(ax)
                    uvw[f, :, ax] = hi[ax] if e else lo[ax]
                    uvw[f, :, b] = lo[b] + self._st[0] * (hi[b] - lo[b])
                    uvw[f, :, c] = lo[c] + self._st[1] * (hi[c] - lo[c])
                x, jac = self.fmap.evaluate_with_jacobian(uvw.reshape(-1, 3))
                n = len(missing)
                x, jac = x.reshape(n, m, 3), jac.reshape(n, m, 3, 3).transpose(0, 3, 1, 2)  # (face, d/d axis, m, 3)
                across = np.array([_cyclic(ax) for ax, _ in missing])
                nrm = np.cross(jac[np.arange(n), across[:, 0]], jac[np.arange(n), across[:, 1]])
                size = np.linalg.norm(nrm, axis=2)
                real = size > 1e-9 * np.maximum(size.max(axis=1), 1e-300)[:, None]
                nrm = np.where(real[..., None], nrm / np.maximum(size, 1e-300)[..., None], 0.0)
                boxes = np.stack([x.min(axis=1), x.max(axis=1)], axis=1)
                for f, face in enumerate(missing):
                    self._shared[keys[face]] = (x[f], nrm[f], self._inner, boxes[f])
            self._faces[idx] = {f: self._shared[keys[f]] for f in _SIX_FACES}
        return self._faces[idx][(axis, end)]

    def _cell(self, idx):
        """The cell's six faces stacked in _SIX_FACES order: points (6, m, 3), normals (6, m, 3), interior (6, m) and
        boxes (6, 2, 3); made on first use. Placing the joints of 1024 pieces measures ~6k point sets, and stacking
        the faces of each anew was a fifth of that."""
        idx = tuple(idx)
        got = self._cells.get(idx)
        if got is None:
            faces = [self._face(idx, axis, end) for axis, end in _SIX_FACES]
            got = self._cells[idx] = tuple(np.stack(parts) for parts in zip(*faces, strict=True))
        return got

    def distance(self, idx, keep_out, p, beyond=np.inf):
        """mm (n,) from points p (n, 3) to the nearest of the cell's faces other than keep_out (axis, end): across the
        tangent plane of the nearest sample inside a face, straight to a sample on its rim. Faces whose box lies
        `beyond` mm or more from the points' box are skipped (their distance counts as inf)."""
        x, nrm, inner, boxes = self._cell(idx)
        lo, hi = p.min(axis=0), p.max(axis=0)
        gap = np.maximum(np.maximum(boxes[:, 0] - hi, lo - boxes[:, 1]), 0.0)
        # sqrt(g . g) is np.linalg.norm's own sum, without its checks
        use = np.array([face != keep_out and math.sqrt(g.dot(g)) < beyond
                        for face, g in zip(_SIX_FACES, gap, strict=True)])
        if not use.any():
            return np.full(len(p), np.inf)
        from ._joint_kernels import face_distance

        return face_distance(np.ascontiguousarray(p, dtype=float), x, nrm, inner, use)

    def clear(self, fd, k, s):
        """Whether the joint at point k of face fd at size s keeps its radius and SIDE_WALL of a wall to every other
        face of both its cells along its whole length (the hole in the upper cell, the pin's base in the lower)."""
        key = (fd.n, k, s, tuple(np.round(fd.d[k], 9)))  # placement tries again what the plan already asked
        if key in self._clear:
            return self._clear[key]
        a = fd.face.axis
        out = True
        for side, idx, keep_out in ((-1, fd.face.lower, (a, 1)), (+1, fd.face.upper, (a, 0))):
            depth, way, rho = _intrusion(fd, s, side)
            need = rho + SIDE_WALL * s.wall - 1e-9
            t = np.linspace(0.0, float(depth[k]), 7)
            p = fd.x[k][None, :] + (way * t)[:, None] * fd.d[k][None, :]
            if float(self.distance(idx, keep_out, p, beyond=need).min()) < need:
                out = False
                break
        self._clear[key] = out
        return out


@dataclass(frozen=True, eq=False)
class _Setup:
    """What placing joints on a tiling starts from: the asked sizes, the smallest a pin may shrink to, the sizes
    tried largest first, and the faces' shapes (tiling.faces order)."""

    sizes: _Sizes
    r_min: float
    l_min: float
    steps: tuple
    shapes: list
    space: str
    sides: _Sides
    lengths: _Geometry

    def holds(self, n, direction):
        """Whether face number n holds the smallest pin (alone) pointing along the unit mm direction (3,) from its
        lower cell to its upper one: what an assembly plan asks of a split's direction."""
        shape = self.shapes[n]
        if not np.any(shape.nrm[shape.usable] @ np.asarray(direction, float) >= _COS_TILT - 1e-12):
            return False  # leaning too far everywhere: what _fits finds last, at a fraction of its cost
        fd = _directed(shape, direction)
        ok = _fits(fd, self.steps[-1])
        # the roomiest few points that fit are measured against the real side faces, as placement will
        for k in np.argsort(-np.where(ok, _room_score(fd), -np.inf))[:min(int(ok.sum()), 4)]:
            if self.sides.clear(fd, int(k), self.steps[-1]):
                return True
        return False


def _setup(tiling, fmap, joint_spec):
    """The _Setup of place_joints for a spec.JointSpec whose style is not none. Raises SpecError for sizes that are
    not positive."""
    cell_lengths = _measure(tiling, fmap)
    r_given, l_given = joint_spec.radius, joint_spec.length
    r_def, l_def = default_sizes(tiling, fmap, cell_lengths)
    sizes = _Sizes(float(r_def if r_given is None else r_given), float(l_def if l_given is None else l_given),
                   float(joint_spec.clearance), float(joint_spec.axial_clearance), joint_spec.style, joint_spec.shape)
    r_min, l_min = float(joint_spec.min_radius), float(joint_spec.min_length)
    problems = []
    for key, v, low in (("radius", sizes.radius, 0.0), ("length", sizes.length, 0.0),
                        ("clearance", sizes.clearance, -1e-12), ("axial_clearance", sizes.axial_clearance, -1e-12),
                        ("min_radius", r_min, 0.0), ("min_length", l_min, 0.0)):
        if not np.isfinite(v) or v <= low:
            problems.append(f"joints.{key}: must be {'positive' if low == 0 else 'zero or more'} (got {v:g})")
    if problems:
        raise SpecError(problems)
    # never shrink below what was asked, when that is smaller than the minimum
    r_min, l_min = min(r_min, sizes.radius), min(l_min, sizes.length)
    return _Setup(sizes, r_min, l_min, tuple(_size_steps(sizes, r_min, l_min)),
                  _face_shapes(tiling, fmap, cell_lengths, sizes.reach), joint_spec.space, _Sides(tiling, fmap),
                  cell_lengths)


def place_joints(tiling, fmap, joint_spec=None, plan=None):
    """A joint on every shared face with room for one -> Layout (joints, one contact record per face).

    joint_spec: spec.JointSpec (None: its defaults; radius and length None are derived here); plan:
    volpuzzle.assembly.AssemblyPlan, whose splits set the pins' directions and whose faces are placed first (None:
    pins normal to their faces). Raises SpecError for sizes that are not positive; a face without room is not an error
    here (see require_joined).
    """
    joint_spec = joint_spec if joint_spec is not None else JointSpec()
    style = joint_spec.style
    if style == "none" or not tiling.faces:
        return Layout((), tuple(_contact(f, False, None, "joints.style is none" if style == "none" else None)
                                for f in tiling.faces))
    return _place(tiling, fmap, _setup(tiling, fmap, joint_spec), plan)


def _place(tiling, fmap, setup, plan):
    """place_joints on a _Setup."""
    sizes, r_min, l_min, steps, space = setup.sizes, setup.r_min, setup.l_min, list(setup.steps), setup.space
    dirs = _split_dirs(tiling, fmap, plan) if plan is not None else {}
    data = [_directed(shape, dirs.get(shape.n)) for shape in setup.shapes]
    first = {n for n, _ in plan.faces_with_joints} if plan is not None else set()
    smallest = steps[-1]
    stacks = _stacks(data)
    alone = {n: int(ok.sum()) for n, ok in _fits_each(stacks, smallest).items()}
    order = sorted(range(len(data)), key=lambda n: (n not in first, alone[n], n))
    cells = list(tiling.cells)
    # the reruns below place the same faces at the same sizes again; every face is tried at the asked size first
    memo = {(n, 0): _fit_entry(data[n], ok, steps[0]) for n, ok in _fits_each(stacks, steps[0]).items()}
    upright = _fits_each(stacks, smallest, lean=False)
    del stacks
    chosen = _greedy(data, steps, order, cells, setup.sides, memo)
    for _ in range(4):
        # a face that shrank or got nothing goes first next time, kept if the puzzle is better for it
        late = [n for n in order if n not in chosen or chosen[n][1] is not sizes]
        if not late:
            break
        order = sorted(order, key=lambda n: n not in late)
        again = _greedy(data, steps, order, cells, setup.sides, memo)
        if _cost(again, sizes, data, cells) >= _cost(chosen, sizes, data, cells):
            break
        chosen = again

    joints, contacts = [], []
    for n, fd in enumerate(data):
        f = fd.face
        room = bool(upright[n].any())
        if n not in chosen:
            contacts.append(_contact(f, room, None, _why_not(fd, smallest, room, r_min, l_min, setup.sides)))
            continue
        k, s = chosen[n]
        base = float(_base(fd, s)[k])
        cos = float(fd.cos[k])
        j = Joint(
            pin_cell=tuple(f.lower), hole_cell=tuple(f.upper), axis=f.axis, across_seam=f.seam is not None,
            center=_readonly(fd.x[k]), direction=_readonly(fd.d[k] / np.linalg.norm(fd.d[k])), radius=s.radius,
            length=s.length, clearance=s.clearance, axial_clearance=s.axial_clearance, shape=s.shape, style=s.style,
            space=space, uvw_pin=_readonly(fd.uvw[-1][k]), uvw_hole=_readonly(fd.uvw[+1][k]),
            base_depth=round(base, 4), jacobian_pin=_readonly(fd.jac[-1][k]), jacobian_hole=_readonly(fd.jac[+1][k]),
            tilt_deg=float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))),
            shrunk=bool(s.radius < sizes.radius or s.length < sizes.length))
        joints.append(j)
        contacts.append(_contact(f, True, j, None))
    return Layout(tuple(joints), tuple(contacts),
                  {"radius_mm": sizes.radius, "length_mm": sizes.length, "min_radius_mm": r_min,
                   "min_length_mm": l_min})


def _greedy(data, steps, order, cells, sides=None, memo=None):
    """Faces in `order`, each at its roomiest point that fits and keeps a wall to the joints already placed in its two
    cells, at the largest size of `steps` that has such a point -> {face number: (point index, _Sizes)}. sides
    (_Sides): the point is also measured against the cells' real side faces. memo: a dict kept between calls on the
    same data and steps, for what does not depend on the joints placed (_fit_of)."""
    memo = {} if memo is None else memo
    inside = {idx: [] for idx in cells}  # cell -> [(p0, p1, radius)] of the joints already placed in it
    chosen = {}
    for n in order:
        fd = data[n]
        for i, s in enumerate(steps):
            fit, score, segs = _fit_of(memo, fd, i, s)
            if fit is None:
                continue
            ok = fit.copy()
            for side, idx in ((-1, fd.face.lower), (+1, fd.face.upper)):
                if inside[idx] and ok.any():
                    ok &= segs[side].apart_all(inside[idx], s.wall)
            while ok.any():
                k = int(np.argmax(np.where(ok, score, -np.inf)))
                if sides is None or sides.clear(fd, k, s):
                    break
                ok[k] = False
            if ok.any():
                chosen[n] = (k, s)
                for side, idx in ((-1, fd.face.lower), (+1, fd.face.upper)):
                    cyl = segs[side]
                    inside[idx].append((cyl.p0[k].copy(), cyl.p1[k].copy(), cyl.rp))
                break
    return chosen


def _fit_of(memo, fd, i, s):
    """(_fits (k,) or None where no point fits, _room_score (k,), {side: _Cylinders}) of face fd at size s = steps[i],
    computed once per memo: what _greedy asks of a face whatever joints are placed already."""
    key = (fd.n, i)
    if key not in memo:
        memo[key] = _fit_entry(fd, _fits(fd, s), s)
    return memo[key]


def _fit_entry(fd, ok, s):
    """_fit_of's entry of face fd at size s from its _fits ok (k,)."""
    if not ok.any():
        return None, None, None
    return ok, _room_score(fd), {side: _Cylinders(*_segments(fd, s, side)) for side in (-1, +1)}


class _Cylinders:
    """Cylinders of axes p0 -> p1 (k, 3) and radius rp, each tested against the joints already placed (apart_all)."""

    __slots__ = ("p0", "p1", "rp")

    def __init__(self, p0, p1, rp):
        self.p0 = np.ascontiguousarray(p0, dtype=float)
        self.p1 = np.ascontiguousarray(p1, dtype=float)
        self.rp = float(rp)

    def apart_all(self, others, gap):
        """(k,) bool: each of these cylinders is at least gap apart from every one of others [(q0 (3,), q1 (3,),
        rq)]: their axes are that far beyond both radii, or one lies wholly that far beyond an end plane of the
        other."""
        q0 = np.array([q[0] for q in others], dtype=float).reshape(-1, 3)
        q1 = np.array([q[1] for q in others], dtype=float).reshape(-1, 3)
        rq = np.array([q[2] for q in others], dtype=float)
        from ._joint_kernels import cylinders_apart

        return cylinders_apart(self.p0, self.p1, self.rp, q0, q1, rq, float(gap))


def _cost(chosen, sizes, data, cells):
    """(parts of the joint graph and loose cells, faces without a joint, faces with a smaller one, mm of radius
    given up): less is better."""
    parts, loose = joint_graph(cells, [(data[n].face.lower, data[n].face.upper) for n in chosen])
    small = [s for _, s in chosen.values() if s is not sizes]
    return (len(parts) + len(loose), len(data) - len(chosen), len(small),
            round(sum(sizes.radius - s.radius for s in small), 6))


def _why_not(fd, smallest, room, r_min, l_min, sides=None):
    """One sentence: why face fd carries no joint."""
    if not fd.usable.any():
        return "no room: the face is collapsed (a pole), or its split slides along it: at most 0 mm"
    if not room:
        best, length = 0.0, l_min
        for share in (1.0, 0.75, 0.5, 0.35):  # too shallow for l_min: what a shorter pin could be
            length = _round_down(share * l_min)
            best = _largest_fit(fd, smallest, r_min, length)
            if best > 0 and _fits_sides(fd, smallest.scaled(best, length), sides):
                break
            best = 0.0
        size = f"{best:g} mm" + (f" and {length:g} mm long" if best > 0 and length < l_min else "")
        return (f"no room: the face holds a pin of radius at most {size} with its clearance and wall, less "
                f"than the smallest allowed, {r_min:g} mm and {l_min:g} mm long")
    if not _fits(fd, smallest).any():
        leaning = _fits(fd, smallest, limit=False)
        if not leaning.any():
            lean = float(np.degrees(np.arccos(np.clip(fd.cos[fd.usable].max(), -1.0, 1.0))))
            return (f"tilt: its split slides {np.floor(lean * 10) / 10:g} deg or more off the face's normal, and a pin "
                    f"leaning that far needs more room than the face has")
        lean = float(np.degrees(np.arccos(np.clip(fd.cos[leaning].max(), -1.0, 1.0))))
        return (f"tilt: its split slides at least {np.floor(lean * 10) / 10:g} deg off the face's normal where a pin "
                f"fits, more than the {MAX_TILT_DEG:g} deg a straight pin may lean")
    ok = _fits(fd, smallest)
    if sides is not None and not any(sides.clear(fd, int(k), smallest) for k in np.flatnonzero(ok)):
        return (f"no room: where a pin of {smallest.radius:g} mm fits the face, it or its hole would come within "
                f"{SIDE_WALL * smallest.wall:g} mm of another face of {piece_id(fd.face.lower)} or "
                f"{piece_id(fd.face.upper)} (the pieces bend or narrow there)")
    return (f"crowded: every spot with room meets another joint of {piece_id(fd.face.lower)} or "
            f"{piece_id(fd.face.upper)}")


def _fits_sides(fd, s, sides):
    """Whether the face holds a pin of size s alone at some point, measured on the real side faces too (sides None:
    by _fits only)."""
    ok = _fits(fd, s, lean=False)
    return bool(ok.any()) and (sides is None or any(sides.clear(fd, int(k), s) for k in np.flatnonzero(ok)))


def _contact(f, room, joint, reason):
    out = {"pieces": [piece_id(f.lower), piece_id(f.upper)], "axis": AXES[f.axis],
           "across_seam": f.seam is not None, "room": bool(room), "pinned": joint is not None, "reason": reason}
    if joint is not None:
        out["radius_mm"] = float(joint.radius)
        out["length_mm"] = float(joint.length)
    return out


def plan_joints(tiling, fmap, joint_spec=None, plan=None):
    """The joints of place_joints (list of Joint): one on every face with room, pins on the lower cell; [] for style
    none."""
    return list(place_joints(tiling, fmap, joint_spec, plan).joints)


# ---------------------------------------------------------------------------------------------------------------------
# The joint graph: pieces as nodes, joints as edges


def joints_by_cell(joints):
    """{cell index: numbers (ascending) into `joints` of those with the cell on their pin or hole side}: what the
    per-cell questions of label and the assembly replay look at, so that their cost per piece does not grow with the
    number of pieces."""
    out = {}
    for k, j in enumerate(joints or ()):
        pin, hole = tuple(j.pin_cell), tuple(j.hole_cell)
        out.setdefault(pin, []).append(k)
        if hole != pin:
            out.setdefault(hole, []).append(k)
    return out


def cell_joints(joints):
    """{cell index: its joints (in `joints` order)}, pin side or hole side: joints_by_cell as the joints themselves,
    for loops over the pieces that would otherwise scan every joint for each piece (pieces x joints)."""
    joints = list(joints or ())
    return {cell: [joints[k] for k in ks] for cell, ks in joints_by_cell(joints).items()}


def joint_graph(piece_ids, edges):
    """piece_ids: iterable of ids; edges: iterable of (id, id) -> (parts: list of sorted id lists, largest first;
    loose: sorted ids with no joint)."""
    ids = sorted(set(piece_ids))
    parent = {p: p for p in ids}

    def root(p):
        while parent[p] != p:
            parent[p] = parent[parent[p]]
            p = parent[p]
        return p

    touched = set()
    for a, b in edges:
        if a in parent and b in parent:
            parent[root(a)] = root(b)
            touched |= {a, b}
    groups = {}
    for p in ids:
        groups.setdefault(root(p), []).append(p)
    parts = sorted(groups.values(), key=lambda g: (-len(g), g))
    return parts, sorted(set(ids) - touched)


def graph_problem(piece_ids, edges, contacts=(), style="pin", allow=(), grid=None, roomy=None, randomized=True):
    """One line saying why the puzzle does not hold together (a piece without a joint, or more than one part), with
    what would fit; None when it holds, for style none, or when joints.allow has 'loose'. contacts: report records
    (Layout.contacts) whose reasons explain it; roomy: (grid, radius, length) of a coarser grid whose cells have room
    for the smallest pin (coarser_grid), named when a contact has no room; randomized: whether a warp R bends the
    cuts (only then is a smaller randomize.amplitude advice)."""
    if style == "none" or "loose" in tuple(allow):
        return None
    ids = sorted(set(piece_ids))
    if len(ids) < 2:
        return None
    parts, loose = joint_graph(ids, edges)
    if not loose and len(parts) == 1:
        return None
    stray = loose[:1] or parts[-1]
    mine = [c for c in contacts if set(c.get("pieces", ())) & set(stray)
            and not set(c.get("pieces", ())) <= set(stray) and not c.get("pinned")]
    reasons = [c.get("reason") or "" for c in mine]
    # the advice answers the reason the message shows: a grid coarse enough for room can still be crowded (the
    # 4x4x64 twisted torus names crowding first; the grid its 'no room' faces would ask for, 4x4x47, is crowded too)
    shown_reason = next((r for r in reasons if r), "")
    advice = "a coarser grid, or joints.allow: [loose]"
    if shown_reason.startswith("no room"):
        fits = [_fit_in(r) for r in reasons if r.startswith("no room")]
        best, length = max(fits)
        if roomy is not None:
            advice = (f"grid {list(roomy[0])} or coarser (cells with room for a pin of {roomy[1]:g} mm by "
                      f"{roomy[2]:g} mm), or joints.allow: [loose]")
        size = f"joints.min_radius at most {best:g}" + (f" and joints.min_length at most {length:g}" if length else "")
        advice = (f"{size} there, " if best > 0 else "") + advice
    elif shown_reason.startswith("crowded"):
        # the other joints of its pieces crowd it: smaller joints or larger cells make room (the 4x4x64 twisted
        # torus stays crowded with joints.radius 1 at 150 mm and builds at model.size 300)
        advice = "a smaller joints.radius, a larger model.size, " + advice
    elif shown_reason.startswith("tilt"):
        # smaller blocks have flatter splits; a bumpy warp tilts them further
        advice = ("more pieces along the curved axis" + (" or a smaller randomize.amplitude" if randomized else "")
                  + ", or joints.allow: [loose]")
    why = next((f"between {c['pieces'][0]} and {c['pieces'][1]}, {c['reason']}" for c in mine if c.get("reason")),
               "no joint was placed on its contacts")
    got = f"grid {list(grid)}" if grid is not None else f"{len(parts)} parts"
    if loose:
        head = f"joints: piece {stray[0]} gets no joint" + (f" (and {len(loose) - 1} more)" if len(loose) > 1 else "")
    else:
        shown = ", ".join(stray[:4]) + (", ..." if len(stray) > 4 else "")
        head = f"joints: the puzzle falls apart into {len(parts)} parts ({shown} hold to the rest by no joint)"
    return f"{head}; {why} (got {got}, expected {advice})"


def _fit_in(reason):
    """(radius, length or None) mm of the pin a 'no room' reason (_why_not) says its face holds; (0, None) when it
    names no size (the pin's spot comes too close to another face of its pieces)."""
    if "at most " not in reason:
        return 0.0, None
    size = reason.split("at most ")[1].split(" with ")[0]
    radius = float(size.split(" mm")[0])
    return radius, (float(size.split(" and ")[1].split(" mm")[0]) if " and " in size else None)


def coarser_grid(tiling, setup):
    """(grid, radius, length): the grid, at most tiling.grid along every axis, whose cells would have room for the
    smallest pin of setup (its footprint with clearance and a wall each side, and its hole with room behind it),
    judged by the narrowest cell's middle line along each axis scaled by the change of count; None when the grid
    already has that room or no coarser one would (a single cell along the axis)."""
    s = setup.steps[-1]
    # across the face: the footprint and a wall each side (_fits); along the pin: the hole and, from its axis, its
    # radius and a share of a wall to the cell's far face (_Sides), the stricter of the two
    need = max(2.0 * (s.reach + s.wall), s.hole_depth + s.wall, s.hole_depth + s.reach + SIDE_WALL * s.wall)
    grid = [int(g) for g in tiling.grid]
    out = list(grid)
    for x in range(3):
        if grid[x] < 2:
            continue
        narrowest = min(_center_len(setup.lengths, idx, x) for idx in tiling.cells)
        if narrowest < need:
            out[x] = max(1, int(np.floor(grid[x] * narrowest / need)))
    return (tuple(out), s.radius, s.length) if out != grid else None


def require_joined(tiling, layout, joint_spec=None, roomy=None, randomized=True):
    """Raise SpecError (one line) unless every cell has a joint and the joints join all cells into one part; style
    none and joints.allow: [loose] excepted. joint_spec: spec.JointSpec (None: its defaults); roomy: coarser_grid's
    answer, named in the message."""
    joint_spec = joint_spec if joint_spec is not None else JointSpec()
    problem = graph_problem([piece_id(c) for c in tiling.cells],
                            [(piece_id(j.pin_cell), piece_id(j.hole_cell)) for j in layout.joints],
                            layout.contacts, joint_spec.style, tuple(joint_spec.allow), tiling.grid, roomy,
                            randomized)
    if problem:
        raise SpecError(problem)


def report_figures(report):
    """The joint figures of a build's report dict: touching pairs, with room, pinned, loose pieces, joint-graph parts,
    largest and smallest piece volume (mm^3). Touching pairs and room are None when the report lists no contacts."""
    pieces = report.get("pieces") or []
    ids = [p.get("id") for p in pieces]
    joints = report.get("joints") or []
    parts, loose = joint_graph(ids, [(j.get("pin_piece"), j.get("hole_piece")) for j in joints])
    contacts = report.get("contacts")
    if contacts is None:  # mesh mode lists its contacts with the mesh's own figures
        contacts = (report.get("mesh") or {}).get("contacts")
    vols = [float(p["volume_mm3"]) for p in pieces if p.get("volume_mm3") is not None]
    return {
        "pieces": len(ids),
        "touching_pairs": None if contacts is None else len(contacts),
        "with_room": None if contacts is None else sum(1 for c in contacts if c.get("room")),
        "pinned": None if contacts is None else sum(1 for c in contacts if c.get("pinned")),
        "pinned_with_room": None if contacts is None else sum(1 for c in contacts if c.get("room") and c.get("pinned")),
        "joints": len(joints),
        "pieces_without_joint": loose,
        "parts": len(parts),
        "largest_volume_mm3": max(vols) if vols else None,
        "smallest_volume_mm3": min(vols) if vols else None,
    }


# ---------------------------------------------------------------------------------------------------------------------
# Solids


def _manifold():
    import manifold3d

    return manifold3d


def _frame(j, flip=False):
    """3x4 rigid transform: local z -> the joint's direction (reversed if flip), origin -> its centre."""
    e1, e2, n = frame_from_direction(np.asarray(j.direction, dtype=float) * (-1.0 if flip else 1.0))
    m = np.zeros((3, 4))
    m[:, 0], m[:, 1], m[:, 2], m[:, 3] = e1, e2, n, j.center
    return m


def _snap_profile(r, length, base, grow=0.0, extra=0.0):
    """(radius, z) points of the snap pin from z = -base to the tip: straight, swelling to 1.15 r at 70% length,
    necking to 0.9 r near the tip, then a chamfer. grow widens it radially, extra lengthens the tip (for the hole)."""
    t = np.array([0.0, 0.2, 0.4, 0.46, 0.52, 0.58, 0.64, 0.7, 0.75, 0.8, 0.85, 0.9, 1.0])
    zs = np.concatenate([[-base], t * length])

    def radius(z):
        t = z / length
        if t <= 0.4:
            return r
        if t <= 0.7:
            return r + (SNAP_SWELL - 1.0) * r * 0.5 * (1 - np.cos(np.pi * (t - 0.4) / 0.3))
        if t <= 0.9:
            return SNAP_SWELL * r + (0.9 - SNAP_SWELL) * r * 0.5 * (1 - np.cos(np.pi * (t - 0.7) / 0.2))
        return 0.9 * r - (t - 0.9) / 0.1 * min(0.2 * r, 0.1 * length)  # chamfer

    pts = [(radius(max(z, 0.0)) + grow, z) for z in zs]
    pts[-1] = (pts[-1][0], length + extra)
    return pts


def _local_solid(j, radius, z0, z1, grow=0.0, extra=0.0):
    """The joint's solid in its local frame (axis z), from z0 to z1 (before extra)."""
    m3 = _manifold()
    seg = j.segments
    if j.shape == "snap":
        prof = _snap_profile(j.radius, j.length, -z0, grow=grow, extra=extra)
        poly = np.array([(0.0, z0)] + prof + [(0.0, prof[-1][1])], dtype=float)
        solid = m3.Manifold.revolve(m3.CrossSection([poly]), seg)
    else:
        solid = m3.Manifold.cylinder(z1 + extra - z0, radius, -1.0, seg).translate([0.0, 0.0, z0])
    return solid


def pin_solid(j):
    """What is added to the pin cell (Manifold, mm): from base_depth behind the face to `length` in front."""
    if j.style != "pin":
        raise GeometryError(f"joint {piece_id(j.pin_cell)}-{piece_id(j.hole_cell)}: style {j.style} has no pin")
    s = _local_solid(j, j.radius, -j.base_depth, j.length).transform(_frame(j))
    return check_status(s, f"pin of {piece_id(j.pin_cell)}", "building its solid")


def _hole_local(j):
    return _local_solid(j, j.radius + j.clearance, -j.base_depth, j.length, grow=j.clearance, extra=j.axial_clearance)


def hole_solid(j, cell_index):
    """What is subtracted from cell_index (Manifold, mm): radius + clearance, depth length + axial_clearance into the
    cell, starting base_depth outside it. With style dowel the pin cell gets one too, reaching back into it."""
    idx = tuple(cell_index)
    if idx == j.hole_cell:
        frame = _frame(j)
    elif idx == j.pin_cell and j.style == "dowel":
        frame = _frame(j, flip=True)
    else:
        raise GeometryError(f"joint {piece_id(j.pin_cell)}-{piece_id(j.hole_cell)} makes no hole in {piece_id(idx)}")
    return check_status(_hole_local(j).transform(frame), f"hole in {piece_id(idx)}", "building its solid")


def dowel_solid(j):
    """The loose dowel (Manifold, mm) in its assembled place: radius r, length 2 * length, centred on the face."""
    s = _local_solid(j, j.radius, -j.length, j.length)
    if j.shape == "snap":  # a dowel is plain: it must slide into both holes
        m3 = _manifold()
        s = m3.Manifold.cylinder(2 * j.length, j.radius, -1.0, j.segments).translate([0.0, 0.0, -j.length])
    what = f"dowel between {piece_id(j.pin_cell)} and {piece_id(j.hole_cell)}"
    return check_status(s.transform(_frame(j)), what, "building its solid")


def _domain_transform(j, uvw, jac, flip=False):
    """3x4 map local -> parameters: the physical frame, then the inverse Jacobian at uvw (F^-1 to first order)."""
    fr = _frame(j, flip=flip)
    m = np.zeros((3, 4))
    m[:, :3] = np.linalg.inv(np.asarray(jac, dtype=float)) @ fr[:, :3]
    m[:, 3] = uvw
    return m


def pin_solid_domain(j):
    """The pin in parameter space (Manifold, uvw units), to be composed with the pin cell through F. Sized by the
    Jacobian at the face point: about the requested mm there, distorted away from it (the paper's Fig. 16)."""
    if j.style != "pin":
        raise GeometryError(f"joint {piece_id(j.pin_cell)}-{piece_id(j.hole_cell)}: style {j.style} has no pin")
    m = _domain_transform(j, j.uvw_pin, j.jacobian_pin)
    solid = _local_solid(j, j.radius, -j.base_depth, j.length).transform(m)
    return check_status(solid, f"domain pin of {piece_id(j.pin_cell)}", "building its solid")


def hole_solid_domain(j, cell_index):
    """The hole in cell_index's parameter frame (Manifold, uvw units); across a seam the hole cell's own parameters."""
    idx = tuple(cell_index)
    if idx == j.hole_cell:
        m = _domain_transform(j, j.uvw_hole, j.jacobian_hole)
    elif idx == j.pin_cell and j.style == "dowel":
        m = _domain_transform(j, j.uvw_pin, j.jacobian_pin, flip=True)
    else:
        raise GeometryError(f"joint {piece_id(j.pin_cell)}-{piece_id(j.hole_cell)} makes no hole in {piece_id(idx)}")
    return check_status(_hole_local(j).transform(m), f"domain hole in {piece_id(idx)}", "building its solid")


def require_pieces_joined(spec, pieces, joints, contacts):
    """The final pieces must all carry a joint and hang together (volpuzzle.joint.graph_problem), unless allowed."""
    problem = graph_problem([p.id for p in pieces], [(piece_id(j.pin_cell), piece_id(j.hole_cell)) for j in joints],
                            contacts or (), spec.joints.style, spec.joints.allow, spec.grid)
    if problem:
        raise SpecError(problem, source=spec.source)


def dowel_parts(joints):
    """[(name, Trimesh)] the loose dowels of dowel joints, printed beside the pieces ("dowel-00", ...)."""
    from .geometry import to_trimesh

    return [(f"dowel-{i:02d}", to_trimesh(dowel_solid(j))) for i, j in enumerate(joints)]


def place_planned_joints(tiling, fmap, joint_spec):
    """The joint stage of a volume model -> (Layout, assembly.AssemblyPlan with its joints, or None for style none or
    a single cell). Raises SpecError unless every cell is joined (require_joined).

    With straight pins and bumpy cut faces a jointed face can only part along its pins, so the assembly is planned
    first (blocks that slide apart) and every pin of a split points along its sliding direction.
    """
    setup = None
    if joint_spec.style == "none" or not tiling.faces:
        layout, plan = place_joints(tiling, fmap, joint_spec), None
    else:
        from .assembly import plan_assembly

        # the plan is searched for splits whose sliding directions its faces can hold pins along
        setup = _setup(tiling, fmap, joint_spec)
        plan = plan_assembly(tiling, fmap, holds=setup.holds)
        layout = _place(tiling, fmap, setup, plan)
    if plan is not None:
        from .assembly import with_joints

        plan = with_joints(plan, tiling, list(layout.joints))
    roomy = None
    if setup is not None and any(c["reason"] and c["reason"].startswith("no room") for c in layout.contacts):
        roomy = coarser_grid(tiling, setup)
    require_joined(tiling, layout, joint_spec, roomy, randomized=fmap.warp is not None)
    return layout, plan
