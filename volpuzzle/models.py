"""Built-in models: the paper's shapes as trivariate (rational) B-splines, lengths in mm.

Every constructor returns a right-handed Volume whose Jacobian is positive in the interior (it may vanish on
collapsed boundaries only: the corner edges of the square-to-disk section, the poles of the shells).
The spec names them in `model.builtin: {type: ..., ...}`; `make_builtin` validates such a dict.
"""

import difflib
import math

import numpy as np

from .errors import ModelError, SpecError
from .spline import basis
from .spline.knots import greville
from .spline.volume import Volume

SQRT_HALF = math.sqrt(0.5)


# --- small spline helpers ------------------------------------------------------------------------------------
def _unit_arc(angle, segments):
    """Rational quadratic arc of the unit circle from angle 0 to `angle` (radians) in `segments` equal pieces
    of at most 90 degrees (NURBS Book section 7.5, A7.1): points (2*segments+1, 2), weights, knots."""
    d = angle / segments
    pts, wts = [], []
    for k in range(segments):
        a0, am = k * d, (k + 0.5) * d
        pts += [(math.cos(a0), math.sin(a0)), (math.cos(am) / math.cos(d / 2), math.sin(am) / math.cos(d / 2))]
        wts += [1.0, math.cos(d / 2)]
    pts.append((math.cos(angle), math.sin(angle)))
    wts.append(1.0)
    pts = np.array(pts)
    if abs(angle - 2 * math.pi) < 1e-12:
        pts[-1] = pts[0]  # close exactly, not to round-off
    inner = np.repeat(np.arange(1, segments) / segments, 2)
    knots = np.concatenate([[0, 0, 0], inner, [1, 1, 1]])
    return pts, np.array(wts), knots


def _disk_section(r, centre_weight=1.0):
    """Rational biquadratic square-to-disk patch of radius r: points (3, 3, 2), weights (3, 3).

    Its four boundary curves are exact quarter arcs; the corners sit on the circle at 45 degrees, where two
    arcs meet at a straight angle, so det J vanishes there (and only there)."""
    c, e = r * SQRT_HALF, r * math.sqrt(2.0)
    pts = np.array([[(-c, -c), (-e, 0.0), (-c, c)],
                    [(0.0, -e), (0.0, 0.0), (0.0, e)],
                    [(c, -c), (e, 0.0), (c, c)]])
    wts = np.array([[1.0, SQRT_HALF, 1.0], [SQRT_HALF, centre_weight, SQRT_HALF], [1.0, SQRT_HALF, 1.0]])
    return pts, wts


def _square_section(r):
    """The square [-r, r]^2 as a (degree-elevated, linear) biquadratic patch: points (3, 3, 2), weights 1."""
    g = np.array([-r, 0.0, r])
    return np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1), np.ones((3, 3))


def _revolve(section_pts, section_w, R, angle, segments):
    """Sweep a (radial, z) section at distance R from the z axis around it: exact (NURBS Book A8.1).

    section_pts (n_u, n_v, 2), section_w (n_u, n_v) -> control points (n_u, n_v, n_w, 3), weights."""
    arc, arc_w, knots = _unit_arc(angle, segments)
    rho = R + section_pts[..., 0]
    cps = np.empty(section_pts.shape[:2] + (len(arc), 3))
    cps[..., 0] = rho[..., None] * arc[:, 0]
    cps[..., 1] = rho[..., None] * arc[:, 1]
    cps[..., 2] = section_pts[..., 1][..., None]
    return cps, section_w[..., None] * arc_w, knots


def _basis_matrix(knots, degree, t):
    """Dense collocation matrix (len(t), n): N_j(t_i)."""
    t = np.asarray(t, dtype=float)
    n = len(knots) - degree - 1
    span = basis.find_span(knots, degree, t)
    vals = basis.basis_functions(knots, degree, t, span)
    m = np.zeros((len(t), n))
    for k in range(degree + 1):
        m[np.arange(len(t)), span - degree + k] = vals[:, k]
    return m


