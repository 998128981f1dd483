"""joint: one pin (or dowel) per shared face, placed so that the pins and holes of a piece never meet.

Placement. A face along axis a joins its `lower` cell (pin) to its `upper` cell (hole), so the pin always points along
+a, also across a periodic seam (the last cell along a carries the pin). Every cell then has at most one pin on each of
its three max faces and one hole on each of its three min faces: at most three of each.

Inside one piece the joint solids of two different axes a, b (third axis c) are kept apart by one of
  - a lateral offset: their lines differ in c by at least 2 (radius + clearance) + a wall, so the axes are skew, or
  - depth: the a-joints reach only `length + axial_clearance` (or `base_depth`) into the piece from its a-faces, and
    the b-joint crosses the piece at an a-level beyond that.
Each axis gets one offset pattern on its faces, (k_b, k_c) in {-1, 0, 1}^2 steps of that separation; the cheapest
pattern for which every pair in every piece is apart (including holes moved by a seam's swap or flip), and every pin
circle stays a wall inside its face, wins. Joints of one axis in one piece (pin base on the max face, hole on the min
face) are kept apart by depth: their intrusions plus a wall must fit in the piece's depth.

Space. 'physical' (default): the joint is a straight cylinder in mm, centred where F maps the face parameter and
perpendicular to the mapped face, so radius, length and clearances hold in the printed object. 'domain': the pin is
built in the parameter domain and composed with the piece through F, as the paper does; it is sized by the Jacobian at
the face point, so it is right only to first order and is distorted where F bends (the paper's Fig. 16 problem). Across
a periodic seam a domain-space pin reaches past the domain's max along a; compose must evaluate it there (or through
the seam).
"""

from dataclasses import dataclass
from itertools import product

import numpy as np

from .errors import GeometryError, SpecError

AXES = "uvw"
CIRCLE_TOL = 0.02  # mm: largest distance between a joint's polygon and its circle
SNAP_SWELL = 1.15  # widest radius of a snap pin, in pin radii
DEFAULT_CLEARANCE = 0.15
DEFAULT_AXIAL_CLEARANCE = 0.3


def _wall(radius):
    """mm of material kept between two holes, and between a hole and a face's edge."""
    return max(0.8, 0.4 * radius)


def piece_id(index):
    return "p" + "-".join(str(int(i)) for i in index)


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
    dF/duvw at uvw_pin / uvw_hole, for the domain-space solids.
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

    @property
    def segments(self):
        """Circle segments for pin and hole alike (same count keeps the radial gap uniform)."""
        r = (self.radius * (SNAP_SWELL if self.shape == "snap" else 1.0)) + self.clearance
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


# ---------------------------------------------------------------------------------------------------------------------
# Measuring the cells


@dataclass(frozen=True, eq=False)
class _Geometry:
    """lengths: {cell: (3, G, G)} mm length of the cell's parameter lines along each axis a, on a G x G grid of the
    other two (cyclic) fractions _GRID, each line as a polyline of 8 chords; sag: {face number: mm of the face's bulge
    per mm^2 of disc radius at its centre}."""

    lengths: dict
    sag: dict


_GRID = np.linspace(0.0, 1.0, 7)


def _len_at(geo, idx, a, fr):
    """Length (n,) mm of the a-lines of cell idx through fractions fr (n, 3), bilinear in the grid."""
    b, c = _cyclic(a)
    tab = geo.lengths[idx][a]
    g = len(_GRID) - 1
    x = np.clip(np.asarray(fr, dtype=float)[:, b], 0.0, 1.0) * g
    y = np.clip(np.asarray(fr, dtype=float)[:, c], 0.0, 1.0) * g
    i = np.minimum(x.astype(int), g - 1)
    j = np.minimum(y.astype(int), g - 1)
    tx, ty = x - i, y - j
    return ((1 - tx) * (1 - ty) * tab[i, j] + tx * (1 - ty) * tab[i + 1, j] + (1 - tx) * ty * tab[i, j + 1]
            + tx * ty * tab[i + 1, j + 1])


