"""Resource limits: the work a spec asks for, estimated from the spec and the model before any of it is done.

A few bytes of spec or model can ask for hours of work and more memory than the machine has (a 200^3 random map,
a million pieces, a tolerance of a nanometre). Each estimate here costs milliseconds, so `validate` and `build`
refuse such a spec at once, saying the limit and what would fit. A user who means it raises a limit in the spec
(`limits: {triangles: 20000000}`) or lifts them all with `--allow-large`.
"""

from __future__ import annotations

import math
import os
import struct
import zipfile
from dataclasses import dataclass

import numpy as np

from .errors import SpecError
from .io import regular_file_problem

__all__ = ["Limits", "LIMIT_HELP", "estimate_triangles", "check_spec_limits", "check_model_limits",
           "warp_memory_bytes", "mesh_file_triangles"]

# What one control point of the random map costs while its Jacobian is certified (measured: 36^3 points took
# 720 MB, 20^3 took 137 MB; the certificate's Bernstein coefficients grow with the cube of the points per axis).
_WARP_BYTES_PER_POINT = 15e3
# Triangles per (mm^2 / (mm * mm)): a chord error t over a radius of curvature R allows edges of about sqrt(8 R t);
# calibrated on the quarter torus (real count 1.8x the estimate) and the twisted torus (0.45x) at 0.3 to 0.01 mm.
_TRIANGLES_PER_AREA = 0.75


@dataclass(frozen=True)
class Limits:
    """Upper bounds on the work of one build. unlimited (--allow-large) lifts them all."""
    pieces: int = 2048  # grid cells
    control_points: int = 32  # randomize.control_points, per axis
    triangles: int = 2_000_000  # estimated triangles of all pieces together
    mesh_triangles: int = 1_000_000  # triangles of a mesh model
    unlimited: bool = False


LIMIT_HELP = {
    "pieces": "grid cells (pieces) of one puzzle",
    "control_points": "randomize.control_points per axis",
    "triangles": "estimated triangles of all pieces together",
    "mesh_triangles": "triangles of a mesh model",
}
_RAISE = "raise limits.{key} in the spec or pass --allow-large if you mean it"


def _over(limits: Limits, key: str, value) -> bool:
    return not limits.unlimited and value > getattr(limits, key)


def warp_memory_bytes(control_points: int) -> float:
    """Memory the certificate of a random map with control_points per axis needs, roughly (bytes)."""
    return _WARP_BYTES_PER_POINT * float(control_points) ** 3


def _gb(x: float) -> str:
    return f"{x / 1e9:.3g} GB" if x >= 1e8 else f"{x / 1e6:.3g} MB"


def check_spec_limits(spec) -> None:
    """Refuse what the spec alone shows to be too large: pieces, the random map, a mesh model's triangles.
    Raises one SpecError listing every limit passed."""
    lim = spec.limits
    problems = []
    pieces = math.prod(int(g) for g in spec.grid)
    if _over(lim, "pieces", pieces):
        fit = _fit_grid(spec.grid, lim.pieces)
        problems.append(f"grid: {' x '.join(str(g) for g in spec.grid)} = {pieces:.4g} pieces is more than the "
                        f"limit of {lim.pieces} (got {list(spec.grid)}, expected at most {lim.pieces} pieces, e.g. "
                        f"{fit}; {_RAISE.format(key='pieces')})")
    r = spec.randomize
    if r is not None and _over(lim, "control_points", r.control_points):
        problems.append(f"randomize.control_points: {r.control_points}^3 control points need about "
                        f"{_gb(warp_memory_bytes(r.control_points))} to prove the map one-to-one, more than the "
                        f"limit of {lim.control_points} per axis ({_gb(warp_memory_bytes(lim.control_points))}) "
                        f"(got {r.control_points}, expected 4 to {lim.control_points}; "
                        f"{_RAISE.format(key='control_points')})")
    if spec.model.mesh is not None:
        n = mesh_file_triangles(spec.model.mesh)
        if n is not None and _over(lim, "mesh_triangles", n):
            problems.append(f"model.mesh: {spec.model.mesh.name} has about {n:,} triangles, more than the limit of "
                            f"{lim.mesh_triangles:,} (got {n:,}, expected at most {lim.mesh_triangles:,}: simplify "
                            f"the mesh, e.g. decimate it in a mesh editor; {_RAISE.format(key='mesh_triangles')})")
    if problems:
        raise SpecError(problems, source=spec.source)


def _fit_grid(grid, limit: int) -> list:
    """The grid scaled down evenly along its split axes until it has at most `limit` cells."""
    fit = [int(g) for g in grid]
    for _ in range(3):
        if math.prod(fit) <= limit:
            break
        free = [a for a in range(3) if fit[a] > 1]
        f = (limit / math.prod(fit)) ** (1 / len(free))
        fit = [max(1, int(fit[a] * f)) if a in free else 1 for a in range(3)]
    while math.prod(fit) > limit:
        fit[fit.index(max(fit))] -= 1
    return fit


def _breaks(domain, n, split):
    lo, hi = domain
    if isinstance(split, tuple):
        return np.r_[lo, np.asarray(split, float), hi]
    return np.linspace(lo, hi, int(n) + 1)


