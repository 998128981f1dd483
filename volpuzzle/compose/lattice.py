"""The lattice of a tiling's grid vertices, edges and faces, and where periodic seams identify them: a point on a
periodic min face is its max-face twin seen through the seam map, so both cells on a seam share one canonical key."""

import numpy as np

from ..errors import GeometryError


def _others(a):
    return tuple(k for k in range(3) if k != a)


class _Lattice:
    """Integer grid: vertex g (3,) indexes the breaks; edge (a, g) runs from g to g + e_a; face (a, g) is the
    rectangle at g spanned by the other two axes (b, c), b < c. Points on a periodic min face are identified with
    points on the max face (their canonical place)."""

    def __init__(self, n, seams):
        self.n = tuple(int(x) for x in n)
        self.seams = tuple(seams)

    def _to_max(self, g, seam):
        a, swap, flip = seam
        b, c = _others(a)
        jb, jc = g[b], g[c]
        # the inverse of Seam.map_max_to_min on the (integer, break-aligned) face coordinates: unflip, then unswap
        if flip[0]:
            jb = self.n[b] - jb
        if flip[1]:
            jc = self.n[c] - jc
        if swap:
            jb, jc = jc, jb
        out = list(g)
        out[a], out[b], out[c] = self.n[a], jb, jc
        return out

    def vertex(self, g):
        g = list(g)
        for _ in range(8):
            moved = False
            for s in self.seams:
                if g[s[0]] == 0:
                    g = self._to_max(g, s)
                    moved = True
            if not moved:
                return tuple(g)
        raise GeometryError("compose: grid vertices did not settle under the periodic seams")

    def edge(self, a, g):
        """-> (canonical key (axis, g0, g1, g2), reversed: the canonical edge runs the other way)."""
        p0, p1 = list(g), list(g)
        p1[a] += 1
        for _ in range(8):
            moved = False
            for s in self.seams:
                if p0[s[0]] == 0 and p1[s[0]] == 0:
                    p0, p1 = self._to_max(p0, s), self._to_max(p1, s)
                    moved = True
            if not moved:
                break
        else:
            raise GeometryError("compose: grid edges did not settle under the periodic seams")
        ax = next(k for k in range(3) if p0[k] != p1[k])
        rev = p0[ax] > p1[ax]
        lo = p1 if rev else p0
        return (ax, *lo), rev

    def face(self, a, g):
        """-> (canonical key (a, g0, g1, g2), seam (a, swap, flip) the face was seen through, or None)."""
        for s in self.seams:
            if s[0] == a and g[a] == 0:
                b, c = _others(a)
                corners = []
                for db, dc in ((0, 0), (1, 0), (0, 1), (1, 1)):
                    p = list(g)
                    p[b] += db
                    p[c] += dc
                    corners.append(self._to_max(p, s))
                lo = np.min(np.array(corners), axis=0)
                return (a, *(int(x) for x in lo)), s
        return (a, *(int(x) for x in g)), None

    def cell_faces(self, index):
        """The six faces of a cell: (canonical key, min side (so reversed), seam or None, own (a, g))."""
        out = []
        for a in range(3):
            for side in (0, 1):
                g = list(index)
                g[a] += side
                key, seam = self.face(a, g)
                out.append((key, side == 0, seam, (a, tuple(g))))
        return out


def _seam_tuples(tiling):
    out = []
    for a in sorted(tiling.seams):
        if a in tiling.periodic:
            s = tiling.seams[a]
            out.append((int(a), bool(s.swap), tuple(bool(x) for x in s.flip)))
    return tuple(out)


def _seen_through(st, seam):
    """Canonical (max face) local coordinates (k, 2) -> the same points in the min face's own coordinates:
    Seam.map_max_to_min, swap then flip (the cut grids are symmetric, so it holds cell by cell)."""
    if seam is None:
        return st
    _, swap, flip = seam
    st = np.array(st[:, ::-1] if swap else st, dtype=float)
    for k in range(2):
        if flip[k]:
            st[:, k] = 1.0 - st[:, k]
    return st