def _reverse_axis(vol, axis):
    """The same volume with axis `axis` running the other way (flips the sign of det J)."""
    k = vol.knots[axis]
    knots = list(vol.knots)
    knots[axis] = (k[0] + k[-1]) - k[::-1]
    cps = np.flip(vol.control_points, axis=axis)
    w = None if vol.weights is None else np.flip(vol.weights, axis=axis)
    return Volume(vol.degrees, tuple(knots), cps, w)


def _det_samples(vol, n=7):
    """det J at an interior grid of n^3 points (off the boundary, where collapsed edges live)."""
    (u0, u1), (v0, v1), (w0, w1) = vol.domain
    s = (np.arange(n) + 0.5) / n
    g = np.stack(np.meshgrid(u0 + s * (u1 - u0), v0 + s * (v1 - v0), w0 + s * (w1 - w0), indexing="ij"), -1)
    return np.linalg.det(vol.derivatives(g.reshape(-1, 3)))


def _right_handed(vol):
    """Reverse u when the construction came out left-handed, so every builtin is right-handed."""
    return _reverse_axis(vol, 0) if np.median(_det_samples(vol)) < 0 else vol


# --- the shapes --------------------------------------------------------------------------------------------------
def quarter_torus(major_radius=60.0, minor_radius=20.0):
    """A quarter of a solid torus, exact rational: u, v across the circular section, w the major angle (90 deg).

    The section is the rational biquadratic square-to-disk patch rather than a polar form: split 2x2 it gives four
    equal, rounded quadrant pieces with full-width faces between them, whereas a polar form collapses the whole
    centre line into one edge, so its inner pieces become knife-edged wedges and joints along the axis sit in a
    degenerate spot. The price is det J = 0 on the four corner edges of the patch, on the boundary only.
    """
    pts, w = _disk_section(minor_radius)
    # u runs along z and v along the radius: (e_z, e_rho, e_phi) is right-handed
    cps, wts, knots = _revolve(pts[..., ::-1], w, major_radius, math.pi / 2, 1)
    k2 = np.array([0, 0, 0, 1, 1, 1.0])
    return _right_handed(Volume((2, 2, 2), (k2, k2, knots), cps, wts))


def torus(major_radius=60.0, minor_radius=20.0):
    """Full solid torus, exact rational, closed along w (the major angle: 9 control points, double knots)."""
    pts, w = _disk_section(minor_radius)
    cps, wts, knots = _revolve(pts[..., ::-1], w, major_radius, 2 * math.pi, 4)  # right-handed as above
    k2 = np.array([0, 0, 0, 1, 1, 1.0])
    return _right_handed(Volume((2, 2, 2), (k2, k2, knots), cps, wts))


def twisted_torus_point(major_radius, minor_radius, twist, uvw):
    """The exact twisted torus the builtin approximates: (n, 3) parameters in [0, 1]^3 -> (n, 3) points.

    v and u span the square [-r, r]^2 in the (radial, z) plane (u along z, v along the radius, so that it is
    right-handed), turned by twist * w degrees; w goes once round counter-clockwise seen from +z."""
    uvw = np.asarray(uvw, dtype=float)
    x = (2 * uvw[:, 1] - 1) * minor_radius
    y = (2 * uvw[:, 0] - 1) * minor_radius
    phi = 2 * math.pi * uvw[:, 2]
    th = math.radians(twist) * uvw[:, 2]
    xr = np.cos(th) * x - np.sin(th) * y
    yr = np.sin(th) * x + np.cos(th) * y
    rho = major_radius + xr
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), yr], axis=1)