def _center_len(geo, idx, a):
    return float(_len_at(geo, idx, a, np.full((1, 3), 0.5))[0])


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
    geo = _Geometry({cell.index: seg[n] for n, cell in enumerate(cells)}, {})

    # The bulge of each face over a small disc at its centre, to size the pin's base.
    if tiling.faces:
        ring = np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], axis=1)
        centers, info = [], []
        for n, f in enumerate(tiling.faces):
            cell = tiling.cells[f.lower]
            a = f.axis
            b, c = _cyclic(a)
            uvw = cell.center.copy()
            uvw[a] = cell.box[1, a]
            fr = np.array([[0.5, 0.5, 0.5]])
            fr[0, a] = 1.0
            rho = 0.2 * min(float(_len_at(geo, f.lower, b, fr)[0]), float(_len_at(geo, f.lower, c, fr)[0]))
            centers.append(uvw)
            info.append((n, a, b, c, rho))
        x0, jac = fmap.evaluate_with_jacobian(np.array(centers))
        steps = []
        for (n, a, b, c, rho), u0, j in zip(info, centers, jac):
            p = np.repeat(u0[None], 8, axis=0)
            p[:, b] += ring[:, 0] * rho / max(np.linalg.norm(j[:, b]), 1e-12)
            p[:, c] += ring[:, 1] * rho / max(np.linalg.norm(j[:, c]), 1e-12)
            steps.append(p)
        xr = fmap.evaluate(np.concatenate(steps)).reshape(len(steps), 8, 3)
        for (n, a, b, c, rho), x, xc, j in zip(info, xr, x0, jac):
            nrm = np.cross(j[:, b], j[:, c])
            size = np.linalg.norm(nrm)
            if rho <= 1e-9 or size <= 1e-12:
                geo.sag[n] = 0.0  # a collapsed face: no joint will fit there anyway
                continue
            geo.sag[n] = float(np.max(np.abs((x - xc) @ (nrm / size)))) / rho ** 2
    return geo


def _face_side(tiling, geo, f):
    """Shorter in-face side of face f through its centre, mm."""
    b, c = _cyclic(f.axis)
    fr = np.array([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]])
    fr[0, f.axis], fr[1, f.axis] = 1.0, 0.0
    lo = [_len_at(geo, f.lower, x, fr[:1])[0] for x in (b, c)]
    up = [_len_at(geo, f.upper, x, fr[1:])[0] for x in (b, c)]
    return float(min(lo + up))


def _round_down(x, step=0.1):
    return round(float(np.floor(x / step + 1e-9) * step), 6)


def default_sizes(tiling, fmap, _geo=None):
    """(radius, length) mm from the smallest face and the thinnest cell: radius 12% of the smallest face's short side,
    length 2 radii but at most 35% of the thinnest cell depth; both rounded down to 0.1 mm."""
    geo = _geo or _measure(tiling, fmap)
    if tiling.faces:
        side = min(_face_side(tiling, geo, f) for f in tiling.faces)
        depth = min(_center_len(geo, idx, f.axis) for f in tiling.faces for idx in (f.lower, f.upper))
    else:
        side = depth = min(_center_len(geo, idx, a) for idx in tiling.cells for a in range(3))
    radius = max(_round_down(0.12 * side), 0.1)
    length = max(_round_down(min(2.0 * radius, 0.35 * depth)), 0.1)
    return radius, length


# ---------------------------------------------------------------------------------------------------------------------
# Placement


# The offset choices (k_b, k_c) of one axis, in steps of the separation: half steps let two joints sit either side
# of a face's centre line.
_KS = list(product((-1.0, -0.5, 0.0, 0.5, 1.0), repeat=2))
_NK = len(_KS)
_KCOST = np.array([(sum(x != 0 for x in k), sum(abs(x) for x in k)) for k in _KS])


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
        return self.radius * (SNAP_SWELL if self.shape == "snap" else 1.0) + self.clearance

    @property
    def wall(self):
        return _wall(self.radius)

    @property
    def separation(self):
        return 2.0 * self.reach + self.wall

    @property
    def hole_depth(self):
        return self.length + self.axial_clearance


