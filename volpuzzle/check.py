"""The build's self-checks: every piece a closed solid, volumes adding up, no two pieces overlapping.

The figures go into report.json "checks"; `passed` False fails the build. `check_directory` runs the
same checks on a built output folder from its files alone (`volpuzzle check DIR`).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from .errors import GeometryError, ModelError, VolpuzzleError
from .geometry import boolean, boxes_nested, check_status, cylinder, is_ok, joined, kernel_arrays
from .geometry import memo as _memo
from .grid import frame_from_direction

__all__ = ["check_pieces", "closed_problem", "signed_volume", "overlap_volume", "shifted_overlap",
           "candidate_pairs", "failure_message", "assert_passed", "check_directory", "piece_solid",
           "check_joint_graph", "check_printability", "piece_bed_contact", "bed_contact_problem", "pin_fit",
           "fit_line", "neighbour_gaps", "report_face_gaps", "pairs_apart"]


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (divergence theorem): positive when normals point outwards."""
    if len(faces) == 0:
        return 0.0
    # Centre first: the sum of tetrahedra is exact for any origin, but far origins cost digits.
    v = np.asarray(vertices, dtype=np.float64)
    v = v - v.mean(axis=0)
    a, b, c = (v[np.asarray(faces)[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def closed_problem(mesh: trimesh.Trimesh):
    """None if the mesh is a closed solid (watertight, consistently wound, one body, positive volume),
    else a short description of what is wrong."""
    return _memo(mesh, "closed", lambda: _closed_problem(mesh))


def remember_closed(mesh: trimesh.Trimesh, problem) -> None:
    """closed_problem(mesh) as already found (in a worker, for a copy of the same arrays): the checks ask again."""
    _memo(mesh, "closed", lambda: problem)


def _closed_problem(mesh):
    if len(mesh.faces) == 0:
        return "no triangles"
    if _plainly_closed(mesh):
        return None
    # Merge coincident vertices first: what a reader of the STL sees is the welded mesh.
    m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True, validate=False)
    if not m.is_watertight:
        edges = trimesh.grouping.group_rows(m.edges_sorted, require_count=1)
        return f"not watertight ({len(edges)} open edges)" if len(edges) else "not watertight (non-manifold edges)"
    if not m.is_winding_consistent:
        return "inconsistent winding"
    bodies = joined(m.face_adjacency, len(m.faces))[0]  # the triangles joined across the edges they share
    if bodies != 1:
        # trimesh's body_count joins bodies at a shared vertex; the loader (io.mesh.mesh_problems) does not, and a
        # piece of two parts that touch at a point prints as two parts
        pinch = " that meet only at vertices (a pinch)" if m.body_count < bodies else ""
        return f"{bodies} separate bodies{pinch}, expected 1"
    vol = signed_volume(m.vertices, m.faces)
    if not vol > 0:
        return f"volume {vol:.6g} mm^3 is not positive (normals point inwards)"
    return None


def _plainly_closed(mesh) -> bool:
    """True when the mesh is a closed solid just as it is: every vertex used and none that trimesh's merge would join
    to another, no triangle repeating a vertex, and io.mesh.mesh_problems (the loader's own numpy test: every edge
    twice and oppositely wound, one body, outward) finds nothing. Then _closed_problem's trimesh route (~5 ms a
    piece: 6 of the check's 49 CPU s at 1024 pieces) would find nothing either; False only means: ask it, for what
    is wrong."""
    from .io.mesh import mesh_problems

    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces, dtype=np.int64)
    n = len(v)
    if f.ndim != 2 or f.shape[1] != 3 or n == 0 or f.min() < 0 or f.max() >= n:
        return False
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])):
        return False
    used = np.zeros(n, dtype=bool)
    used[f.ravel()] = True
    if not used.all() or not np.all(np.isfinite(v)):
        return False
    # the very rounding trimesh's merge_vertices uses (tol.merge, rounded as it rounds: unique_rows' own digits
    # subtract 1e-6 first, and joined two vertices trimesh keeps apart, or kept apart two it joins): no two vertices
    # may share it
    keys = (v * 10 ** trimesh.util.decimal_to_digits(trimesh.tol.merge)).round().astype(np.int64)
    if len(trimesh.grouping.unique_rows(keys)[0]) != n:
        return False
    # mesh_problems counts bodies across edges, stricter than trimesh's vertex groups (a pinch sends it to trimesh),
    # and its volume is uncentred: the centred sum below is the one the trimesh route judges by
    return not mesh_problems(mesh) and signed_volume(v, f) > 0


def piece_solid(mesh: trimesh.Trimesh, pid: str):
    """manifold3d.Manifold of a closed mesh, or the engine's complaint as a string; made once per mesh, so the
    overlap check, the joint check and the assembly replay share it (treat it as read-only)."""
    def make():
        from .geometry import manifold_from_mesh

        try:
            return manifold_from_mesh(mesh.vertices, mesh.faces, f"piece {pid}", keep_faces=False)
        except GeometryError as e:
            return str(e)

    return _memo(mesh, "solid", make)


def solid_problem(mesh: trimesh.Trimesh, pid: str):
    """piece_solid's complaint about the mesh, or None when the engine makes its solid; remembered per mesh, also as
    found by another process (check_pieces), so that asking needs no solid here."""
    def make():
        solid = piece_solid(mesh, pid)
        return solid if isinstance(solid, str) else None

    return _memo(mesh, "solid problem", make)


def remember_solid_problem(mesh: trimesh.Trimesh, problem) -> None:
    """solid_problem(mesh) as already found (in a worker, for a copy of the same arrays): the joint check asks."""
    _memo(mesh, "solid problem", lambda: problem)


def overlap_volume(a, b) -> float:
    """Volume common to two manifold3d.Manifolds (0 for solids that only touch)."""
    inter = a ^ b
    if not is_ok(inter):
        raise GeometryError(f"intersection failed with status {inter.status()}")
    return float(inter.volume())


# A direction in no special position: no grid or symmetry plane of a model is normal to it.
_SHIFT_DIR = np.array([1.0, np.sqrt(2.0), np.sqrt(3.0)]) / np.sqrt(6.0)


def shifted_overlap(a, b, budget: float):
    """(estimate, error bound) of vol(a ∩ b), measured with b moved by a tiny shift t.

    Neighbouring pieces share their faces exactly, and coincident faces are manifold3d's slow path
    (5-10x slower than solids in general position). Moving b by t gives general position, and
    |vol(a ∩ (b + t)) - vol(a ∩ b)| <= vol(b Δ (b + t)) <= |t| * area(∂b), so t is chosen to keep that
    bound near budget (and well above the engine's tolerance).
    """
    shift, area = _shift_of(b, budget, _tolerance(a, b))
    return _moved_overlap(a, b, shift), shift * area


def _tolerance(a, b):
    """The engine's tolerance (mm) of a Boolean of two manifold3d.Manifolds."""
    return max(float(a.get_tolerance()), float(b.get_tolerance()), 1e-12)


def _shift_of(b, budget, tol):
    """(shift mm, area of b mm^2) of shifted_overlap, for the engine's tolerance tol (mm)."""
    area = max(float(b.surface_area()), 1e-12)
    return min(max(budget / area, 1e3 * tol), 1e-3), area


def _moved_overlap(a, b, shift):
    """vol(a ∩ (b + shift along _SHIFT_DIR)) mm^3."""
    return overlap_volume(a, b.translate(tuple(shift * _SHIFT_DIR)))


