"""tile: split the parameter domain D into an l x m x n grid of cells (parameter boxes)."""

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .errors import SpecError
from .grid import AXES, piece_id


@dataclass(frozen=True, eq=False)
class Cell:
    """index (i, j, k) in the grid; box (2, 3): row 0 the min parameters, row 1 the max."""

    index: tuple
    box: np.ndarray

    @property
    def id(self):
        return piece_id(self.index)

    @property
    def center(self):
        return self.box.mean(axis=0)

    def face_key(self, axis, high):
        """(axis, the face's parameter along it, its min and max along each other axis): the same for the face two
        neighbouring cells share, so that what is sampled on it serves both. high: the max face, else the min."""
        lo, hi = self.box
        return (int(axis), float(hi[axis] if high else lo[axis]),
                *(float(x) for a in range(3) if a != axis for x in (lo[a], hi[a])))


@dataclass(frozen=True, eq=False)
class Face:
    """A face shared by two cells: the max face (along `axis`) of cell `lower` is the min face of cell `upper`.

    Across a periodic seam, `lower` is a last cell and `upper` a first one, and `seam` maps parameters on
    the lower cell's
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

    @cached_property
    def _face_numbers(self):
        return faces_by_cell(self.faces)  # once per tiling: a scan of every face per cell grows as n^2

    def face_numbers(self, index):
        """Numbers (ascending, into self.faces) of the faces touching one cell."""
        return self._face_numbers.get(tuple(index), ())

    def faces_of(self, index):
        """Faces touching one cell, as (face, side) with side -1 when the cell is on the face's min side, in the
        order of self.faces."""
        index = tuple(index)
        out = []
        for n in self.face_numbers(index):
            f = self.faces[n]
            if f.lower == index:
                out.append((f, +1))
            if f.upper == index:
                out.append((f, -1))
        return out


def faces_by_cell(faces):
    """{cell index: numbers (ascending) of the faces in `faces` that have the cell on either side}."""
    out = {}
    for n, f in enumerate(faces):
        out.setdefault(tuple(f.lower), []).append(n)
        if tuple(f.upper) != tuple(f.lower):
            out.setdefault(tuple(f.upper), []).append(n)
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


def _cell_masses(prefix, pos):
    """Masses (g0, g1, g2) of the cells between break positions pos (three arrays, in boxes of the mass grid), from
    the prefix sums (n+1, n+1, n+1) of a mass that is constant in each box (so linear between grid planes)."""
    vals = prefix
    for a in range(3):
        n = vals.shape[a] - 1
        p = np.clip(pos[a], 0.0, n)
        i = np.minimum(np.floor(p).astype(int), n - 1)
        f = (p - i).reshape([-1 if x == a else 1 for x in range(3)])
        vals = np.take(vals, i, axis=a) * (1 - f) + np.take(vals, i + 1, axis=a) * f
    for a in range(3):
        vals = np.diff(vals, axis=a)
    return vals


def _balanced(breaks, mass, axes, sweeps=4, steps=40):
    """Breaks (three arrays) with the axes in `axes` cut so that the cells hold even shares of the mesh: first at
    the equal-volume quantiles of the mesh along each axis, then each cut moved between its neighbours to lower the
    ratio of the largest to the smallest cell (quantiles of each axis alone leave the bunny's octants 4x apart).
    mass: (n, n, n) fractions of the mesh volume in equal boxes of the domain (cage.mesh_mass)."""
    m = np.asarray(mass, float)
    n = m.shape
    prefix = np.zeros(tuple(k + 1 for k in n))
    prefix[1:, 1:, 1:] = m.cumsum(0).cumsum(1).cumsum(2)
    lo = [b[0] for b in breaks]
    span = [b[-1] - b[0] for b in breaks]
    pos = [(np.asarray(b, float) - b0) / s * k for b, b0, s, k in zip(breaks, lo, span, n, strict=True)]
    for a in axes:
        marg = m.sum(axis=tuple(x for x in range(3) if x != a))
        cum = np.concatenate([[0.0], np.cumsum(marg)]) + np.linspace(0.0, 1e-9, n[a] + 1)  # strictly increasing
        cum /= cum[-1]
        g = len(pos[a]) - 1
        pos[a] = np.concatenate([[0.0], np.interp(np.arange(1, g) / g, cum, np.arange(n[a] + 1)), [float(n[a])]])

    def ratio(p):
        c = _cell_masses(prefix, p)
        return float(c.max() / max(c.min(), 1e-9))

    best = ratio(pos)
    for _ in range(sweeps):
        for a in axes:
            for i in range(1, len(pos[a]) - 1):
                for t in np.linspace(pos[a][i - 1], pos[a][i + 1], steps + 1)[1:-1]:
                    trial = [p.copy() for p in pos]
                    trial[a][i] = t
                    r = ratio(trial)
                    if r < best - 1e-9:
                        best, pos = r, trial
    return tuple(b0 + p / k * s for b0, p, k, s in zip(lo, pos, n, span, strict=True))


def _breaks(vol, grid, splits, axis, mass=None):
    lo, hi = vol.domain[axis]
    n = grid[axis]
    split = splits[axis] if splits is not None else "uniform"
    if split is None or split == "uniform":
        return np.linspace(lo, hi, n + 1)
    if split == "balanced":
        if mass is None:
            raise SpecError(f"splits.{AXES[axis]}: balanced splits follow a mesh's volume (got balanced without a "
                            "mesh model, expected uniform, knots or a list of parameters)")
        return np.linspace(lo, hi, n + 1)  # placed by _balanced once every axis has its breaks
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
    for d, flip, sb in ((0, seam.flip[0], dst[0]), (1, seam.flip[1], dst[1])):
        target = (1 - sb[::-1]) if flip else sb
        have = nb if d == 0 else nc
        if len(target) != len(have) or not np.allclose(target, have, atol=1e-9):
            raise SpecError(
                f"periodic.{AXES[axis]}: the seam {'turns' if seam.swap else 'mirrors'} the {AXES[b]}{AXES[c]} face, "
                f"so the cuts along {AXES[b]} and {AXES[c]} must match across it "
                f"(got {AXES[b]} {np.round(nb, 4).tolist()} and {AXES[c]} {np.round(nc, 4).tolist()}, "
                f"expected the same cuts on both, e.g. equal uniform grids)")

    def index_map(ib, ic):
        s = (np.array([src[0][ib], src[0][ib + 1]]), np.array([src[1][ic], src[1][ic + 1]]))
        if seam.swap:
            s = (s[1], s[0])
        s = tuple(1 - x[::-1] if f else x for x, f in zip(s, seam.flip, strict=True))
        jb = int(np.argmin(np.abs(nb[:-1] - s[0][0])))
        jc = int(np.argmin(np.abs(nc[:-1] - s[1][0])))
        return jb, jc

    return index_map


def tile(vol, grid, splits=None, periodic=(), seams=None, mass=None):
    """Cut D into cells. grid (3,) ints; splits: three of 'uniform' | 'knots' | 'balanced' | cut parameters; periodic:
    axis indices; seams: {axis: Seam} for the periodic axes (from spline.seams.find_seams); mass: for balanced
    splits, (n, n, n) fractions of the mesh volume in equal boxes of the domain (cage.mesh_mass)."""
    seams = dict(seams or {})
    grid = tuple(int(g) for g in grid)
    breaks = tuple(_breaks(vol, grid, splits, a, mass) for a in range(3))
    balanced = [a for a in range(3) if splits is not None and splits[a] == "balanced" and grid[a] > 1]
    if balanced:
        breaks = _balanced(breaks, mass, balanced)
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


def seams_for(spec, vol, found=None):
    """The seams of vol's closed axes (spline.seams.find_seams, or `found` when already found) -> ({axis: seam} of
    those spec.periodic asks to join, {axis: seam} of all found, for the report)."""
    from .spline.seams import find_seams

    found = find_seams(vol) if found is None else found
    return {a: s for a, s in found.items() if a in spec.periodic}, found


def check_grid_vs_tolerance(spec, tiling, fmap):
    """A cell thinner than a few tolerances cannot be printed or joined; say which grid would fit."""
    problems = []
    tol = spec.output.tolerance
    for a in range(3):
        lengths = []
        for cell in tiling.cells.values():
            lo, hi = cell.box
            mid = cell.center
            p0, p1 = mid.copy(), mid.copy()
            p0[a], p1[a] = lo[a], hi[a]
            ts = np.linspace(0, 1, 9)[:, None]
            pts = fmap.evaluate(p0 + ts * (p1 - p0))
            lengths.append(float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))))
        smallest = min(lengths)
        # Below about ten tolerances the chords of a piece are as coarse as the piece itself.
        if smallest < 10 * tol:
            fit = int(spec.grid[a] * smallest / (10 * tol))
            advice = (f"at most {fit} along {AXES[a]} or output.tolerance at most {smallest / 10:.3g} mm" if fit >= 1
                      else f"output.tolerance at most {smallest / 10:.3g} mm")
            problems.append(
                f"grid: {spec.grid[a]} pieces along {AXES[a]} make pieces {smallest:.3g} mm thin, too thin for "
                f"output.tolerance {tol:g} mm (got {spec.grid[a]}, expected {advice})")
    if problems:
        raise SpecError(problems, source=spec.source)
