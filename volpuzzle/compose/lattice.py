"""The lattice of a tiling's grid vertices, edges and faces, and where periodic seams identify them: a point on a
periodic min face is its max-face twin seen through the seam map, so both cells on a seam share one canonical key."""

from typing import NamedTuple

import numpy as np

from ..errors import GeometryError
from ..grid import other_axes


class PeriodicSeam(NamedTuple):
    """A periodic axis as the lattice sees it: the max face along `axis` is the min face after swapping its two
    face coordinates (swap) and then flipping each (flip: (bool, bool), s -> 1 - s), as spline.seams.Seam."""

    axis: int
    swap: bool
    flip: tuple


class GridKey(NamedTuple):
    """A grid edge or face at grid vertex corner = (i, j, k): the edge runs from it to corner + e_axis; the face is
    the rectangle there spanned by the two axes other than `axis`. Sorts and hashes as the plain tuple."""

    axis: int
    i: int
    j: int
    k: int

    @property
    def corner(self):
        return self[1:]


class CellFace(NamedTuple):
    """One of a cell's six faces. key: the canonical face's GridKey (whose triangles face +e_axis); reverse: the cell's
    min face along the axis, whose outward side is the canonical face's back; seam: the PeriodicSeam the face was
    seen through (None inside the grid); axis and corner: the face as the cell itself places it."""

    key: GridKey
    reverse: bool
    seam: PeriodicSeam | None
    axis: int
    corner: tuple


class Lattice:
    """Integer grid: vertex g (3,) indexes the breaks; edge (a, g) runs from g to g + e_a; face (a, g) is the
    rectangle at g spanned by the other two axes (b, c), b < c. Points on a periodic min face are identified with
    points on the max face (their canonical place). counts: cells per axis; seams: PeriodicSeam tuple."""

    def __init__(self, counts, seams):
        self.counts = tuple(int(x) for x in counts)
        self.seams = tuple(seams)

    def _to_max(self, g, seam):
        a, swap, flip = seam
        b, c = other_axes(a)
        jb, jc = g[b], g[c]
        # the inverse of Seam.map_max_to_min on the (integer, break-aligned) face coordinates: unflip, then unswap
        if flip[0]:
            jb = self.counts[b] - jb
        if flip[1]:
            jc = self.counts[c] - jc
        if swap:
            jb, jc = jc, jb
        out = list(g)
        out[a], out[b], out[c] = self.counts[a], jb, jc
        return out

    def vertex(self, g):
        """Grid vertex g -> its canonical grid vertex (3,) tuple."""
        g = list(g)
        for _ in range(8):
            moved = False
            for s in self.seams:
                if g[s.axis] == 0:
                    g = self._to_max(g, s)
                    moved = True
            if not moved:
                return tuple(g)
        raise GeometryError("compose: grid vertices did not settle under the periodic seams")

    def edge(self, a, g):
        """-> (canonical edge's GridKey, reversed: the canonical edge runs the other way)."""
        p0, p1 = list(g), list(g)
        p1[a] += 1
        for _ in range(8):
            moved = False
            for s in self.seams:
                if p0[s.axis] == 0 and p1[s.axis] == 0:
                    p0, p1 = self._to_max(p0, s), self._to_max(p1, s)
                    moved = True
            if not moved:
                break
        else:
            raise GeometryError("compose: grid edges did not settle under the periodic seams")
        axis = next(k for k in range(3) if p0[k] != p1[k])
        reverse = p0[axis] > p1[axis]
        start = p1 if reverse else p0
        return GridKey(axis, *start), reverse

    def face(self, a, g):
        """-> (canonical face's GridKey, the PeriodicSeam the face was seen through, or None)."""
        for s in self.seams:
            if s.axis == a and g[a] == 0:
                b, c = other_axes(a)
                corners = []
                for db, dc in ((0, 0), (1, 0), (0, 1), (1, 1)):
                    p = list(g)
                    p[b] += db
                    p[c] += dc
                    corners.append(self._to_max(p, s))
                lo = np.min(np.array(corners), axis=0)
                return GridKey(a, *(int(x) for x in lo)), s
        return GridKey(a, *(int(x) for x in g)), None

    def cell_faces(self, index):
        """The six CellFaces of cell `index`, min then max side along u, v, w."""
        out = []
        for a in range(3):
            for side in (0, 1):
                g = list(index)
                g[a] += side
                key, seam = self.face(a, g)
                out.append(CellFace(key, side == 0, seam, a, tuple(g)))
        return out


def periodic_seams(tiling):
    """The tiling's periodic axes as a PeriodicSeam tuple, in axis order."""
    out = []
    for a in sorted(tiling.seams):
        if a in tiling.periodic:
            s = tiling.seams[a]
            out.append(PeriodicSeam(int(a), bool(s.swap), tuple(bool(x) for x in s.flip)))
    return tuple(out)


def seen_through(st, seam):
    """Canonical (max face) local coordinates (k, 2) -> the same points in the min face's own coordinates:
    Seam.map_max_to_min, swap then flip (the cut grids are symmetric, so it holds cell by cell)."""
    if seam is None:
        return st
    st = np.array(st[:, ::-1] if seam.swap else st, dtype=float)
    for k in range(2):
        if seam.flip[k]:
            st[:, k] = 1.0 - st[:, k]
    return st


def seen_back(st, seam):
    """The inverse of seen_through: min face local coordinates (k, 2) -> the same points on the max face (flip,
    then swap)."""
    if seam is None:
        return st
    st = np.array(st, dtype=float)
    for k in range(2):
        if seam.flip[k]:
            st[:, k] = 1.0 - st[:, k]
    return st[:, ::-1] if seam.swap else st
