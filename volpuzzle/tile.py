"""tile: split the parameter domain D into an l x m x n grid of cells (parameter boxes)."""

from dataclasses import dataclass

import numpy as np

from .errors import SpecError

AXES = "uvw"


@dataclass(frozen=True, eq=False)
class Cell:
    """index (i, j, k) in the grid; box (2, 3): row 0 the min parameters, row 1 the max."""

    index: tuple
    box: np.ndarray

    @property
    def id(self):
        return "p" + "-".join(str(i) for i in self.index)

    @property
    def center(self):
        return self.box.mean(axis=0)


@dataclass(frozen=True, eq=False)
class Face:
    """A face shared by two cells: the max face (along `axis`) of cell `lower` is the min face of cell `upper`.

    Across a periodic seam, `lower` is a last cell and `upper` a first one, and `seam` maps parameters on the lower cell's
    max face to the coincident parameters on the upper cell's min face (Seam.map_max_to_min).
    """

    axis: int
    lower: tuple
    upper: tuple
    seam: object = None


@dataclass(frozen=True, eq=False)
class Tiling:
    """domain (2, 3); breaks: three arrays of grid[a] + 1 increasing parameters; cells by index; faces between cells."""

    domain: np.ndarray
    breaks: tuple
    periodic: tuple
    seams: dict
    cells: dict
    faces: tuple

    @property
    def grid(self):
        return tuple(len(b) - 1 for b in self.breaks)

    def cell(self, index):
        return self.cells[tuple(index)]

    def faces_of(self, index):
        """Faces touching one cell, as (face, side) with side -1 when the cell is on the face's min side."""
        index = tuple(index)
        out = []
        for f in self.faces:
            if f.lower == index:
                out.append((f, +1))
            if f.upper == index:
                out.append((f, -1))
        return out


def _knot_cuts(knots, degree, count, axis):
    """Pick `count` interior knots as cuts: strongest breaks (highest multiplicity) first, then nearest to uniform."""
    k = np.asarray(knots)
    inner = k[degree + 1:len(k) - degree - 1]
    values, mult = np.unique(inner, return_counts=True)
    if len(values) < count:
        raise SpecError(
            f"splits.{AXES[axis]}: 'knots' gives only {len(values)} interior knots, too few for {count + 1} pieces "
            f"(got grid {count + 1} along {AXES[axis]}, expected at most {len(values) + 1}, or use uniform splits)")
    if len(values) == count:
        return values
    lo, hi = k[degree], k[-degree - 1]
    targets = lo + (hi - lo) * np.arange(1, count + 1) / (count + 1)
    chosen = []
    for t in targets:
        # Prefer C0/C1 breaks (high multiplicity), then the knot nearest to the uniform position.
        free = [i for i in range(len(values)) if i not in chosen]
        best = min(free, key=lambda i: (-mult[i], abs(values[i] - t)))
        chosen.append(best)
    return np.sort(values[chosen])


def _breaks(vol, grid, splits, axis):
    lo, hi = vol.domain[axis]
    n = grid[axis]
    split = splits[axis] if splits is not None else "uniform"
    if split is None or split == "uniform":
        return np.linspace(lo, hi, n + 1)
    if split == "knots":
        cuts = _knot_cuts(vol.knots[axis], vol.degrees[axis], n - 1, axis) if n > 1 else np.empty(0)
        return np.concatenate([[lo], cuts, [hi]])
    cuts = np.asarray(split, dtype=float).ravel()
    key = f"splits.{AXES[axis]}"
    if len(cuts) != n - 1:
        raise SpecError(f"{key}: {len(cuts)} parameters for {n} pieces (got {cuts.tolist()}, expected {n - 1} values)")
    if len(cuts) and (cuts[0] <= lo or cuts[-1] >= hi or np.any(np.diff(cuts) <= 0)):
        raise SpecError(f"{key}: parameters must increase strictly inside the domain "
                        f"(got {cuts.tolist()}, expected values in ({lo:g}, {hi:g}))")
    return np.concatenate([[lo], cuts, [hi]])