def _fit_closed_layers(curve, corner_map, size, tol=1e-4):
    """Cubic clamped interpolation at the Greville points of the exact curves `curve(w) -> (len(w), 2, 2, 3)`,
    refined until the largest error on dense samples is below tol * size / 2. The last layer is then set to
    the first one permuted by corner_map, so the seam closes exactly. -> (2, 2, n, 3), knots."""
    check = np.linspace(0, 1, 2001)
    exact = curve(check)
    for spans in (8, 12, 16, 24, 32, 48, 64, 96, 128):
        knots = np.concatenate([[0, 0, 0], np.linspace(0, 1, spans + 1), [1, 1, 1]])
        g = greville(knots, 3)
        a = _basis_matrix(knots, 3, g)
        data = curve(g).reshape(len(g), -1)
        cps = np.linalg.solve(a, data)
        approx = (_basis_matrix(knots, 3, check) @ cps).reshape(exact.shape)
        err = np.max(np.linalg.norm(approx - exact, axis=-1))
        if err < 0.5 * tol * size:
            break
    layers = np.moveaxis(cps.reshape(len(g), 2, 2, 3), 0, 2).copy()
    for (i, j), (i2, j2) in corner_map.items():
        layers[i, j, -1] = layers[i2, j2, 0]
    return layers, knots


def twisted_torus(major_radius=60.0, minor_radius=15.0, twist=90.0):
    """Solid torus of square section (half side minor_radius) turning by `twist` degrees once round.

    Degree 1 across the section (exact: the section is a square at every angle), a cubic B-spline fit along the
    major angle within 1e-4 of the size; closed: the last control layer is the first one turned by `twist`.
    `twist` must be a multiple of 90 so that the turned square lands on itself."""
    R, r = float(major_radius), float(minor_radius)

    def curve(w):
        uv = np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]])  # corners (i, j) in C order
        uvw = np.concatenate([np.repeat(uv[None], len(w), 0), np.repeat(np.asarray(w)[:, None, None], 4, 1)], -1)
        return twisted_torus_point(R, r, twist, uvw.reshape(-1, 3)).reshape(len(w), 2, 2, 3)

    # which corner of the first section does corner (i, j) of the last section land on?
    end = curve(np.array([1.0]))[0]
    start = curve(np.array([0.0]))[0]
    corner_map = {}
    for i in range(2):
        for j in range(2):
            d = np.linalg.norm(start - end[i, j], axis=-1)
            corner_map[(i, j)] = tuple(int(x) for x in np.unravel_index(np.argmin(d), d.shape))
    layers, knots = _fit_closed_layers(curve, corner_map, size=2 * (R + r * math.sqrt(2)))
    k1 = np.array([0, 0, 1, 1.0])
    return _right_handed(Volume((1, 1, 3), (k1, k1, knots), layers, None))


def _gtorus_path(R):
    """The closed planar path of the generalized torus, as 10 pieces (position, unit tangent, length) callables.

    A 'D': a straight bottom at y = -R/2 (split at its middle, where the seam is), two quarter arcs of radius
    R/2 turning up, and the upper half circle of radius R in six 30-degree pieces."""
    rho, a = R / 2, R / 2
    pieces = []

    def line(p0, p1):
        p0, p1 = np.array(p0, float), np.array(p1, float)
        t = (p1 - p0) / np.linalg.norm(p1 - p0)
        return (lambda s: p0 + np.outer(s, p1 - p0), lambda s: np.tile(t, (len(s), 1)), float(np.linalg.norm(p1 - p0)))

    def arc(c, rad, a0, a1):
        c = np.array(c, float)

        def pos(s):
            th = a0 + (a1 - a0) * np.asarray(s)
            return c + rad * np.stack([np.cos(th), np.sin(th)], 1)

        def tan(s):
            th = a0 + (a1 - a0) * np.asarray(s)
            return np.stack([-np.sin(th), np.cos(th)], 1)
        return pos, tan, rad * abs(a1 - a0)

    pieces.append(line((0.0, -rho), (a, -rho)))
    pieces.append(arc((a, 0.0), rho, -math.pi / 2, 0.0))
    for k in range(6):
        pieces.append(arc((0.0, 0.0), R, k * math.pi / 6, (k + 1) * math.pi / 6))
    pieces.append(arc((-a, 0.0), rho, math.pi, 1.5 * math.pi))
    pieces.append(line((-a, -rho), (0.0, -rho)))
    return pieces