def cut_surface_area(vol, grid, splits, samples: int = 9) -> float:
    """mm^2 of every cell face of the tiling (outer faces once, inner cut faces once): the surface compose meshes.
    Sampled on a samples x samples lattice per cut surface; the cost is (cuts) x samples^2 evaluations."""
    dom = np.asarray(vol.domain, float)
    total = 0.0
    t = np.linspace(0.0, 1.0, samples)
    for a in range(3):
        b, c = [k for k in range(3) if k != a]
        cuts = _breaks(dom[a], grid[a], splits[a])
        if len(cuts) > 65:  # more cuts change the estimate little: sample 65 and scale
            scale = (len(cuts)) / 65.0
            cuts = np.linspace(cuts[0], cuts[-1], 65)
        else:
            scale = 1.0
        s, r = np.meshgrid(dom[b, 0] + t * (dom[b, 1] - dom[b, 0]), dom[c, 0] + t * (dom[c, 1] - dom[c, 0]),
                           indexing="ij")
        uvw = np.zeros((len(cuts), samples, samples, 3))
        uvw[..., a] = cuts[:, None, None]
        uvw[..., b] = s
        uvw[..., c] = r
        with np.errstate(all="ignore"):
            p = np.asarray(vol.evaluate(uvw.reshape(-1, 3)), float).reshape(len(cuts), samples, samples, 3)
            d1 = p[:, 1:, 1:] - p[:, :-1, :-1]
            d2 = p[:, :-1, 1:] - p[:, 1:, :-1]
            area = 0.5 * np.linalg.norm(np.cross(d1, d2), axis=-1).sum()
        total += scale * float(area)
    return total


def estimate_triangles(vol, grid, splits, tolerance: float, volume_mm3: float) -> float:
    """Triangles compose will make, roughly: the cut surfaces' area over the area a triangle within `tolerance`
    covers on a surface curved like a piece (radius of curvature about the size of a piece)."""
    pieces = math.prod(int(g) for g in grid)
    area = cut_surface_area(vol, grid, splits)
    radius = max((abs(volume_mm3) / pieces) ** (1 / 3), 1e-9)
    return _TRIANGLES_PER_AREA * area / (radius * float(tolerance)) + 12.0 * pieces


def check_model_limits(spec, vol) -> None:
    """Refuse an output.tolerance that would make more triangles than the limit, and non-finite geometry
    (control points so large that areas overflow). vol: the model (or cage) in mm."""
    lim = spec.limits
    cps = np.asarray(vol.control_points, float).reshape(-1, 3)
    with np.errstate(all="ignore"):
        volume_mm3 = float(np.prod(cps.max(axis=0) - cps.min(axis=0)))  # the hull's box: cheap, and enough here
    tol = spec.output.tolerance
    n = estimate_triangles(vol, spec.grid, spec.splits, tol, volume_mm3)
    if not math.isfinite(n):
        raise SpecError(["model: its size overflows double precision (the surface area is not finite; got "
                         "coordinates too large, expected a model of at most a few kilometres)"], source=spec.source)
    if _over(lim, "triangles", n):
        fit = tol * n / lim.triangles
        raise SpecError([f"output.tolerance: {tol:g} mm would make about {n:.3g} triangles, more than the limit of "
                         f"{lim.triangles:,} (got {tol:g}, expected at least {fit:.2g} mm for this model and grid; "
                         f"{_RAISE.format(key='triangles')})"], source=spec.source)


def mesh_file_triangles(path):
    """Triangles a mesh file holds, from its header or a quick count, without parsing it (nor importing trimesh)
    -> int, or None when the file cannot tell (the reader then decides)."""
    path = os.fspath(path)
    if regular_file_problem(path):
        return None
    ext = os.path.splitext(path)[1].lower()
    size = os.path.getsize(path)
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
            if ext == ".stl":
                if size >= 84:
                    count = int(struct.unpack("<I", head[80:84])[0])
                    if 84 + 50 * count == size or not head.lstrip()[:5].lower() == b"solid":
                        return min(count, (size - 84) // 50)  # a lying header is the reader's to report
                return size // 250  # an ASCII facet takes about 250 bytes
            if ext == ".ply":
                for line in head.split(b"end_header")[0].splitlines():
                    tok = line.split()
                    if tok[:2] == [b"element", b"face"] and len(tok) == 3 and tok[2].isdigit():
                        return int(tok[2])
                return None
            if ext == ".off":
                rows = [r.split(b"#")[0].split() for r in head.splitlines()]
                rows = [r for r in rows if r]
                if len(rows) > 1 and len(rows[1]) >= 2 and rows[1][1].isdigit():
                    return int(rows[1][1])
                return None
            if ext == ".obj":
                f.seek(0)
                count, last = 0, b"\n"
                while True:
                    chunk = f.read(1 << 22)
                    if not chunk:
                        return count
                    count += (last + chunk).count(b"\nf ")
                    last = chunk[-1:]
        if ext == ".3mf":
            with zipfile.ZipFile(path) as z:
                return sum(i.file_size for i in z.infolist() if i.filename.endswith(".model")) // 100
        if ext == ".glb":
            return size // 36
    except (OSError, ValueError, zipfile.BadZipFile, struct.error):
        return None
    return None