def _base_estimate(geo, n, sizes):
    rho = 1.2 * sizes.reach
    return max(0.5, 1.5 * geo.sag.get(n, 0.0) * rho ** 2 + 0.3)


def _intrusions(tiling, geo, sizes):
    """{cell: {(axis, side): (face number, mm reached into the cell)}}; side +1 = max face, -1 = min face."""
    out = {idx: {} for idx in tiling.cells}
    for n, f in enumerate(tiling.faces):
        base = _base_estimate(geo, n, sizes)
        out[f.lower][(f.axis, +1)] = (n, sizes.hole_depth if sizes.style == "dowel" else base)
        out[f.upper][(f.axis, -1)] = (n, sizes.hole_depth)
    return out


def _length_problems(tiling, geo, sizes, intr):
    """The pin-length fit: both intrusions along an axis plus a wall within the cell's depth."""
    worst = None
    for idx, slots in intr.items():
        for a in range(3):
            lo = slots.get((a, -1))
            hi = slots.get((a, +1))
            if lo is None and hi is None:
                continue
            need = (lo[1] if lo else 0.0) + (hi[1] if hi else 0.0) + sizes.wall
            depth = _center_len(geo, idx, a)
            if need > depth + 1e-9:
                # what would fit: solve for the length with the other intrusions unchanged
                holes = sum(1 for s, side in ((lo, -1), (hi, +1)) if s is not None
                            and (side == -1 or sizes.style == "dowel"))
                other = need - holes * sizes.hole_depth
                best = (depth - other) / max(holes, 1) - sizes.axial_clearance
                if worst is None or best < worst[0]:
                    worst = (best, idx, a, depth)
    if worst is None:
        return []
    best, idx, a, depth = worst
    return [f"joints.length: a pin of length {sizes.length:g} does not fit piece {piece_id(idx)}, {depth:.1f} mm deep "
            f"along {AXES[a]} (got {sizes.length:g}, expected at most {max(_round_down(best), 0.0):g})"]


def _face_fractions(tiling, f, ks, delta):
    """For each offset choice k, the joint's fractions (3,) and parameters (3,) in the lower and in the upper cell."""
    a = f.axis
    b, c = _cyclic(a)
    low = tiling.cells[f.lower]
    up = tiling.cells[f.upper]
    fr = np.empty((len(ks), 3))
    fr[:, a] = 1.0
    fr[:, b] = 0.5 + np.array([k[0] for k in ks]) * delta[b]
    fr[:, c] = 0.5 + np.array([k[1] for k in ks]) * delta[c]
    uvw = low.box[0] + fr * (low.box[1] - low.box[0])
    if f.seam is not None:
        uvw_up = np.asarray(f.seam.map_max_to_min(uvw), dtype=float)
    else:
        uvw_up = uvw.copy()
        uvw_up[:, a] = up.box[0, a]
    fr_up = (uvw_up - up.box[0]) / (up.box[1] - up.box[0])
    return fr, fr_up, uvw, uvw_up