def generalized_torus(major_radius=60.0, minor_radius=15.0):
    """A torus-like loop whose section goes from a square (at the seam, middle of the straight bottom) to a
    circle (at the top) and back, swept along a 'D' path: straight bottom, quarter arcs, upper half circle.

    Cubic along the sweep with double knots at the 9 breaks between its 10 pieces (C1 there, so
    `splits: {w: knots}` cuts at them: 2x2x10 as in the paper); closed along w with the identity seam.
    The section is a rational biquadratic patch blended between the square and the square-to-disk patch."""
    R, r = float(major_radius), float(minor_radius)
    pieces = _gtorus_path(R)
    lengths = np.array([p[2] for p in pieces])
    breaks = np.concatenate([[0.0], np.cumsum(lengths) / lengths.sum()])
    breaks[-1] = 1.0
    sq_p, sq_w = _square_section(r)
    dk_p, dk_w = _disk_section(r)
    sq_p, dk_p = sq_p[..., ::-1], dk_p[..., ::-1]  # u along z, v outward: right-handed with w along the path

    def homogeneous(k, s):
        """Exact homogeneous section control points on piece k at local s -> (3, 3, 4), and their d/dw."""
        pos, tan, _ = pieces[k]
        h = breaks[k + 1] - breaks[k]
        out = []
        for ds in (0.0, 1e-6, -1e-6):  # central difference; the pieces extend analytically past their ends
            ss = np.array([s + ds])
            ww = breaks[k] + h * ss
            m = 0.5 * (1 - np.cos(2 * math.pi * ww))[0]  # 0: square at the seam, 1: circle at the top
            p = (1 - m) * sq_p + m * dk_p
            wt = (1 - m) * sq_w + m * dk_w
            c, t = pos(ss)[0], tan(ss)[0]
            nrm = np.array([t[1], -t[0]])  # outward in-plane normal of the counter-clockwise path
            xy = c + p[..., 0:1] * nrm
            xyz = np.concatenate([xy, p[..., 1:2]], -1)
            out.append(np.concatenate([xyz * wt[..., None], wt[..., None]], -1))
        return out[0], (out[1] - out[2]) / (2e-6 * h)

    # cubic Hermite per piece in homogeneous space. The offset of a line-to-arc joint is G1 but changes speed,
    # so both sides use the mean derivative at each break: that makes the curve C1, as the double knots require.
    n = len(pieces)
    pts = [homogeneous(k, 0.0)[0] for k in range(n)]
    der = [(homogeneous(k, 0.0)[1] + homogeneous(k - 1, 1.0)[1]) / 2 for k in range(n)]
    bez = []
    for k in range(n):
        h = breaks[k + 1] - breaks[k]
        k1 = (k + 1) % n
        bez += [pts[k], pts[k] + h / 3 * der[k], pts[k1] - h / 3 * der[k1]]
    bez.append(pts[0])  # closed: the last layer is the first one
    # drop the joint Bezier points at interior breaks: with a double knot they follow from their neighbours
    keep = [i for i in range(len(bez)) if i % 3 != 0 or i == 0 or i == len(bez) - 1]
    hp = np.stack([bez[i] for i in keep], axis=2)  # (3, 3, 22, 4)
    knots_w = np.concatenate([[0, 0, 0, 0], np.repeat(breaks[1:-1], 2), [1, 1, 1, 1]])
    k2 = np.array([0, 0, 0, 1, 1, 1.0])
    return _right_handed(Volume.from_homogeneous((2, 2, 3), (k2, k2, knots_w), hp))