def _normalised(b):
    return (b - b[0]) / (b[-1] - b[0])


def _seam_index_map(seam, axis, breaks):
    """Map of (index along b, index along c) of a last cell to the first cell it meets across the seam."""
    b, c = [a for a in range(3) if a != axis]
    nb, nc = _normalised(breaks[b]), _normalised(breaks[c])
    src = (nb, nc)
    dst = (nc, nb) if seam.swap else (nb, nc)
    # The seam maps the face's grid lines onto the grid lines of the other side only when they match.
    for d, flip, sb, name in ((0, seam.flip[0], dst[0], AXES[b]), (1, seam.flip[1], dst[1], AXES[c])):
        target = (1 - sb[::-1]) if flip else sb
        have = nb if d == 0 else nc
        if len(target) != len(have) or not np.allclose(target, have, atol=1e-9):
            raise SpecError(
                f"periodic.{AXES[axis]}: the seam {'turns' if seam.swap else 'mirrors'} the {AXES[b]}{AXES[c]} face, so the "
                f"cuts along {AXES[b]} and {AXES[c]} must match across it (got {AXES[b]} {np.round(nb, 4).tolist()} and "
                f"{AXES[c]} {np.round(nc, 4).tolist()}, expected the same cuts on both, e.g. equal uniform grids)")

    def index_map(ib, ic):
        s = (np.array([src[0][ib], src[0][ib + 1]]), np.array([src[1][ic], src[1][ic + 1]]))
        if seam.swap:
            s = (s[1], s[0])
        s = tuple(1 - x[::-1] if f else x for x, f in zip(s, seam.flip))
        jb = int(np.argmin(np.abs(nb[:-1] - s[0][0])))
        jc = int(np.argmin(np.abs(nc[:-1] - s[1][0])))
        return jb, jc

    return index_map


def tile(vol, grid, splits=None, periodic=(), seams=None):
    """Cut D into cells. grid (3,) ints; splits: three of 'uniform' | 'knots' | cut parameters; periodic: axis indices;
    seams: {axis: Seam} for the periodic axes (from spline.seams.find_seams)."""
    seams = dict(seams or {})
    grid = tuple(int(g) for g in grid)
    breaks = tuple(_breaks(vol, grid, splits, a) for a in range(3))
    cells = {}
    for idx in np.ndindex(*grid):
        box = np.array([[breaks[a][idx[a]] for a in range(3)], [breaks[a][idx[a] + 1] for a in range(3)]])
        box.setflags(write=False)
        cells[idx] = Cell(idx, box)
    faces = []
    for a in range(3):
        for idx in np.ndindex(*grid):
            if idx[a] + 1 < grid[a]:
                up = list(idx)
                up[a] += 1
                faces.append(Face(a, idx, tuple(up)))
    for a in sorted(periodic):
        if a not in seams:
            raise SpecError(f"periodic.{AXES[a]}: the min and max {AXES[a]} faces of the model do not meet in space "
                            f"(got periodic [{AXES[a]}], expected only axes whose faces coincide)")
        b, c = [x for x in range(3) if x != a]
        index_map = _seam_index_map(seams[a], a, breaks)
        for idx in np.ndindex(*grid):
            if idx[a] != grid[a] - 1:
                continue
            jb, jc = index_map(idx[b], idx[c])
            up = [0, 0, 0]
            up[a], up[b], up[c] = 0, jb, jc
            if grid[a] == 1 and tuple(up) == idx:
                continue  # a single cell closing on itself has no neighbour to join
            faces.append(Face(a, idx, tuple(up), seams[a]))
    domain = vol.domain_array.copy()
    domain.setflags(write=False)
    return Tiling(domain, breaks, tuple(sorted(periodic)), seams, cells, tuple(faces))