def _search(tiling, geo, sizes, intr):
    """The cheapest offset pattern {axis: (k_b, k_c)} under which all joints are apart, with every face's fractions
    and parameters -> (pattern, {face number: (uvw_lower, uvw_upper)}) or None."""
    reach, sep, wall = sizes.reach, sizes.separation, sizes.wall
    fr_low, fr_up, uvws = {}, {}, {}
    allowed = {a: np.ones(_NK, bool) for a in range(3)}
    for n, f in enumerate(tiling.faces):
        b, c = _cyclic(f.axis)
        centre = np.full((1, 3), 0.5)
        centre[0, f.axis] = 1.0
        delta = np.zeros(3)
        for x in (b, c):  # one offset step: the separation, in fractions of this face
            delta[x] = sep / max(float(_len_at(geo, f.lower, x, centre)[0]), 1e-9)
        fl, fu, ul, uu = _face_fractions(tiling, f, _KS, delta)
        fr_low[n], fr_up[n], uvws[n] = fl, fu, (ul, uu)
        for idx, fr in ((f.lower, fl), (f.upper, fu)):
            for x in (b, c):
                room = np.minimum(fr[:, x], 1.0 - fr[:, x]) * _len_at(geo, idx, x, fr)
                allowed[f.axis] &= room >= reach + wall - 1e-9
    # pair tables: ok[(a1, a2)][k1, k2] for a1 < a2, over every piece
    ok = {pair: np.ones((_NK, _NK), bool) for pair in ((0, 1), (0, 2), (1, 2))}
    for idx, slots in intr.items():
        items = []
        for (a, side), (n, depth) in slots.items():
            fr = fr_low[n] if side == +1 else fr_up[n]
            lens = np.stack([_len_at(geo, idx, x, fr) for x in range(3)], axis=1)  # (_NK, 3)
            opposite = slots.get((a, -side))
            # the piece's depth at this joint holds both intrusions of this axis and a wall
            need = depth + (opposite[1] if opposite else 0.0) + wall
            allowed[a] &= lens[:, a] >= need - 1e-9
            items.append((a, side, fr, depth, lens))
        for i in range(len(items)):
            for j in range(i + 1, len(items)):
                s1, s2 = items[i], items[j]
                if s1[0] == s2[0]:
                    continue
                if s1[0] > s2[0]:
                    s1, s2 = s2, s1
                a1, a2 = s1[0], s2[0]
                a3 = 3 - a1 - a2
                span = np.minimum(s1[4][:, None, a3], s2[4][None, :, a3])
                lateral = np.abs(s1[2][:, None, a3] - s2[2][None, :, a3]) * span >= sep - 1e-9

                def clear(s, other, along_rows):
                    a, side, _, depth, _ = s
                    f_other = other[2][:, a]
                    level = (f_other if side == -1 else 1.0 - f_other) * other[4][:, a]
                    good = level - reach - wall >= depth - 1e-9  # (_NK,) over the other's k
                    return good[None, :] if along_rows else good[:, None]

                ok[(a1, a2)] &= lateral | clear(s1, s2, True) | clear(s2, s1, False)
    feasible = (allowed[0][:, None, None] & allowed[1][None, :, None] & allowed[2][None, None, :]
                & ok[(0, 1)][:, :, None] & ok[(0, 2)][:, None, :] & ok[(1, 2)][None, :, :])
    if not feasible.any():
        return None
    ks = np.argwhere(feasible)
    cost = _KCOST[ks].sum(axis=1)  # (n, 2): offsets used, then their size
    best = ks[np.lexsort((cost[:, 1], cost[:, 0]))[0]]
    k = best
    pattern = {a: _KS[k[a]] for a in range(3)}
    placed = {n: (uvws[n][0][k[f.axis]], uvws[n][1][k[f.axis]]) for n, f in enumerate(tiling.faces)}
    return pattern, placed


def _spec_value(spec, name, default):
    v = getattr(spec, name, None) if spec is not None else None
    return default if v is None else v


def _sizes_from(spec, radius, length):
    return _Sizes(float(radius), float(length), float(_spec_value(spec, "clearance", DEFAULT_CLEARANCE)),
                  float(_spec_value(spec, "axial_clearance", DEFAULT_AXIAL_CLEARANCE)),
                  str(_spec_value(spec, "style", "pin")), str(_spec_value(spec, "shape", "cylinder")))


def _largest_radius(tiling, geo, sizes, hi):
    """Largest radius (0.1 mm steps) that can be placed, the other sizes fixed; 0 if none."""
    def fits(r):
        s = _Sizes(r, sizes.length, sizes.clearance, sizes.axial_clearance, sizes.style, sizes.shape)
        intr = _intrusions(tiling, geo, s)
        return not _length_problems(tiling, geo, s, intr) and _search(tiling, geo, s, intr) is not None

    lo = 0.0
    if not fits(0.1):
        return 0.0
    lo = 0.1
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        if fits(mid):
            lo = mid
        else:
            hi = mid
    return _round_down(lo)