def candidate_pairs(bounds: np.ndarray, min_common_volume: float = 0.0, chunk: int = 1 << 20):
    """Pairs (i, j), i < j, whose bounding boxes share more than min_common_volume: a sweep along x.

    bounds: (n, 2, 3). Two solids cannot overlap by more than their boxes share, so pairs at or below
    the limit need no Boolean at all (face neighbours of an unrandomized grid share a box of volume 0).
    The sweep's candidates (boxes that meet along x) are tested in vectorised blocks of about `chunk` pairs.
    """
    bounds = np.asarray(bounds, float).reshape(-1, 2, 3)
    n = len(bounds)
    order = np.argsort(bounds[:, 0, 0], kind="stable")
    lo_x = bounds[order, 0, 0]
    # after position a, the boxes that start before box a ends along x: positions a+1 .. stop[a]-1
    stop = np.searchsorted(lo_x, bounds[order, 1, 0], side="left")
    first = np.arange(1, n + 1)
    count = np.maximum(stop - first, 0)
    ends = np.cumsum(count)
    found = []
    a = 0
    while a < n:
        # whole sweep rows per block, each block about `chunk` pairs
        b = max(a + 1, int(np.searchsorted(ends, (ends[a - 1] if a else 0) + chunk, side="right")))
        b = min(b, n)
        rows = np.repeat(np.arange(a, b), count[a:b])
        if len(rows):
            offset = np.arange(len(rows)) - np.repeat(np.cumsum(count[a:b]) - count[a:b], count[a:b])
            i, j = order[rows], order[first[rows] + offset]
            common = np.clip(np.minimum(bounds[i, 1], bounds[j, 1]) - np.maximum(bounds[i, 0], bounds[j, 0]), 0, None)
            meet = np.all(common > 0, axis=1) & (np.prod(common, axis=1) > min_common_volume)
            found.append(np.stack([np.minimum(i, j)[meet], np.maximum(i, j)[meet]], axis=1))
        a = b
    pairs = np.concatenate(found) if found else np.zeros((0, 2), int)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    return [(int(i), int(j)) for i, j in pairs]


def check_pieces(pieces: Sequence[tuple[str, trimesh.Trimesh]], expected_volume_mm3: float,
                 volume_tolerance: float = 0.005, overlap_fraction: float = 1e-3,
                 exact_overlaps: bool = False, workers=None, apart=()) -> dict:
    """Check pieces [(id, mesh in mm)] -> the report's "checks" dict.

    Keys: all_closed, closed_failures (ids), volume_sum_mm3, expected_volume_mm3, volume_error (relative,
    signed), volume_tolerance, max_overlap_mm3, max_overlap_pair, overlap_limit_mm3 (overlap_fraction of the
    smallest piece's volume), overlap_error_bound_mm3, overlap_pairs_tested, overlap_pairs_apart (of those, the
    ones `apart` settled), overlap_time_s, failures (sentences), passed. Overlaps are measured for pairs whose boxes
    share more than the limit, with one piece shifted by a hair (see shifted_overlap; error bound 1% of the limit)
    unless exact_overlaps. apart: pairs of ids (frozensets) already proved disjoint (the keys of pairs_apart), which
    overlap by 0 without a Boolean. workers: a volpuzzle.workers.Workers that measures some of the pairs (the same
    figures).
    """
    ids = [str(p[0]) for p in pieces]
    meshes = [p[1] for p in pieces]
    failures = []
    closed_failures = []
    volumes = np.zeros(len(meshes))
    for k, (pid, mesh) in enumerate(zip(ids, meshes, strict=True)):
        problem = closed_problem(mesh)
        if problem:
            closed_failures.append(pid)
            failures.append(f"piece {pid} is not a closed solid: {problem}")
        volumes[k] = abs(signed_volume(mesh.vertices, mesh.faces))
    volume_sum = float(volumes.sum())
    expected = float(expected_volume_mm3)
    volume_error = (volume_sum - expected) / expected if expected > 0 else float("inf")
    if not abs(volume_error) <= volume_tolerance:
        failures.append(f"piece volumes add up to {volume_sum:.6g} mm^3, expected {expected:.6g} "
                        f"(error {volume_error:+.3%}, limit {volume_tolerance:.3%})")

    good = [k for k, pid in enumerate(ids) if pid not in set(closed_failures)]
    limit = overlap_fraction * float(volumes[good].min()) if good else 0.0
    t0 = time.perf_counter()
    max_overlap, max_pair, tested, max_bound, settled = 0.0, [], 0, 0.0, 0
    if len(good) > 1:
        bounds = np.array([meshes[k].bounds for k in good])
        pairs = candidate_pairs(bounds, min_common_volume=limit)
        measured = [(a, b) for a, b in pairs if frozenset((ids[good[a]], ids[good[b]])) not in apart]
        tested = settled = len(pairs) - len(measured)
        from .workers import MeshRef, in_tasks, map_pieces

        # each process makes the solids of the pairs it measures (the engine may refuse one: then its pairs are not
        # measured); made here first, they were ~2 s of this process at 1024 pieces with the workers idle
        used = {k for pair in measured for k in pair}
        shared = ({k: (MeshRef(meshes[good[k]]), ids[good[k]]) for k in used}, exact_overlaps, 0.01 * limit)
        chunks = in_tasks(measured, _PAIRS_PER_TASK)
        found = map_pieces(workers, _overlaps, chunks, shared=shared, what="check")
        named = set()
        for (a, b), (v, bound, problems) in zip(measured, [r for chunk in found for r in chunk], strict=True):
            for k, problem in zip((a, b), problems, strict=True):
                if k not in named:  # each piece once, where its first pair names it
                    named.add(k)
                    remember_solid_problem(meshes[good[k]], problem)
                    if problem is not None:
                        failures.append(f"{problem}; its overlaps were not measured")
            if v is None:
                continue
            max_bound = max(max_bound, bound)
            tested += 1
            if v > max_overlap:
                max_overlap, max_pair = v, [ids[good[a]], ids[good[b]]]
    overlap_time = time.perf_counter() - t0
    if max_overlap > limit:
        failures.append(f"pieces {max_pair[0]} and {max_pair[1]} overlap by {max_overlap:.4g} mm^3 "
                        f"(limit {limit:.4g} mm^3)")
    return {
        "all_closed": not closed_failures,
        "closed_failures": closed_failures,
        "volume_sum_mm3": volume_sum,
        "expected_volume_mm3": expected,
        "volume_error": volume_error,
        "volume_tolerance": volume_tolerance,
        "max_overlap_mm3": max_overlap,
        "max_overlap_pair": max_pair,
        "overlap_limit_mm3": limit,
        "overlap_error_bound_mm3": max_bound,
        "overlap_pairs_tested": tested,
        "overlap_pairs_apart": settled,
        "overlap_time_s": round(overlap_time, 4),
        "failures": failures,
        "passed": not failures,
    }


_PAIRS_PER_TASK = 12  # overlap pairs per worker task at least (workers.in_tasks): ~50 ms


def _overlaps(shared, pairs):
    """[(overlap mm^3, error bound, (problem of k, problem of l))] of pairs (k, l) of check_pieces, wherever they are
    measured: shared ({k: (MeshRef, piece id)}, exact, shift budget mm^3). A problem is the engine's complaint about a
    piece's solid (piece_solid), else None; a pair with one is not measured (overlap and bound None)."""
    from .assembly import parts_apart, piece_extents

    refs, exact, budget = shared
    out = []
    known = {}  # k -> (solid, extents): a chunk's pairs share their pieces, and each memo look-up hashes the mesh

    def of(k):
        if k not in known:
            known[k] = (piece_solid(refs[k][0].mesh, refs[k][1]), piece_extents(refs[k][0].mesh))
        return known[k]

    for a, b in pairs:
        (sa, ea), (sb, eb) = of(a), of(b)
        problems = tuple(s if isinstance(s, str) else None for s in (sa, sb))
        if problems != (None, None):
            out.append((None, None, problems))
            continue
        tol = _tolerance(sa, sb)
        shift, area = (0.0, 0.0) if exact else _shift_of(sb, budget, tol)
        # Solids whose parts lie apart share nothing, which is what the Boolean finds of them (~half the pairs of a
        # build: neighbours stand a face clearance apart) at a fraction of its cost
        if parts_apart(ea, eb, shift * _SHIFT_DIR, _APART_MARGIN + 10.0 * tol):
            out.append((0.0, shift * area, problems))
        elif exact:
            out.append((overlap_volume(sa, sb), 0.0, problems))
        else:
            out.append((_moved_overlap(sa, sb, shift), shift * area, problems))
    return out


_APART_MARGIN = 1e-6  # mm parts must lie apart by to count as disjoint: far above the rounding of their projections


def failure_message(checks: dict, what: str = "the build") -> str:
    """One line for the user saying every check that failed."""
    parts = checks.get("failures") or ["see report.json checks"]
    return f"{what} failed its own checks: " + "; ".join(parts)


def assert_passed(checks: dict, what: str = "the build") -> dict:
    """Raise GeometryError with every failure unless checks["passed"]; returns checks."""
    if not checks.get("passed", False):
        raise GeometryError(failure_message(checks, what))
    return checks


_REPORT_MAX_BYTES = 64 << 20  # report.json of a 10k-piece puzzle is ~20 MB
_PIECE_MAX_BYTES = 1 << 30