def sphere_shell(outer_radius=50.0, inner_radius=40.0):
    """Thick spherical shell, exact rational: u the polar angle (collapsed at the poles), v the azimuth (closed),
    w the radius from inner to outer; this order makes it right-handed (e_theta x e_phi = e_r)."""
    half, half_w, ku = _unit_arc(math.pi, 2)
    # the semicircle from the north pole down to the south pole, in (distance from the axis, z)
    merid = np.stack([half[:, 1], half[:, 0]], 1)
    merid[np.abs(merid) < 1e-15] = 0.0
    circ, circ_w, kv = _unit_arc(2 * math.pi, 4)
    radii = np.array([inner_radius, outer_radius], float)
    cps = np.empty((len(merid), len(circ), 2, 3))
    cps[..., 0] = merid[:, 0, None, None] * circ[None, :, 0, None] * radii
    cps[..., 1] = merid[:, 0, None, None] * circ[None, :, 1, None] * radii
    cps[..., 2] = merid[:, 1, None, None] * radii
    wts = np.repeat((half_w[:, None] * circ_w[None, :])[..., None], 2, axis=2)
    kw = np.array([0, 0, 1, 1.0])
    return _right_handed(Volume((2, 2, 1), (ku, kv, kw), cps, wts))


def _duck_radius(d):
    """Radial function of the duck's outer surface about its centre, for unit directions d (n, 3) -> (n,).

    Length 1 along x (beak at +x), a body ellipsoid plus smooth bumps on the radial function: a head up front
    with a beak, and a tail raised at the back. Star-shaped by construction, so the shell cannot fold."""
    body = 1.0 / np.sqrt((d[:, 0] / 0.42) ** 2 + (d[:, 1] / 0.30) ** 2 + (d[:, 2] / 0.25) ** 2)

    def bump(direction, height, width):
        c = np.asarray(direction, float) / np.linalg.norm(direction)
        ang = np.arccos(np.clip(d @ c, -1.0, 1.0))
        return height * np.exp(-(ang / width) ** 2)

    return (body + bump((0.55, 0, 1.0), 0.26, 0.38)    # head
            + bump((1.0, 0, 0.72), 0.17, 0.13)         # beak
            + bump((-1.0, 0, 0.5), 0.15, 0.18))       # tail


def _periodic_matrix(n, t, degree=3):
    """Collocation matrix (len(t), n) of the uniform periodic cubic B-spline with n control points on [0, 1]."""
    knots = (np.arange(n + 2 * degree + 1) - degree) / n
    full = _basis_matrix(knots, degree, t)  # (m, n + degree), control points wrapped
    return full[:, :n] + np.pad(full[:, n:], ((0, 0), (0, n - degree)))