def plan_joints(tiling, fmap, joint_spec=None):
    """One Joint per shared face (also across periodic seams), pins on the lower cell; [] for style none.

    joint_spec: any object with style, shape, radius, length, clearance, axial_clearance, space (None = defaults).
    Raises SpecError naming the key, the value and what would fit when a pin is too wide for a face or too long
    for a piece.
    """
    style = str(_spec_value(joint_spec, "style", "pin"))
    if style == "none" or not tiling.faces:
        return []
    space = str(_spec_value(joint_spec, "space", "physical"))
    geo = _measure(tiling, fmap)
    r_given = getattr(joint_spec, "radius", None) if joint_spec is not None else None
    l_given = getattr(joint_spec, "length", None) if joint_spec is not None else None
    r_def, l_def = default_sizes(tiling, fmap, geo)
    sizes = _sizes_from(joint_spec, r_def if r_given is None else r_given, l_def if l_given is None else l_given)
    problems = []
    for key, v, low in (("radius", sizes.radius, 0.0), ("length", sizes.length, 0.0),
                        ("clearance", sizes.clearance, -1e-12), ("axial_clearance", sizes.axial_clearance, -1e-12)):
        if not np.isfinite(v) or v <= low:
            problems.append(f"joints.{key}: must be {'positive' if low == 0 else 'zero or more'} (got {v:g})")
    if problems:
        raise SpecError(problems)

    if r_given is not None:
        # A pin wider than its face is the real mistake; say so before any length fit derived from it.
        f = min(tiling.faces, key=lambda f: _face_side(tiling, geo, f))
        side = _face_side(tiling, geo, f)
        if sizes.radius + sizes.clearance >= 0.5 * side:
            r_max = _largest_radius(tiling, geo, sizes, 0.5 * side)
            raise SpecError(
                f"joints.radius: a pin of radius {sizes.radius:g} does not fit the face between {piece_id(f.lower)} "
                f"and {piece_id(f.upper)}, {side:.1f} mm across (got {sizes.radius:g}, expected at most {r_max:g})")
    intr = _intrusions(tiling, geo, sizes)
    if l_given is None:
        # a derived length shrinks to what the thinnest piece holds
        while _length_problems(tiling, geo, sizes, intr) and sizes.length > 0.15:
            sizes = _Sizes(sizes.radius, _round_down(sizes.length * 0.9), sizes.clearance, sizes.axial_clearance,
                           sizes.style, sizes.shape)
            intr = _intrusions(tiling, geo, sizes)
    problems = _length_problems(tiling, geo, sizes, intr)
    if problems:
        raise SpecError(problems)
    found = _search(tiling, geo, sizes, intr)
    if found is None:
        r_max = _largest_radius(tiling, geo, sizes, sizes.radius)
        if r_given is None and r_max > 0:
            sizes = _Sizes(r_max, sizes.length, sizes.clearance, sizes.axial_clearance, sizes.style, sizes.shape)
            intr = _intrusions(tiling, geo, sizes)
            found = _search(tiling, geo, sizes, intr)
        if found is None:
            f = min(tiling.faces, key=lambda f: _face_side(tiling, geo, f))
            raise SpecError(
                f"joints.radius: a pin of radius {sizes.radius:g} does not fit the face between {piece_id(f.lower)} "
                f"and {piece_id(f.upper)} (got {sizes.radius:g}, expected at most {r_max:g})")
    _, placed = found

    joints = []
    faces = list(tiling.faces)
    uvw_low = np.array([placed[n][0] for n in range(len(faces))])
    uvw_up = np.array([placed[n][1] for n in range(len(faces))])
    x0, jac = fmap.evaluate_with_jacobian(uvw_low)
    orientation = int(getattr(fmap, "orientation", 1) or 1)
    dirs = []
    for n, f in enumerate(faces):
        a = f.axis
        b, c = _cyclic(a)
        j = jac[n]
        nrm = np.cross(j[:, b], j[:, c])
        det = float(np.dot(j[:, a], nrm))
        # det > 0 means J_b x J_c already points along +a; a left-handed map turns it round
        sign = np.sign(det) if abs(det) > 1e-12 else orientation
        nrm = sign * nrm / max(np.linalg.norm(nrm), 1e-300)
        dirs.append(nrm)
    bases = _actual_bases(fmap, faces, uvw_low, x0, jac, dirs, sizes, geo)
    _, jac_up = fmap.evaluate_with_jacobian(uvw_up)
    for n, f in enumerate(faces):
        joints.append(Joint(
            pin_cell=tuple(f.lower), hole_cell=tuple(f.upper), axis=f.axis, across_seam=f.seam is not None,
            center=_readonly(x0[n]), direction=_readonly(dirs[n]), radius=sizes.radius, length=sizes.length,
            clearance=sizes.clearance, axial_clearance=sizes.axial_clearance, shape=sizes.shape, style=sizes.style,
            space=space, uvw_pin=_readonly(uvw_low[n]), uvw_hole=_readonly(uvw_up[n]), base_depth=bases[n],
            jacobian_pin=_readonly(jac[n]), jacobian_hole=_readonly(jac_up[n])))
    return joints


