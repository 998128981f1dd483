"""Small analytic volumes shared by several test modules."""

import numpy as np

from volpuzzle.spline import Volume


def ring(twist=0.0, major=40.0, side=16.0, n=17):
    """A square-section ring around z, periodic in w; the section turns by `twist` radians once round (pi/2: the
    seam swaps u and v).

    The control points sample the exact shape at the Greville abscissae (a quasi-interpolant), and the last slice
    is the first one turned, so the seam closes exactly.
    """
    knots = np.concatenate([[0, 0, 0], np.linspace(0, 1, n - 2), [1, 1, 1]])
    grev = np.array([knots[i + 1:i + 4].mean() for i in range(n)])
    cp = np.zeros((2, 2, n, 3))
    for i, j, m in np.ndindex(2, 2, n):
        s, t = (i - 0.5) * side, (j - 0.5) * side
        phi, th = 2 * np.pi * grev[m], twist * grev[m]
        if m == n - 1:
            phi = 0.0
        er = np.array([np.cos(phi), np.sin(phi), 0.0])
        ez = np.array([0.0, 0.0, 1.0])
        cp[i, j, m] = major * er + (s * np.cos(th) - t * np.sin(th)) * er + (s * np.sin(th) + t * np.cos(th)) * ez
    return Volume((1, 1, 3), ([0, 0, 1, 1], [0, 0, 1, 1], knots), cp)


def half_cone(r0=5.0, slant=150.0, tilt_deg=60.0, wall=8.0, n=13):
    """Half a conical wall: u up the slant (leaning tilt_deg off vertical), v round half a turn, w through the wall.
    Its u faces' normals (the slant) turn with v by up to 2 * tilt over the half turn, like a shell's faces round a
    ring of cells: the duck's."""
    knots = np.concatenate([[0, 0, 0], np.linspace(0, 1, n - 2), [1, 1, 1]])
    grev = np.array([knots[i + 1:i + 4].mean() for i in range(n)])
    tilt = np.radians(tilt_deg)
    along = np.array([np.sin(tilt), np.cos(tilt)])  # (radial, z)
    across = np.array([-np.cos(tilt), np.sin(tilt)])
    cp = np.zeros((2, n, 2, 3))
    for i, j, k in np.ndindex(2, n, 2):
        phi = np.pi * grev[j]
        rz = np.array([r0, 0.0]) + i * slant * along + k * wall * across
        cp[i, j, k] = [rz[0] * np.cos(phi), rz[0] * np.sin(phi), rz[1]]
    return Volume((1, 3, 1), ([0, 0, 1, 1], knots, [0, 0, 1, 1]), cp)