def _inside_file(directory: Path, rel, field: str, max_bytes: int) -> tuple[Path, bytes]:
    """(path, bytes) of the regular file `rel` inside directory, read without following any symlink; raises
    VolpuzzleError naming `field` for anything else: an absolute path, '..', a symlink anywhere on the way, a
    FIFO or device, a file too large. A checker run on a folder someone sent must read that folder only."""
    import errno
    import os
    import stat

    if not isinstance(rel, str) or not rel or "\x00" in rel:
        raise VolpuzzleError(f"{field}: not a file name inside the folder (got {rel!r}, expected a relative path "
                             f"such as pieces/p0-0-0.stl)")
    parts = rel.replace("\\", "/").split("/")
    if rel.startswith(("/", "\\")) or (len(parts[0]) >= 2 and parts[0][1] == ":") or ".." in parts:
        raise VolpuzzleError(f"{field}: points outside the folder (got {rel!r}, expected a relative path inside "
                             f"{directory}, without '..')")
    parts = [p for p in parts if p not in ("", ".")]
    if not parts:
        raise VolpuzzleError(f"{field}: not a file name inside the folder (got {rel!r}, expected a relative path)")
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    dflags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    path = directory.joinpath(*parts)
    fds = []
    try:
        try:
            fds.append(os.open(directory, dflags & ~getattr(os, "O_NOFOLLOW", 0)))
            for part in parts[:-1]:  # every folder on the way opened relative to the last, never followed
                fds.append(os.open(part, dflags, dir_fd=fds[-1]))
            fd = os.open(parts[-1], flags, dir_fd=fds[-1])
        except FileNotFoundError:
            raise
        except OSError as e:
            if e.errno in (errno.ELOOP, errno.ENOTDIR):
                link = next((p for p in (directory.joinpath(*parts[:i + 1]) for i in range(len(parts)))
                             if p.is_symlink()), None)
                what = (f"{link.relative_to(directory)} is a symbolic link" if link is not None
                        else f"{rel} passes through something that is not a folder")
                raise VolpuzzleError(f"{field}: {what} (got {rel!r}, expected regular files and folders inside "
                                     f"{directory}, no links)") from None
            raise VolpuzzleError(f"{field}: cannot open {rel} ({e.strerror or e})") from None
        fds.append(fd)
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise VolpuzzleError(f"{field}: {rel} is not a regular file (got mode {stat.filemode(st.st_mode)}, "
                                 f"expected a regular file)")
        if st.st_size > max_bytes:
            raise VolpuzzleError(f"{field}: {rel} is too large (got {st.st_size:,} bytes, expected at most "
                                 f"{max_bytes:,})")
        with os.fdopen(os.dup(fd), "rb") as f:
            data = f.read(max_bytes + 1)
    finally:
        for fd in fds:
            os.close(fd)
    return path, data


def _load_mesh(path: Path, data: bytes) -> trimesh.Trimesh:
    """A piece file's bytes -> trimesh; every failure a ModelError naming the file."""
    if path.suffix.lower() == ".3mf":
        import tempfile

        from .io.threemf import read_3mf

        # lib3mf reads files by name: hand it a private copy of the bytes already read, never the path itself
        with tempfile.NamedTemporaryFile(suffix=".3mf") as tmp:
            tmp.write(data)
            tmp.flush()
            try:
                objs = read_3mf(tmp.name)
            except VolpuzzleError as e:  # it names the copy: the user knows the file
                raise ModelError(str(e).replace(tmp.name, str(path))) from None
        if len(objs) != 1:
            raise ModelError(f"{path}: expected one piece, found {len(objs)} objects")
        _, v, f, _ = objs[0]
        return trimesh.Trimesh(v, f, process=True, validate=False)
    from .io.mesh import mesh_from_bytes

    try:
        return mesh_from_bytes(path, data)
    except VolpuzzleError:
        raise
    except Exception as e:  # noqa: BLE001 - a hostile file must give a message, never a crash
        raise ModelError(f"{path}: unreadable piece file: {type(e).__name__}: {e}") from None


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _vec3(x) -> bool:
    return isinstance(x, list) and len(x) == 3 and all(_finite(v) for v in x)


def _report_fields(report, where: str):
    """(pieces [(id, file)], expected volume, volume tolerance, joints) from report.json, every field checked for
    its type; VolpuzzleError naming the field otherwise."""
    def bad(field, what, got, expected):
        return VolpuzzleError(f"{where}: {field}: {what} (got {_short(got)}, expected {expected})")

    if not isinstance(report, dict):
        raise bad("(top level)", "not an object", report, "a JSON object with pieces, checks, joints")
    entries = report.get("pieces")
    if entries is None or entries == []:
        raise VolpuzzleError(f"{where}: lists no pieces")
    if not isinstance(entries, list):
        raise bad("pieces", "not a list", entries, "a list of {id, file, ...} objects")
    pieces, ids, files = [], set(), set()
    for k, e in enumerate(entries):
        if not isinstance(e, dict):
            raise bad(f"pieces[{k}]", "not an object", e, "an object with id and file")
        pid, rel = e.get("id"), e.get("file")
        if not isinstance(pid, str) or not pid:
            raise bad(f"pieces[{k}].id", "not a piece id", pid, "a text such as p0-0-0")
        if not isinstance(rel, str) or not rel:
            raise bad(f"pieces[{k}].file", "not a file name", rel, "a relative path such as pieces/p0-0-0.stl")
        if pid in ids:
            raise bad(f"pieces[{k}].id", "given twice", pid, "each piece once")
        vol = e.get("volume_mm3")
        if vol is not None and not _finite(vol):  # the joint figures add these up
            raise bad(f"pieces[{k}].volume_mm3", "not a volume", vol, "a finite number of mm^3, or nothing")
        key = rel.replace("\\", "/").lstrip("./")
        if key in files:
            raise bad(f"pieces[{k}].file", "the file of another piece too", rel, "one file per piece")
        ids.add(pid)
        files.add(key)
        pieces.append((pid, rel))
    old = report.get("checks", {})
    model = report.get("model", {})
    for name, value in (("checks", old), ("model", model)):
        if value is not None and not isinstance(value, dict):
            raise bad(name, "not an object", value, "a JSON object")
    old, model = old or {}, model or {}
    expected = old.get("expected_volume_mm3")
    field = "checks.expected_volume_mm3"
    if expected is None:
        expected, field = model.get("volume_mm3"), "model.volume_mm3"
    if expected is None:
        raise VolpuzzleError(f"{where}: no expected volume (checks.expected_volume_mm3 or model.volume_mm3)")
    if not _finite(expected) or not expected > 0:
        raise bad(field, "not a positive volume", expected, "a finite number of mm^3 > 0")
    tol = old.get("volume_tolerance", 0.005)
    if not _finite(tol) or not 0 <= tol < 1:
        raise bad("checks.volume_tolerance", "not a fraction", tol, "a number from 0 to 1")
    joints = report.get("joints") or []
    if not isinstance(joints, list):
        raise bad("joints", "not a list", joints, "a list of joint objects")
    for k, j in enumerate(joints):
        f = f"joints[{k}]"
        if not isinstance(j, dict):
            raise bad(f, "not an object", j, "an object with pin_piece, hole_piece, center_mm, direction, ...")
        for key in ("pin_piece", "hole_piece"):
            if not isinstance(j.get(key), str):
                raise bad(f"{f}.{key}", "not a piece id", j.get(key), "a text such as p0-0-0")
        if not _vec3(j.get("center_mm")):
            raise bad(f"{f}.center_mm", "not a point", j.get("center_mm"), "3 finite numbers")
        d = j.get("direction")
        if not _vec3(d) or not 0.5 < math.sqrt(sum(x * x for x in d)) < 2:
            raise bad(f"{f}.direction", "not a unit direction", d, "3 finite numbers of length 1")
        for key, lo in (("radius_mm", 0.0), ("length_mm", 0.0)):
            v = j.get(key)
            if not _finite(v) or not lo < v < 1e4:
                raise bad(f"{f}.{key}", "not a size", v, "a finite number of mm, > 0")
        c = j.get("clearance_mm", 0.0)
        if not _finite(c) or not 0 <= c < j["radius_mm"] * 10:
            raise bad(f"{f}.clearance_mm", "not a clearance", c, "a finite number of mm, >= 0")
        if not isinstance(j.get("style", "pin"), str):
            raise bad(f"{f}.style", "not a joint style", j.get("style"), "pin or dowel")
    _check_report_shapes(report, bad)
    return pieces, float(expected), float(tol), joints