def duck_shell(size=120.0, thickness=8.0):
    """A rubber-duck-like thick shell, `size` mm long: a ruled volume between a freeform closed surface and its
    inward offset by `thickness` (control points moved along the surface normal).

    u: the polar angle about the duck's left-right axis (collapsed at the two flank poles), v: the azimuth round
    the side profile through beak, head, back, tail and belly (closed, C2 across the seam), w: from the inner
    to the outer surface. Polynomial, bicubic by linear; meant for a 4 x 8 x 1 puzzle."""
    n_u, n_v = 12, 24  # control rows (polar, clamped) and columns (azimuth, periodic before clamping)
    th = np.linspace(0, math.pi, 3 * n_u + 1)
    ph = np.arange(3 * n_v) / (3 * n_v)
    tt, pp = np.meshgrid(th, 2 * math.pi * ph, indexing="ij")
    # poles on +y / -y: the flanks, where the duck is plain; the features run round the azimuth
    d = np.stack([np.sin(tt) * np.sin(pp), np.cos(tt), np.sin(tt) * np.cos(pp)], -1).reshape(-1, 3)
    pts = (_duck_radius(d)[:, None] * d).reshape(len(th), len(ph), 3)
    ku = np.concatenate([[0, 0, 0], np.linspace(0, 1, n_u - 2), [1, 1, 1]])
    a = _basis_matrix(ku, 3, th / math.pi)
    b = _periodic_matrix(n_v, ph)
    north, south = pts[0, 0], pts[-1, 0]
    # least squares with the pole rows held on the poles (NURBS Book 9.4.1, separable in u and v)
    rhs = pts - a[:, :1, None] * north - a[:, -1:, None] * south
    inner = np.einsum("ia,abk->ibk", np.linalg.pinv(a[:, 1:-1]), rhs)
    inner = np.einsum("jb,ibk->ijk", np.linalg.pinv(b), inner)
    per = np.concatenate([np.tile(north, (1, n_v, 1)), inner, np.tile(south, (1, n_v, 1))], 0)
    # the periodic v direction in clamped form: the same curve, exactly, on a clamped knot vector
    kv = np.concatenate([[0, 0, 0], np.linspace(0, 1, n_v + 1), [1, 1, 1]])
    s = np.linspace(0, 1, 8 * n_v + 1)
    to_clamped = np.linalg.pinv(_basis_matrix(kv, 3, s)) @ _periodic_matrix(n_v, s)
    outer = np.einsum("jb,ibk->ijk", to_clamped, per)
    outer[:, -1] = outer[:, 0]  # close exactly, not to round-off
    ext = outer.reshape(-1, 3)
    outer = outer * (size / float(np.max(ext.max(0) - ext.min(0))))
    kw = np.array([0, 0, 1, 1.0])
    shell = Volume((3, 3, 1), (ku, kv, kw), np.stack([outer, outer], 2))
    # outward normals at the Greville points; the pole rows take the mean normal of a ring just off the pole
    gu = np.clip(greville(ku, 3), 1e-3, 1 - 1e-3)
    gv = greville(kv, 3)
    uu, vv = np.meshgrid(gu, gv, indexing="ij")
    uvw = np.stack([uu.ravel(), vv.ravel(), np.zeros(uu.size)], 1)
    xyz, der = shell.evaluate_with_derivatives(uvw)
    nrm = np.cross(der[:, :, 0], der[:, :, 1])
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    nrm *= np.sign(np.sum(nrm * (xyz - ext.mean(0) * 0), axis=1))[:, None]
    nrm = nrm.reshape(uu.shape + (3,))
    for row in (0, -1):
        m = nrm[row].mean(0)
        nrm[row] = m / np.linalg.norm(m)
    nrm[:, -1] = nrm[:, 0]
    cps = np.stack([outer - thickness * nrm, outer], 2)
    return _right_handed(Volume((3, 3, 1), (ku, kv, kw), cps))


# --- registry and validation -------------------------------------------------------------------------------------
BUILTINS = {
    "quarter-torus": (quarter_torus, {"major_radius": 60.0, "minor_radius": 20.0}),
    "torus": (torus, {"major_radius": 60.0, "minor_radius": 20.0}),
    "twisted-torus": (twisted_torus, {"major_radius": 60.0, "minor_radius": 15.0, "twist": 90.0}),
    "generalized-torus": (generalized_torus, {"major_radius": 60.0, "minor_radius": 15.0}),
    "sphere-shell": (sphere_shell, {"outer_radius": 50.0, "inner_radius": 40.0}),
    "duck-shell": (duck_shell, {"size": 120.0, "thickness": 8.0}),
}

# (smaller, larger, how much smaller at most): a radius that must stay below another one
_ORDERED = {
    "quarter-torus": ("minor_radius", "major_radius", 1.0),
    "torus": ("minor_radius", "major_radius", 1.0),
    "twisted-torus": ("minor_radius", "major_radius", SQRT_HALF),  # the square's corners must clear the axis
    "generalized-torus": ("minor_radius", "major_radius", 0.4),  # corners turn on radius R/2; 0.4 certifies
    "sphere-shell": ("inner_radius", "outer_radius", 1.0),
    "duck-shell": ("thickness", "size", 0.1),
}
_SIGNED = {"twist"}  # may be zero or negative