def _actual_bases(fmap, faces, uvw, x0, jac, dirs, sizes, geo):
    """base_depth per joint: the face's bulge over the pin's disc at the joint itself, at least the estimate."""
    rho = 1.2 * sizes.reach
    ring = np.stack([np.cos(np.arange(12) * np.pi / 6), np.sin(np.arange(12) * np.pi / 6)], axis=1)
    pts = []
    for n, f in enumerate(faces):
        b, c = _cyclic(f.axis)
        p = np.repeat(uvw[n][None], 12, axis=0)
        p[:, b] += ring[:, 0] * rho / max(np.linalg.norm(jac[n][:, b]), 1e-12)
        p[:, c] += ring[:, 1] * rho / max(np.linalg.norm(jac[n][:, c]), 1e-12)
        pts.append(p)
    xr = fmap.evaluate(np.concatenate(pts)).reshape(len(faces), 12, 3)
    out = []
    for n in range(len(faces)):
        sag = float(np.max(np.abs((xr[n] - x0[n]) @ dirs[n])))
        out.append(round(max(_base_estimate(geo, n, sizes), 1.5 * sag + 0.3), 4))
    return out


# ---------------------------------------------------------------------------------------------------------------------
# Solids


def _manifold():
    import manifold3d

    return manifold3d


def _checked(m, what):
    status = m.status()
    if status != _manifold().Error.NoError:
        raise GeometryError(f"{what}: the geometry engine failed ({status})")
    return m


def _frame(j, flip=False):
    """3x4 rigid transform: local z -> the joint's direction (reversed if flip), origin -> its centre."""
    n = np.asarray(j.direction, dtype=float) * (-1.0 if flip else 1.0)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(helper, n)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
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
    return _checked(s, f"pin of {piece_id(j.pin_cell)}")


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
    return _checked(_hole_local(j).transform(frame), f"hole in {piece_id(idx)}")


def dowel_solid(j):
    """The loose dowel (Manifold, mm) in its assembled place: radius r, length 2 * length, centred on the face."""
    s = _local_solid(j, j.radius, -j.length, j.length)
    if j.shape == "snap":  # a dowel is plain: it must slide into both holes
        m3 = _manifold()
        s = m3.Manifold.cylinder(2 * j.length, j.radius, -1.0, j.segments).translate([0.0, 0.0, -j.length])
    return _checked(s.transform(_frame(j)), f"dowel between {piece_id(j.pin_cell)} and {piece_id(j.hole_cell)}")


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
    return _checked(solid, f"domain pin of {piece_id(j.pin_cell)}")


def hole_solid_domain(j, cell_index):
    """The hole in cell_index's parameter frame (Manifold, uvw units); across a seam the hole cell's own parameters."""
    idx = tuple(cell_index)
    if idx == j.hole_cell:
        m = _domain_transform(j, j.uvw_hole, j.jacobian_hole)
    elif idx == j.pin_cell and j.style == "dowel":
        m = _domain_transform(j, j.uvw_pin, j.jacobian_pin, flip=True)
    else:
        raise GeometryError(f"joint {piece_id(j.pin_cell)}-{piece_id(j.hole_cell)} makes no hole in {piece_id(idx)}")
    return _checked(_hole_local(j).transform(m), f"domain hole in {piece_id(idx)}")