def _check_report_shapes(report, bad):
    """The report fields that the joint-graph and printability checks read beyond _report_fields' own, checked for
    their type, so that an edited report.json gets a line naming the field and not an internal error."""
    def obj(field, value):
        if value is not None and not isinstance(value, dict):
            raise bad(field, "not an object", value, "a JSON object")
        return value or {}

    def texts(field, value):
        if value is not None and not (isinstance(value, list) and all(isinstance(x, str) for x in value)):
            raise bad(field, "not a list of names", value, "a list of texts")

    for k, e in enumerate(report["pieces"]):
        pose = obj(f"pieces[{k}].print", e.get("print"))
        t = pose.get("plate_transform")
        if t is not None and not (isinstance(t, list) and len(t) == 4 and all(
                isinstance(row, list) and len(row) == 4 and all(_finite(x) for x in row) for row in t)):
            raise bad(f"pieces[{k}].print.plate_transform", "not a transform", t, "4 rows of 4 finite numbers")
        if t is not None and not _rigid(np.array(t, dtype=float)):
            raise bad(f"pieces[{k}].print.plate_transform", "not a rotation and a move", t,
                      "a rigid motion: a mirror or a scale would print another shape than the piece")
        obj(f"pieces[{k}].label", e.get("label"))
    spec = obj("spec", report.get("spec"))
    joints = obj("spec.joints", spec.get("joints"))
    texts("spec.joints.allow", joints.get("allow"))
    if not isinstance(joints.get("style", "pin"), str):
        raise bad("spec.joints.style", "not a joint style", joints.get("style"), "pin, dowel or none")
    out = obj("spec.output", spec.get("output"))
    if not _finite(out.get("face_clearance", 0.0)):
        raise bad("spec.output.face_clearance", "not a clearance", out.get("face_clearance"), "a number of mm")
    if not _finite((report.get("checks") or {}).get("face_clearance_mm", 0.0) or 0.0):
        raise bad("checks.face_clearance_mm", "not a clearance", report["checks"]["face_clearance_mm"],
                  "a number of mm")
    for field, contacts in (("contacts", report.get("contacts")),
                            ("mesh.contacts", obj("mesh", report.get("mesh")).get("contacts"))):
        if contacts is None:
            continue
        if not isinstance(contacts, list):
            raise bad(field, "not a list", contacts, "a list of contact objects")
        for k, c in enumerate(contacts):
            obj(f"{field}[{k}]", c)
            if c is None:
                raise bad(f"{field}[{k}]", "not an object", c, "an object with pieces, room, pinned")
            texts(f"{field}[{k}].pieces", c.get("pieces"))
    assembly = obj("assembly", report.get("assembly"))
    texts("assembly.stuck", assembly.get("stuck"))


PLACEMENT_TOL = 1e-4  # report.json writes a transform's entries to 6 decimals