def _fmt(x):
    return f"{x:g}" if isinstance(x, (int, float)) and not isinstance(x, bool) else repr(x)


def validate_builtin(params, key="model.builtin"):
    """Check a builtin dict; -> (type name, {param: float}) or raise SpecError listing every problem."""
    if not isinstance(params, dict):
        raise SpecError([f"{key}: must be a mapping with a type (got {params!r}, expected e.g. "
                         f"{{type: torus, major_radius: 60, minor_radius: 20}})"])
    problems = []
    kind = params.get("type")
    if kind is None:
        raise SpecError([f"{key}.type: missing (expected one of {', '.join(BUILTINS)})"])
    if kind not in BUILTINS:
        near = difflib.get_close_matches(str(kind), list(BUILTINS), n=1)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        raise SpecError([f"{key}.type: unknown builtin (got {_fmt(kind)}, "
                         f"expected one of {', '.join(BUILTINS)}){hint}"])
    defaults = BUILTINS[kind][1]
    values = dict(defaults)
    for name, value in params.items():
        if name == "type":
            continue
        if name not in defaults:
            near = difflib.get_close_matches(str(name), list(defaults), n=1)
            hint = f" (did you mean '{near[0]}'?)" if near else ""
            problems.append(f"{key}.{name}: unknown key for {kind}{hint} (got {_fmt(value)}, expected one of "
                            f"{', '.join(defaults)})")
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            problems.append(f"{key}.{name}: must be a number (got {_fmt(value)}, expected e.g. {_fmt(defaults[name])})")
            continue
        if name not in _SIGNED and value <= 0:
            problems.append(f"{key}.{name}: must be positive (got {_fmt(value)}, expected > 0)")
            continue
        values[name] = float(value)
    if kind == "twisted-torus" and "twist" not in {p.split(":")[0].rsplit(".", 1)[-1] for p in problems}:
        t = values["twist"]
        if t % 90 != 0:
            lo, hi = 90 * math.floor(t / 90), 90 * math.ceil(t / 90)
            problems.append(f"{key}.twist: must be a multiple of 90 degrees so the square section closes on itself "
                            f"(got {_fmt(t)}, expected e.g. {_fmt(lo)} or {_fmt(hi)})")
    small, large, factor = _ORDERED[kind]
    bad = {p.split(":")[0].rsplit(".", 1)[-1] for p in problems}
    if small not in bad and large not in bad and not values[small] < factor * values[large]:
        limit = factor * values[large]
        what = large if factor == 1.0 else f"{_fmt(factor)} * {large}"
        problems.append(f"{key}.{small}: must be smaller than {what} (got {_fmt(values[small])}, "
                        f"expected < {_fmt(limit)})")
    if problems:
        raise SpecError(problems)
    return kind, values


def make_builtin(params, key="model.builtin"):
    """Build a builtin from its spec dict, e.g. {'type': 'twisted-torus', 'major_radius': 60} -> Volume."""
    kind, values = validate_builtin(params, key)
    vol = BUILTINS[kind][0](**values)
    # the parameter limits above are meant to keep every shape unfolded; the certificate makes sure (~0.05 s)
    from .spline.jacobian import certify_positive

    cert = certify_positive(vol)
    if not cert.ok:
        shown = ", ".join(f"{k}: {_fmt(v)}" for k, v in values.items())
        raise ModelError(f"{key}: the {kind} with {shown} folds or is not certified right-handed "
                         f"({cert.message} at uvw {np.round(cert.where_uvw, 4).tolist()}); expected smaller "
                         f"thickness or radii relative to the size")
    return vol