def _rigid(t: np.ndarray) -> bool:
    """Whether the (4, 4) transform t turns and moves without mirroring or scaling (to report.json's rounding)."""
    r = t[:3, :3]
    return (bool(np.allclose(t[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=PLACEMENT_TOL))
            and bool(np.allclose(r.T @ r, np.eye(3), rtol=0.0, atol=PLACEMENT_TOL)) and float(np.linalg.det(r)) > 0)


def _short(value) -> str:
    import reprlib

    r = reprlib.Repr()
    r.maxstring, r.maxother, r.maxlist, r.maxdict = 40, 40, 4, 3
    return r.repr(value)


def _cylinder(center, direction, radius, start, stop):
    """A test cylinder of a pin's room (Manifold), not empty; GeometryError otherwise."""
    cyl = cylinder(center, direction, radius, start, stop, "joint check")
    if cyl.is_empty():
        raise GeometryError(f"joint check: cannot build a test cylinder of radius {radius:g} mm (it is empty)")
    return cyl


def check_joints(meshes: dict, joints: Sequence[dict], share: float = 0.02, workers=None) -> list:
    """Every pin inside its hole with its clearance, on the real meshes -> list of failure sentences.

    meshes: {piece id: closed trimesh in mm}; joints: report.json joint entries. A pin's core (90% of its radius and
    length) must lie inside the pin piece, and the pin grown by half its clearance must not touch the hole piece
    (both within `share` of the tested volume, which absorbs the polygonal circles). A test whose cylinders no
    triangle comes near is settled by one ray (_left_to_measure); the engine measures the rest. workers: a
    volpuzzle.workers.Workers that tests some of the pieces (the same sentences, in joint order)."""
    from . import precompile
    from .workers import MeshRef, in_tasks, map_pieces

    tested = [(k, j) for k, j in enumerate(joints) if j.get("pin_piece") in meshes and j.get("hole_piece") in meshes]
    used = {j[key] for _, j in tested for key in ("pin_piece", "hole_piece")}
    broken = {pid for pid in used if solid_problem(meshes[pid], pid)}  # check_pieces says why
    tests = {}  # piece id -> [(joint index, test of that joint, kind, cylinders)], in joint order
    for k, j in tested:
        if j["pin_piece"] not in broken and j["hole_piece"] not in broken:
            for order, (pid, kind, cylinders) in enumerate(_joint_tests(j)):
                tests.setdefault(pid, []).append((k, order, kind, cylinders))
    items = list(tests.items())
    chunks = in_tasks(items, _PIECES_PER_TASK)
    shortcut = len(items) >= _SHORTCUT_MIN_PIECES or precompile.usable("volpuzzle._check_kernels", "cylinder_side")
    found = map_pieces(workers, _joint_measures, chunks,
                       shared=({pid: MeshRef(meshes[pid]) for pid in tests}, share, shortcut), what="check")
    failed = sorted(f for chunk in found for f in chunk)
    return [_joint_sentence(joints[k], order, volume) for k, order, volume in failed]


_PIECES_PER_TASK = 8  # pieces per worker task at least (workers.in_tasks)
# pieces from which _left_to_measure pays for starting numba (~0.5 s) and compiling its kernel on a new machine
# (~1.7 s), at ~3 ms of Booleans saved a piece
_SHORTCUT_MIN_PIECES = 256
_CLEAR_MARGIN = 1e-4  # mm a surface keeps from a test cylinder that passes without the engine (_left_to_measure)


def _joint_tests(j):
    """The tests of one joint entry -> [(piece id, kind, cylinders (_cylinder's arguments) whose union is tested)]:
    kind "inside" measures the cylinders' volume outside the piece, "clear" their volume inside it."""
    pin, hole = j["pin_piece"], j["hole_piece"]
    c, d = j["center_mm"], j["direction"]
    r, length, cl = float(j["radius_mm"]), float(j["length_mm"]), float(j.get("clearance_mm", 0.0))
    if j.get("style", "pin") == "dowel":
        room = [(c, d, r + 0.5 * cl, -0.9 * length, 0.9 * length)]
        return [(pin, "clear", room), (hole, "clear", room)]
    room = [(c, d, r + 0.5 * cl, 0.05 * length, length)]
    if j.get("shape") == "snap":
        # the snap hole necks with its pin to 0.9 r past 70% of the length (joint._snap_profile): a plain room
        # of radius r there would find the neck's wall in the hole piece and fail every snap joint
        room = [(c, d, r + 0.5 * cl, 0.05 * length, 0.7 * length),
                (c, d, 0.9 * r + 0.5 * cl, 0.05 * length, 0.9 * length)]
    return [(pin, "inside", [(c, d, 0.9 * r, 0.1 * length, 0.9 * length)]), (hole, "clear", room)]


def _joint_sentence(j, order, volume):
    """The failure sentence of test `order` of joint entry j (_joint_tests), which measured `volume` mm^3."""
    pin, hole = j["pin_piece"], j["hole_piece"]
    r, cl = float(j["radius_mm"]), float(j.get("clearance_mm", 0.0))
    name = f"joint {pin} -> {hole}"
    if j.get("style", "pin") == "dowel":
        return (f"{name}: the dowel hole in {(pin, hole)[order]} is blocked ({volume:.3g} mm^3 of material "
                f"within radius {r + 0.5 * cl:.2f} mm)")
    if order == 0:
        return f"{name}: the pin of {pin} is missing ({volume:.3g} mm^3 of its core is not there)"
    return (f"{name}: the pin does not fit its hole in {hole} with clearance {cl:g} mm ({volume:.3g} mm^3 of {hole} "
            f"within radius {r + 0.5 * cl:.2f} mm of the pin axis)")


def _joint_measures(shared, items):
    """[(joint index, test, volume mm^3)] of the tests that fail, for items [(piece id, its tests of
    check_joints)], wherever they are measured: shared ({piece id: MeshRef}, share).

    A piece's tests of one kind are first measured together, on the union of their cylinders: a part of the union
    holds at most what the whole does, so when the whole is within the smallest allowance every test passes, in one
    Boolean where a piece with 3 pins and 3 holes would take 6 (the piece, not the small cylinder, is most of a
    Boolean's cost). Otherwise each test is measured alone, as its sentence gives its own volume."""
    from manifold3d import Manifold, OpType

    refs, share, shortcut = shared
    out = []
    for pid, tests in items:
        if shortcut:
            tests = _left_to_measure(refs[pid].mesh, tests)
            if not tests:
                continue  # nor does the piece's solid need building (~2 ms)
        solid = piece_solid(refs[pid].mesh, pid)
        for kind in ("inside", "clear"):
            group = [(k, order, cyls) for k, order, test_kind, cyls in tests if test_kind == kind]
            if not group:
                continue
            shapes = [(k, order, _test_shape(cyls)) for k, order, cyls in group]
            if len(shapes) > 1:
                whole = check_status(Manifold.batch_boolean([s for *_, s in shapes], OpType.Add), "joint check",
                                     f"the union of piece {pid}'s test cylinders")
                if _measured(kind, whole, solid) <= min(share * s.volume() for *_, s in shapes):
                    continue
            for k, order, shape in shapes:
                volume = _measured(kind, shape, solid)
                if volume > share * shape.volume():
                    out.append((k, order, volume))
    return out


def _left_to_measure(mesh, tests):
    """The tests of _joint_measures that need the engine: all but those that pass alone, with no triangle of the piece
    near their cylinders (one connected shape), which then lie wholly inside the piece or wholly outside it
    (_check_kernels.cylinder_side): an "inside" test inside and a "clear" test outside measure 0 mm^3. The engine
    measures the rest, and so every volume a sentence reports."""
    from ._check_kernels import cylinder_side

    vertices, faces = kernel_arrays(mesh)
    # far above the engine's own tolerance (1e-12 of the coordinates) and any rounding
    margin = _CLEAR_MARGIN + 1e-9 * float(np.abs(vertices).max(initial=0.0))
    left = []
    for test in tests:
        kind, cylinders = test[2], test[3]
        sides = set()
        for center, direction, radius, start, stop in cylinders:
            d = np.asarray(direction, dtype=float)
            e1, e2, n = frame_from_direction(d / np.linalg.norm(d))
            sides.add(cylinder_side(vertices, faces, np.asarray(center, dtype=float), e1, e2, n, float(radius),
                                    float(start), float(stop), margin))
        if sides != ({1} if kind == "inside" else {-1}):
            left.append(test)
    return left


def _test_shape(cylinders):
    """The union of a test's cylinders (_cylinder's arguments) -> Manifold."""
    shape = _cylinder(*cylinders[0])
    for more in cylinders[1:]:
        shape = boolean(shape, _cylinder(*more), "union", "joint check")
    return shape


def _measured(kind, shape, solid):
    """mm^3 of shape outside solid (kind "inside") or inside it ("clear")."""
    op = "difference" if kind == "inside" else "intersection"
    return float(boolean(shape, solid, op, "joint check").volume())


def check_joint_graph(report: dict):
    """The puzzle holds together, from report.json alone -> (failure sentences, figures of
    volpuzzle.joint.report_figures). Every listed piece must carry a joint and the joints must join them into one
    part, unless the spec's joints.style is none or its joints.allow has 'loose'; the recorded assembly must not be
    welded unless joints.allow has 'welded'."""
    from .joint import graph_problem

    joints_spec = ((report.get("spec") or {}).get("joints") or {})
    style = joints_spec.get("style", "pin")
    allow = tuple(joints_spec.get("allow") or ())
    pieces = [p.get("id") for p in report.get("pieces") or []]
    edges = [(j.get("pin_piece"), j.get("hole_piece")) for j in report.get("joints") or []]
    failures = []
    randomized = ((report.get("randomize") or {}).get("amplitude") or 0) != 0
    problem = graph_problem(pieces, edges, report.get("contacts") or (), style, allow, randomized=randomized)
    if problem:
        failures.append(problem)
    assembly = report.get("assembly") or {}
    if assembly.get("welded") and "welded" not in allow:
        failures.append(f"the puzzle is welded: {', '.join(assembly.get('stuck') or [])} cannot be taken out "
                        f"(joints.allow has no 'welded')")
    from .joint import report_figures

    return failures, report_figures(report)


def check_directory(directory, raise_on_failure: bool = True) -> dict:
    """`volpuzzle check DIR`: re-run the checks on a built puzzle from its files alone.

    Reads report.json for the piece list and the expected volume; every piece file must be a regular file inside
    DIR (no '..', no absolute path, no symlink on the way) and load. Returns the checks dict plus "missing_files"
    and a one-line "summary"; raises VolpuzzleError when the folder is no build or report.json is malformed or
    points outside the folder, and GeometryError listing every failure when a check fails (unless
    raise_on_failure is False).
    """
    directory = Path(directory)
    report_path = directory / "report.json"
    try:
        is_dir = directory.is_dir()
        has_report = report_path.exists() or report_path.is_symlink()
    except (OSError, ValueError) as e:
        raise VolpuzzleError(f"{directory!s}: cannot open the folder ({getattr(e, 'strerror', None) or e})") from None
    if not is_dir:
        raise VolpuzzleError(f"{directory}: not a folder (expected a volpuzzle output folder)")
    if not has_report:
        raise VolpuzzleError(f"{directory}: not a volpuzzle output folder (no report.json)")
    _, raw = _inside_file(directory, "report.json", str(report_path), _REPORT_MAX_BYTES)
    try:
        report = json.loads(raw.decode("utf-8"), parse_constant=_no_constant, parse_int=_small_int,
                            parse_float=_finite_float)
    except RecursionError:
        raise VolpuzzleError(f"{report_path}: unreadable report: nested too deeply") from None
    except (ValueError, UnicodeDecodeError) as e:
        where = _constant_at(raw)
        if where is not None:  # a hand edit: say which field holds it
            raise VolpuzzleError(f"{report_path}: {where[0]}: {where[1]} is not a JSON number (got {where[1]}, "
                                 f"expected a finite number)") from None
        raise VolpuzzleError(f"{report_path}: unreadable report: {str(e)[:200]}") from None
    entries, expected, tolerance, joints = _report_fields(report, str(report_path))
    pieces, missing, failures = [], [], []
    for k, (pid, rel) in enumerate(entries):
        try:
            path, data = _inside_file(directory, rel, f"{report_path}: pieces[{k}].file", _PIECE_MAX_BYTES)
        except FileNotFoundError:
            missing.append(rel)
            continue
        try:
            pieces.append((pid, _load_mesh(path, data)))
        except VolpuzzleError as err:
            failures.append(str(err))
    by_id = dict(pieces)
    gaps = report_face_gaps(report, by_id)
    checks = check_pieces(pieces, expected, volume_tolerance=tolerance, apart=pairs_apart(gaps, by_id))
    checks["missing_files"] = missing
    joint_failures = check_joints(by_id, joints)
    checks["joints_checked"] = len(joints)
    graph_failures, checks["joint_graph"] = check_joint_graph(report)
    checks["printability"] = check_printability(report, by_id, gaps=gaps)
    checks["printability"]["warnings"] += _unlisted_piece_files(directory, entries)
    checks["failures"] = ([f"missing piece file {m}" for m in missing] + failures + checks["failures"]
                          + joint_failures + graph_failures + checks["printability"]["failures"]
                          + _report_volume_problems(report, by_id) + _report_piece_problems(report, by_id)
                          + _other_file_problems(directory, report, str(report_path)))
    checks["passed"] = not checks["failures"]
    checks["summary"] = (f"{len(pieces)} of {len(entries)} pieces read, "
                         f"{'all' if checks['all_closed'] else 'not all'} closed, "
                         f"volume error {checks['volume_error']:+.3%}, "
                         f"largest overlap {checks['max_overlap_mm3']:.3g} mm^3")
    if raise_on_failure:
        assert_passed(checks, str(directory))
    return checks


def _unlisted_piece_files(directory: Path, entries) -> list:
    """A file in a piece folder that report.json does not list (copied in, or left from something else) would be
    printed with the puzzle without being part of it -> one warning per folder, naming the files."""
    listed = {Path(rel.replace("\\", "/")).as_posix().lstrip("./") for _, rel in entries}
    warnings = []
    for folder in sorted({Path(rel.replace("\\", "/")).parent.as_posix() for rel in listed} - {"."}):
        path = directory / folder
        if path.is_symlink() or not path.is_dir():
            continue
        extra = sorted(f"{folder}/{f.name}" for f in path.iterdir()
                       if f.is_file() and f"{folder}/{f.name}" not in listed)
        if extra:
            shown = ", ".join(extra[:3]) + (f" and {len(extra) - 3} more" if len(extra) > 3 else "")
            warnings.append(f"{shown}: in the folder but not a piece of report.json (expected only its "
                            f"{len(listed)} pieces there; remove it before printing the folder)")
    return warnings


REPORT_VOLUME_RTOL = 1e-3  # the build measures the very mesh it writes: a 3MF's or STL's float rounding is ~1e-7


def _report_volume_problems(report, meshes) -> list:
    """A piece whose file holds another volume than report.json (and so report.md) gives it: the report no longer
    describes the files, though their sum may still match the model."""
    problems = []
    for k, e in enumerate(report["pieces"]):
        claimed, mesh = e.get("volume_mm3"), meshes.get(e["id"])
        if claimed is None or mesh is None:
            continue
        held = abs(float(mesh.volume))
        if abs(held - claimed) > REPORT_VOLUME_RTOL * max(abs(claimed), held):
            problems.append(f"pieces[{k}].volume_mm3: report.json gives {e['id']} {claimed:.6g} mm^3, its file "
                            f"holds {held:.6g} mm^3 (expected within {REPORT_VOLUME_RTOL:.1%})")
    return problems


REPORT_BOUNDS_MM = 1e-3  # a piece's box in report.json against its file's: the files' float32 rounding is ~1e-5 mm


def _report_piece_problems(report, meshes) -> list:
    """Where report.json (and so report.md) describes a piece otherwise than its file holds it (triangles, bbox_mm),
    or places it on no plate, on two, or on one that is not there."""
    problems = []
    plates = report.get("plates")
    plates = plates if isinstance(plates, list) else []
    on = {}  # piece id -> the plates (1-based) that list it
    for n, plate in enumerate(plates, start=1):
        listed = plate.get("pieces") if isinstance(plate, dict) else None
        if not (isinstance(listed, list) and all(isinstance(x, str) for x in listed)):
            problems.append(f"plates[{n - 1}].pieces: not a list of piece ids (got {_short(listed)})")
            continue
        for pid in listed:
            on.setdefault(pid, []).append(n)
    dowels = report.get("dowels") if isinstance(report.get("dowels"), list) else []
    dowels = [d.get("name") for d in dowels if isinstance(d, dict) and isinstance(d.get("name"), str)]
    ids = {e["id"] for e in report["pieces"]} | set(dowels)
    for pid in sorted(set(on) - ids):
        problems.append(f"plates: {pid} is on plate {on[pid][0]} but is no piece nor dowel of report.json")
    for name in dowels if plates else ():  # a dowel is printed as a piece is
        if len(on.get(name, [])) != 1:
            problems.append(f"plates: dowel {name} is on {len(on.get(name, []))} plates (expected one)")
    for k, e in enumerate(report["pieces"]):
        pid, mesh = e["id"], meshes.get(e["id"])
        where = f"pieces[{k}]"
        if mesh is not None and "triangles" in e and e["triangles"] != len(mesh.faces):
            problems.append(f"{where}.triangles: report.json gives {pid} {_short(e['triangles'])}, its file holds "
                            f"{len(mesh.faces)}")
        box = e.get("bbox_mm")
        if mesh is not None and box is not None:
            got = np.asarray(mesh.bounds, dtype=float)
            if not (isinstance(box, list) and len(box) == 2 and all(_vec3(c) for c in box)
                    and np.allclose(np.array(box, dtype=float), got, rtol=0.0, atol=REPORT_BOUNDS_MM)):
                problems.append(f"{where}.bbox_mm: report.json gives {pid} {_short(box)}, its file spans "
                                f"{np.round(got, 4).tolist()} (expected within {REPORT_BOUNDS_MM:g} mm)")
        plate = e.get("plate")
        if plate is not None or plates:
            if len(on.get(pid, [])) > 1:
                problems.append(f"plates: {pid} is on plates {', '.join(map(str, on[pid]))} (expected one)")
            elif not on.get(pid):
                problems.append(f"plates: {pid} is on no plate (expected on the plate {where}.plate gives, of "
                                f"{len(plates)})")
            elif plate is not None and plate != on[pid][0]:
                problems.append(f"{where}.plate: report.json gives {pid} plate {_short(plate)}, plates lists it "
                                f"on plate {on[pid][0]}")
    return problems


_FILE_MAX_BYTES = 8 << 30  # puzzle.3mf of a 10k-piece puzzle, well below


def _other_file_problems(directory: Path, report, where: str) -> list:
    """The files besides the pieces that the folder holds for printing (SPEC section 5): puzzle.3mf, each plate
    and dowel report.json lists, the preview it names. Each must be a regular file inside the folder; a 3MF one a
    ZIP whose parts read back whole, holding a 3D model; a dowel a closed solid, as a piece."""
    import io
    import zipfile

    files = [("puzzle.3mf", "puzzle.3mf")]
    for field in ("plates", "dowels"):
        listed = report.get(field)
        if listed is None:
            continue
        if not isinstance(listed, list):
            return [f"{field}: not a list (got {_short(listed)}, expected a list of {{file, ...}} objects)"]
        for k, entry in enumerate(listed):
            rel = entry.get("file") if isinstance(entry, dict) else None
            files.append((f"{field}[{k}].file", rel))
    if report.get("preview") is not None:
        files.append(("preview", report.get("preview")))
    problems = []
    for field, rel in files:
        try:
            path, data = _inside_file(directory, rel, f"{where}: {field}", _FILE_MAX_BYTES)
        except FileNotFoundError:
            problems.append(f"missing file {rel} ({field})")
            continue
        except VolpuzzleError as e:
            problems.append(str(e))
            continue
        if not data:
            problems.append(f"{rel}: empty file ({field})")
        elif path.suffix.lower() == ".3mf":
            try:
                with zipfile.ZipFile(io.BytesIO(data)) as z:
                    broken = z.testzip()
                    model = any(n.lower().endswith(".model") for n in z.namelist())
            except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as e:
                problems.append(f"{rel}: not a readable 3MF file ({field}: {e})")
                continue
            if broken is not None or not model:
                problems.append(f"{rel}: not a readable 3MF file ({field}: "
                                f"{f'part {broken} is damaged' if broken else 'it holds no 3D model'})")
        if field.startswith("dowels") and data:
            try:
                problem = closed_problem(_load_mesh(path, data))
            except VolpuzzleError as e:
                problem = str(e)
            if problem is not None:
                problems.append(f"{rel}: the dowel is not one closed solid ({problem})")
    return problems


def _no_constant(name):
    raise ValueError(f"{name} is not JSON")


class _Constant(str):
    """NaN, Infinity or -Infinity where report.json holds one (_constant_at)."""


def _constant_at(raw: bytes):
    """(field, token) of the first NaN or Infinity in report.json's bytes, e.g. ('pieces[2].volume_mm3', 'NaN'), or
    None when there is none or the text is otherwise unreadable."""
    try:
        tree = json.loads(raw.decode("utf-8"), parse_constant=_Constant)
    except (ValueError, UnicodeDecodeError, RecursionError):
        return None
    todo = [("", tree)]
    while todo:
        field, node = todo.pop(0)
        if isinstance(node, _Constant):
            return field or "(top level)", str(node)
        if isinstance(node, dict):
            todo[:0] = [(f"{field}.{k}" if field else str(k), v) for k, v in node.items()]
        elif isinstance(node, list):
            todo[:0] = [(f"{field}[{k}]", v) for k, v in enumerate(node)]
    return None


def _finite_float(text):
    x = float(text)
    if not math.isfinite(x):
        raise ValueError(f"the number {text[:12]}... ({len(text)} characters) overflows double precision")
    return x


def _small_int(text):
    if len(text.lstrip("-")) > 30:
        raise ValueError(f"a number of {len(text.lstrip('-'))} digits ({text[:12]}...), expected at most 30")
    return int(text)


# ---------------------------------------------------------------------------------------------------------------------
# printability: what a maker's printer needs, checked from the files as well as during the build

PIN_MIN_RADIUS_MM = 1.0  # a thinner pin snaps or prints as a blob with a 0.4 mm nozzle
PIN_MIN_LENGTH_MM = 3.0  # a shorter one does not hold
BED_MIN_MM2 = 10.0  # less than this on the bed and the first layer has nothing to hold


def pin_fit(style, radius, length, clearance, axial_clearance, face_clearance):
    """Pin size and fit for people -> {"pin_diameter_mm", "pin_length_mm", "clearance_mm", "axial_clearance_mm",
    "face_clearance_mm", "style", "warnings": [sentences]}; a warning when the pin is below the printable minimum."""
    warnings = []
    if style in ("pin", "dowel"):
        if radius < PIN_MIN_RADIUS_MM:
            warnings.append(f"joints.radius: pins of radius {radius:g} mm are below the printable minimum "
                            f"(expected at least {PIN_MIN_RADIUS_MM:g} mm)")
        if length < PIN_MIN_LENGTH_MM:
            warnings.append(f"joints.length: pins {length:g} mm long are below the printable minimum "
                            f"(expected at least {PIN_MIN_LENGTH_MM:g} mm)")
    return {"style": style, "pin_diameter_mm": 2 * float(radius), "pin_length_mm": float(length),
            "clearance_mm": float(clearance), "axial_clearance_mm": float(axial_clearance),
            "face_clearance_mm": float(face_clearance), "warnings": warnings}


def fit_line(fit):
    """One line saying the pin size and fit."""
    if fit.get("style") not in ("pin", "dowel"):
        return f"no pins; face clearance {fit['face_clearance_mm']:g} mm"
    line = (f"{fit['style']}s {fit['pin_diameter_mm']:g} mm across, {fit['pin_length_mm']:g} mm long, clearance "
            f"{fit['clearance_mm']:g} mm radial and {fit['axial_clearance_mm']:g} mm at the tip; face clearance "
            f"{fit['face_clearance_mm']:g} mm")
    s = fit.get("shrunk")
    if s:
        asked = " and ".join(f"{k} {s[f'asked_{k}_mm']:g} mm" for k in ("radius", "length")
                             if s.get(f"asked_{k}_mm") is not None)
        line += f"; {s['joints']} of {s['of']} shrunk to fit their faces (joints asked {asked})"
    return line


def piece_bed_contact(mesh, transform):
    """layout.bed_contact of a piece mesh placed by transform (4, 4); remembered per mesh and transform, since the
    build's report entry and its printability check measure the very same placement. GeometryError for a mesh that
    is not a closed solid (closed_problem, which check_pieces has found already): its section would be a number
    without meaning (an open box's is most of its face), where the engine's slice refused such a mesh."""
    from .layout import bed_contact

    transform = np.asarray(transform, float)

    def measure():
        problem = closed_problem(mesh) if len(mesh.faces) else None  # none: bed_contact says what it says of that
        if problem is not None:
            raise GeometryError(f"piece on the bed: the mesh is not a closed solid: {problem}")
        return bed_contact(mesh.vertices, mesh.faces, transform)

    return _memo(mesh, ("bed_contact", transform.tobytes()), measure)


def bed_contact_problem(under) -> str:
    """The sentence for pieces (ids) that rest on less than BED_MIN_MM2: the build and `check` say the same."""
    return f"pieces {', '.join(under)} rest on less than {BED_MIN_MM2:g} mm^2 of the bed"


def check_printability(report: dict, meshes: dict, workers=None, gaps=None) -> dict:
    """Printability from the files: bed contact of each piece in its print orientation (report.json pieces[].print
    .plate_transform applied to the piece file), the gap between neighbouring pieces (at least the face clearance,
    less what the joints' own clearances allow), pin sizes against the printable minimum, a label per piece.
    meshes: {piece id: closed trimesh in mm}. -> {"bed_contact_mm2": {id: mm^2}, "min_bed_contact_mm2",
    "pieces_under_bed_minimum", "min_face_gap_mm", "face_gap_pair", "unlabelled", "pins_up", "pins",
    "failures": [sentences], "warnings": [sentences]}. workers: a volpuzzle.workers.Workers that measures some of
    the face gaps (the same figures); gaps: report_face_gaps(report, meshes), when already measured."""
    failures, warnings = [], []
    entries = {e.get("id"): e for e in report.get("pieces") or []}
    contact, under = {}, []
    for pid, mesh in meshes.items():
        pose = (entries.get(pid) or {}).get("print") or {}
        transform = pose.get("plate_transform")
        if transform is None:
            warnings.append(f"piece {pid}: report.json gives no print orientation; its bed contact was not checked")
            continue
        try:
            contact[pid] = round(piece_bed_contact(mesh, transform), 2)
        except GeometryError as e:
            failures.append(f"piece {pid}: bed contact not measured ({e})")
            continue
        if contact[pid] < BED_MIN_MM2:
            under.append(pid)
    if under:
        failures.append(bed_contact_problem(under))
    unlabelled = [pid for pid in meshes if not ((entries.get(pid) or {}).get("label") or {}).get("text")]
    labels_on = (report.get("spec") or {}).get("output", {}).get("labels", True)
    if labels_on and unlabelled:
        warnings.append(f"pieces {', '.join(unlabelled)} carry no label")
    face_clearance = _report_face_clearance(report)
    joints = report.get("joints") or []
    thin = [j for j in joints if pin_fit(j.get("style", "pin"), float(j.get("radius_mm", 0)),
                                         float(j.get("length_mm", 0)), 0, 0, 0)["warnings"]]
    if thin:
        # a warning, as in the build: the printable minimum pin is the joint stage's to enforce
        r = min(float(j.get("radius_mm", 0)) for j in thin)
        length = min(float(j.get("length_mm", 0)) for j in thin)
        warnings.append(f"{len(thin)} of {len(joints)} joints (first {thin[0].get('pin_piece')} -> "
                        f"{thin[0].get('hole_piece')}) have pins below the printable minimum (radius down to {r:g} "
                        f"mm, length down to {length:g} mm; expected at least {PIN_MIN_RADIUS_MM:g} and "
                        f"{PIN_MIN_LENGTH_MM:g} mm)")
    if gaps is None:
        gaps = report_face_gaps(report, meshes, workers)
    closed = [g for g in gaps if g[2] < 0.7 * face_clearance]
    if closed:
        g = min(closed, key=lambda x: x[2])
        failures.append(f"pieces {g[0]} and {g[1]} face each other {g[2]:.3f} mm apart (median over their facing "
                        f"vertices), expected the face clearance {face_clearance:g} mm")
    least = least_face_gap(face_clearance, joints, (report.get("checks") or {}).get("tessellation_tolerance_mm"))
    tight = [g for g in gaps if g[3] < least]
    if tight:
        g = min(tight, key=lambda x: x[3])
        warnings.append(f"pieces {g[0]} and {g[1]} come within {g[3]:.3f} mm of each other at one spot (expected at "
                        f"least {least:.3f} mm: the face clearance {face_clearance:g} mm less the tessellation's)")
    gap = min((g[3] for g in gaps), default=None)
    median = min((g[2] for g in gaps), default=None)
    pair = list(min(gaps, key=lambda x: x[3])[:2]) if gaps else []
    pins = sum(((e.get("print") or {}).get("pins") or 0) for e in entries.values())
    pins_up = sum(((e.get("print") or {}).get("pins_up") or 0) for e in entries.values())
    return {"bed_contact_mm2": contact, "min_bed_contact_mm2": min(contact.values()) if contact else None,
            "pieces_under_bed_minimum": under, "min_face_gap_mm": None if gap is None else round(gap, 4),
            "face_gap_pair": pair,
            "median_face_gap_mm": None if median is None else round(median, 4),
            "unlabelled": unlabelled, "pins": pins, "pins_up": pins_up,
            "failures": failures, "warnings": warnings}


def least_face_gap(face_clearance, joints=(), tolerance=None):
    """mm two neighbours may come to at their closest: the face clearance (or a pin's radial clearance in its hole,
    when smaller), less what the tessellation leaves. Both sides of a cut face are the same triangles moved apart by
    the clearance at every vertex; between vertices, where the triangles of a curved face tilt against each other, the
    gap is a little less, within the tessellation tolerance, and at most a quarter of the clearance is allowed for
    that (0.04 mm at the default 0.15: a fifth of a 0.2 mm layer)."""
    radial = [float(j["clearance_mm"]) for j in joints if isinstance(j.get("clearance_mm"), (int, float))]
    clearance = min([face_clearance] + radial)
    allow = 0.25 * clearance if tolerance is None else min(float(tolerance), 0.25 * clearance)
    return clearance - allow


def _report_face_clearance(report):
    """mm of face clearance the build applied by report.json (none with joints.space: domain), else the spec's."""
    spec_out = (report.get("spec") or {}).get("output") or {}
    return float((report.get("checks") or {}).get("face_clearance_mm", spec_out.get("face_clearance", 0.0)) or 0.0)


def report_face_gaps(report: dict, meshes: dict, workers=None) -> list:
    """The face gaps check_printability judges, for the face clearance and contacts report.json gives ->
    neighbour_gaps."""
    return neighbour_gaps(meshes, _report_face_clearance(report), report.get("contacts"), workers)


def neighbour_gaps(meshes: dict, face_clearance: float, contacts=None, workers=None) -> list:
    """[(id, id, median gap, smallest gap) mm] of the neighbours that share a cut face (by contacts, report.json's
    records; any neighbours when None), none without a face clearance (see _face_gaps). meshes: {id: trimesh}."""
    if not face_clearance > 0:
        return []
    return _face_gaps(meshes, face_clearance, _shared_faces(contacts), workers)


def pairs_apart(gaps, meshes: dict) -> dict:
    """{frozenset of two ids: mm their surfaces stand apart at least} of the pairs neighbour_gaps proved disjoint, so
    that the overlap check needs no Boolean for them (nor the assembly replay over their first gap of travel): the
    engine found their surfaces apart (a gap above 0), and neither box holds the other. Two connected solids whose
    surfaces never meet either lie apart or one lies inside the other, and then so does its box. Only the gaps
    before the first touching pair are the engine's (_face_gaps); none after it counts."""
    out = {}
    for a, b, _median, smallest in gaps:
        if not smallest > 0.0:  # touching (or not measured: NaN): the closest vertices stand for the rest
            break
        if not boxes_nested(meshes[a].bounds, meshes[b].bounds):
            out[frozenset((a, b))] = float(smallest)
    return out


def _shared_faces(contacts):
    """{frozenset of two piece ids} that share a cut face by contacts (report.json's records), or None when there are
    none."""
    if not isinstance(contacts, list) or not contacts:
        return None
    pairs = set()
    for c in contacts:
        ids = c.get("pieces") if isinstance(c, dict) else None
        if isinstance(ids, list) and len(ids) == 2 and all(isinstance(x, str) for x in ids):
            pairs.add(frozenset(ids))
    return pairs


def _face_gaps(meshes, face_clearance, shared=None, workers=None):
    """Neighbours (pieces whose boxes come within 3 face clearances and, given `shared`, that share a cut face:
    pieces meeting only at a pole or along an edge have no faces to hold apart) -> [(id, id, median gap, smallest
    gap) mm].
    The median is over the first piece's vertices that have a vertex of the other within 3 clearances, each to the
    nearest such vertex: both sides of a cut face share one triangulation, each set back by half the clearance, so
    matching vertices sit one clearance apart, and 0 where the faces close. The smallest gap is the engine's, over
    the whole surfaces, up to the first pair that touches (0): after it, the closest vertices (an upper bound), since
    what is used of the smallest gaps is their least and the first pair with it, which no later pair can change.
    From _SHORTCUT_MIN_PIECES pieces on, _check_kernels.surface_gap measures the smallest gaps instead of the
    engine: ~2x faster, and exact where the engine's own can be off by ~1e-8 of the coordinates (a pair of nearly
    parallel edges). Neighbours' gaps differ by less than that (2816 of them within 1e-5 mm at 1024 pieces), so the
    one measure is used for every pair of a puzzle, and which is used depends on the pieces alone: `volpuzzle check`
    of the folder finds the same least gap and pair.
    workers: a volpuzzle.workers.Workers that measures some of the pairs (the same figures, in the same order)."""
    from .workers import MeshRef, in_tasks, map_pieces

    ids = sorted(meshes)
    reach = 3.0 * face_clearance
    bounds = np.array([meshes[i].bounds for i in ids]) if ids else np.zeros((0, 2, 3))
    pairs = []
    for i in range(len(ids)):
        # the boxes of every later piece at once: a Python test per pair is most of the check at 1024 pieces
        lo = np.maximum(bounds[i, 0], bounds[i + 1:, 0]) - reach
        hi = np.minimum(bounds[i, 1], bounds[i + 1:, 1]) + reach
        near = i + 1 + np.flatnonzero(~np.any(hi < lo, axis=1))
        pairs.extend((ids[i], ids[k]) for k in near.tolist()
                     if shared is None or frozenset((ids[i], ids[k])) in shared)
    # in pair order (by piece id, so that a chunk's pieces are mostly the same few): each chunk's pieces travel once
    chunks = in_tasks(pairs, _GAP_PAIRS_PER_TASK)
    used = {pid for pair in pairs for pid in pair}
    kernel = len(meshes) >= _SHORTCUT_MIN_PIECES
    found = map_pieces(workers, _gaps_of, chunks,
                       shared=({pid: MeshRef(meshes[pid]) for pid in used}, reach, kernel), what="check")
    out = []
    touching = False
    for (a, b), gap in zip(pairs, [g for chunk in found for g in chunk], strict=True):
        if gap is None:
            continue
        median, measured, closest = gap
        # a chunk measured up to its own first touching pair; the serial rule is the global one
        smallest = closest if touching else measured
        touching = touching or smallest == 0.0
        out.append((a, b, median, smallest))
    return out


_GAP_PAIRS_PER_TASK = 8  # face-gap pairs per worker task at least (workers.in_tasks): ~150 ms of engine gaps
_GAP_SEARCH_MARGIN = 1e-6  # mm the engine searches past the closest vertices: well above their rounding
_GAP_TOUCH = 1e-9  # mm within which surface_gap calls two surfaces touching (0): the engine's rounding is larger


def _gaps_of(shared, pairs):
    """[(median gap, smallest gap, closest vertices) mm, or None for pieces that share no face] of pairs (id, id) of
    _face_gaps, wherever they are measured: shared ({id: MeshRef}, reach mm, whether surface_gap measures the
    smallest gaps, else the engine). After a pair that touches, the smallest gap is not asked again (~10 ms a pair
    with the engine): the closest vertices stand for it, as _face_gaps uses them."""
    from scipy.spatial import cKDTree

    refs, reach, kernel = shared
    trees, arrays = {}, {}  # each piece's tree and arrays are made once, not once per neighbour
    out = []
    touching = False
    for a, b in pairs:
        if b not in trees:
            trees[b] = cKDTree(np.asarray(refs[b].mesh.vertices))
        dist, _ = trees[b].query(np.asarray(refs[a].mesh.vertices), distance_upper_bound=reach)
        dist = dist[np.isfinite(dist)]
        if len(dist) < 8:
            out.append(None)  # the pieces do not share a face
            continue
        closest = float(dist.min())
        # the surfaces come no further apart than their closest vertices, so searching that far (a hair more, for
        # rounding) finds the same least gap as searching the whole reach, in ~20% less time
        search = min(reach, closest + _GAP_SEARCH_MARGIN)
        if touching:
            smallest = closest
        elif kernel:
            smallest = _kernel_gap(refs, arrays, a, b, search)
        else:
            sa, sb = piece_solid(refs[a].mesh, a), piece_solid(refs[b].mesh, b)
            smallest = (float(sa.min_gap(sb, search)) if not (isinstance(sa, str) or isinstance(sb, str))
                        else float("nan"))
        touching = touching or smallest == 0.0
        out.append((float(np.median(dist)), smallest, closest))
    return out


def _kernel_gap(refs, arrays, a, b, search):
    """surface_gap of two pieces of _gaps_of (their arrays kept in `arrays`)."""
    from ._check_kernels import surface_gap

    for pid in (a, b):
        if pid not in arrays:
            arrays[pid] = kernel_arrays(refs[pid].mesh)
    return float(surface_gap(*arrays[a], *arrays[b], np.zeros(3), float(search), _GAP_TOUCH))

