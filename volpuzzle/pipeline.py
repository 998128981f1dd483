"""Runs the stages in order: spec -> model -> tile -> joint -> randomize -> verify -> compose -> check -> export."""

import math
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .errors import GeometryError, SpecError
from .grid import AXES


class Progress:
    """Stage and piece progress on a terminal; silent when stderr is not a terminal (CI, pipes)."""

    def __init__(self, enabled=None):
        if enabled is None:
            enabled = sys.stderr.isatty() and not os.environ.get("VOLPUZZLE_NO_PROGRESS")
        self.enabled = enabled

    def stage(self, name):
        if self.enabled:
            print(f"\r\033[K{name} ...", end="", file=sys.stderr, flush=True)

    def piece(self, i, n, piece_id):
        if self.enabled:
            print(f"\r\033[Kcompose {i}/{n} {piece_id}", end="", file=sys.stderr, flush=True)

    def done(self):
        if self.enabled:
            print("\r\033[K", end="", file=sys.stderr, flush=True)


@dataclass
class Timer:
    timings: dict = field(default_factory=dict)

    @contextmanager
    def __call__(self, name, progress=None):
        if progress is not None:
            progress.stage(name)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = round(self.timings.get(name, 0.0) + time.perf_counter() - t0, 3)


@dataclass(frozen=True, eq=False)
class Model:
    """The model M in mm, ready for the stages, and what the report says of it."""

    volume: object  # spline.Volume, control points in mm (the cage, in mesh mode)
    scale: float  # mm per model unit, including `size`
    info: dict
    mesh: object = None  # trimesh.Trimesh in mm, in mesh mode: each piece is finally intersected with it


def _scaled(vol, factor):
    return vol if factor == 1.0 else vol.scaled(factor)


def load_model_for(spec):
    """Read or construct M, scale it to mm (units, then size). -> Model"""
    from .io import load_model_with_meta
    from .spline.measure import bbox

    ms = spec.model
    if ms.builtin is not None:
        from .models import make_builtin

        vol, meta = make_builtin(ms.builtin), {"format": "builtin", "units": "mm"}
    elif ms.nurbs is not None:
        vol, meta = load_model_with_meta(ms.nurbs, patch=ms.patch)
    elif ms.shell is not None:
        from .shell import load_shell

        # the thickness is mm of the printed object, so the surface is sized before it is offset
        shell, scale, meta = load_shell(ms.shell, ms.unit_scale, ms.size, spec.output.tolerance)
        return Model(shell.volume, scale, {"format": meta.get("format"), "scale_mm_per_unit": scale,
                                           "shell": shell.info})
    else:
        return _load_mesh_model(spec)
    scale = ms.unit_scale
    vol = _scaled(vol, scale)
    if ms.size is not None:
        lo, hi = bbox(vol)
        largest = float(np.max(np.asarray(hi) - np.asarray(lo)))
        factor = ms.size / largest
        vol = _scaled(vol, factor)
        scale *= factor
    return Model(vol, scale, {"format": meta.get("format"), "scale_mm_per_unit": scale})


def _load_mesh_model(spec):
    """A closed mesh in mm and the cage fitted around it (paper section 5)."""
    from .cage import check_inside, make_cage
    from .io.mesh import load_mesh_scaled

    ms = spec.model
    if spec.joints.space == "domain" and spec.joints.style != "none":
        raise SpecError("joints.space: pins built in the domain are not supported with a mesh model "
                        "(got domain, expected physical)", source=spec.source)
    mesh, scale = load_mesh_scaled(ms.mesh, unit_scale=ms.unit_scale, size=ms.size, repair=ms.repair)
    cage, cage_info = make_cage(mesh, ms.cage, scale=scale,
                                balance_grid=spec.grid if "balanced" in spec.splits else None)
    check_inside(mesh, cage)
    info = {"format": "mesh", "scale_mm_per_unit": scale, "mesh_triangles": int(len(mesh.faces)),
            "cage": {k: v for k, v in cage_info.items() if isinstance(v, (int, float, str, list, tuple))}}
    return Model(cage, scale, info, mesh)


def _seams_for(spec, vol):
    from .spline.seams import find_seams

    found = find_seams(vol)
    return {a: s for a, s in found.items() if a in spec.periodic}, found


def _check_grid_vs_tolerance(spec, tiling, fmap):
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


def prepare(spec, timer=None, progress=None):
    """Every stage up to joints, without meshes: what `validate` runs. -> dict of stage results."""
    from .limits import check_model_limits, check_spec_limits

    check_spec_limits(spec)  # refuse work that cannot fit before any of it is done (or its libraries load)
    timer = timer or Timer()
    with timer("load", progress):
        model = load_model_for(spec)
        check_model_limits(spec, model.volume)
    # the geometry engine and trimesh (about 2 s to import) only once the work is known to fit
    from .joint import place_joints, require_joined
    from .mapping import Map
    from .randomize import family_from_spec
    from .spline.measure import volume as volume_of
    from .tile import tile
    from .verify import verify_model, verify_warp

    vol = model.volume
    closed = [AXES.index(a) for a in model.info.get("shell", {}).get("closed_axes", [])]
    if closed:  # a shell's closed direction is periodic whether or not the spec says so
        import dataclasses

        spec = dataclasses.replace(spec, periodic=tuple(sorted(set(spec.periodic) | set(closed))))
    with timer("verify", progress):
        model_check = verify_model(vol)
    seams, all_seams = _seams_for(spec, vol)
    rand = spec.randomize
    warp, rand_report = None, {"seed": None, "amplitude": 0.0, "jacobian_min_coefficient": None, "bijective": True}
    if rand is not None and rand.amplitude > 0:
        with timer("randomize", progress):
            family = family_from_spec(vol.domain_array, rand, np.random.default_rng(rand.seed), seams)
            warp = family(rand.amplitude)
        with timer("verify", progress):
            cert = verify_warp(family, rand.amplitude)
        rand_report = {"seed": rand.seed, "amplitude": rand.amplitude, "control_points": rand.control_points, **cert}
    orientation = -1 if model_check["handedness"] == "left" else 1
    fmap = Map(vol, warp, orientation)
    with timer("tile", progress):
        mass = None
        if model.mesh is not None and "balanced" in spec.splits:
            from .cage import mesh_mass

            # through the warp too: the cells are cut from the randomized cage
            mass = mesh_mass(fmap, model.mesh)
        tiling = tile(vol, spec.grid, spec.splits, spec.periodic, seams, mass)
    _check_grid_vs_tolerance(spec, tiling, fmap)
    plan, joints, contacts = None, [], None
    # In mesh mode the joints and their plan go on the contacts of the final pieces, known only after composing.
    if model.mesh is None:
        with timer("joint", progress):
            if spec.joints.style != "none" and tiling.faces:
                from .assembly import plan_assembly, with_joints

                # With straight pins and bumpy cut faces a jointed face can only part along its pins, so the assembly
                # is planned first (blocks that slide apart) and every pin of a split points along its sliding
                # direction.
                plan = plan_assembly(tiling, fmap)
            layout = place_joints(tiling, fmap, spec.joints, plan)
            joints, contacts = list(layout.joints), list(layout.contacts)
            if plan is not None:
                plan = with_joints(plan, tiling, joints)
            require_joined(tiling, layout, spec.joints)
    from .spline.measure import bbox

    if model.mesh is not None:
        lo, hi = model.mesh.bounds
        model_volume = float(model.mesh.volume)
    else:
        lo, hi = bbox(vol)
        model_volume = float(volume_of(vol))
    model_report = {
        "volume_mm3": model_volume,
        "bbox_mm": [np.round(lo, 4).tolist(), np.round(hi, 4).tolist()],
        "handedness": model_check["handedness"],
        "degenerate": bool(model_check.get("degenerate", False)),
        "notes": list(model_check.get("notes", [])),
        "periodic_axes_found": [AXES[a] for a in sorted(all_seams)],
        **model.info,
    }
    return {"model": model, "tiling": tiling, "fmap": fmap, "joints": joints, "plan": plan,
            "contacts": contacts, "model_report": model_report, "randomize_report": rand_report}


def joint_gap_volume(joint):
    """mm^3 the joint leaves empty between its pieces (volpuzzle.joint.gap_volume)."""
    from .joint import gap_volume

    return gap_volume(joint)


def _check_plate(spec, tiling, fmap):
    """Refuse a plate smaller than the largest piece before any mesh is built, naming the size needed."""
    import trimesh

    plate = np.sort(np.asarray(spec.output.plate, float))[::-1]
    t = np.linspace(0, 1, 5)
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    cells = list(tiling.cells.values())
    pts = fmap.evaluate(np.concatenate([c.box[0] + grid * (c.box[1] - c.box[0]) for c in cells]))
    pts = pts.reshape(len(cells), len(grid), 3)

    def footprint(p, exact):
        # a box along the principal axes that fits proves the piece fits; only a misfit needs trimesh's smallest box
        # (about 10 ms a piece)
        if exact:
            ext = trimesh.bounds.oriented_bounds(p)[1]
        else:
            q = p - p.mean(axis=0)
            ext = np.ptp(q @ np.linalg.svd(q, full_matrices=False)[2].T, axis=0)
        return np.sort(ext)[::-1][:2] + 2 * spec.output.spacing + 2 * spec.output.margin

    if all(np.all(footprint(p, False) <= plate + 1e-9) for p in pts):
        return
    need = np.max([footprint(p, True) for p in pts], axis=0)
    if np.any(need > plate + 1e-9):
        raise SpecError(f"output.plate: the largest piece needs about {need[0]:.0f} x {need[1]:.0f} mm with "
                        f"output.spacing and output.margin (got {list(spec.output.plate)}, expected at least "
                        f"[{np.ceil(need[0]):.0f}, {np.ceil(need[1]):.0f}])", source=spec.source)


def build(spec_path, output_dir=None, fmt=None, seed=None, jobs=None, force=False, progress=None,
          allow_large=False):
    """The whole `volpuzzle build`. Returns the report dict; raises VolpuzzleError on any expected failure."""
    t_start = time.perf_counter()  # the total includes loading the geometry libraries, which the user waits for too
    from .check import BED_MIN_MM2, assert_passed, bed_contact_problem, check_pieces, check_printability
    from .compose import compose
    from .export import check_target, piece_colors, report_piece_entry, spec_inputs, write_build
    from .joint import piece_joints_report
    from .spec import load_spec, spec_to_dict, with_overrides

    progress = progress if progress is not None else Progress()
    spec = with_overrides(load_spec(spec_path), output_dir=output_dir, fmt=fmt, seed=seed, allow_large=allow_large)
    target = check_target(Path(spec.output.directory), force, protect=spec_inputs(spec))
    timer = Timer()
    stages = prepare(spec, timer, progress)
    _check_plate(spec, stages["tiling"], stages["fmap"])
    jobs = jobs or os.cpu_count() or 1
    joints = stages["joints"]
    tolerance = spec.output.tolerance
    mesh_report = None

    state = {}

    def finish(pieces, joints, expected):
        """Print orientations, labels (off the bed side), base cuts, the float32 form the files store, and the
        build's own checks on exactly that."""
        with timer("layout", progress):
            poses = _poses(pieces, joints)
        pieces, labels, engraved = _label(spec, stages, pieces, joints, timer, progress, poses)
        with timer("layout", progress):
            pieces, cut = _base_cuts(pieces, poses)
        if spec.output.labels:
            with timer("label", progress):
                pieces, more = _bed_labels(pieces, labels, poses)
            engraved += more
        with timer("check", progress):
            pieces = _printable(pieces)
            checks = check_pieces([(p.id, p.mesh) for p in pieces], expected - engraved - cut)
        checks["base_cuts_mm3"] = round(cut, 3)
        state["poses"] = poses
        return pieces, labels, engraved, checks

    clearance = spec.output.face_clearance
    if clearance > 0 and joints and spec.joints.space == "domain":
        # pins built in the domain are cut on the cell's own parameter box, whose faces are not set back
        print(f"warning: output.face_clearance: not applied with joints.space: domain (got {clearance:g} mm, the "
              f"cut faces meet)", file=sys.stderr)
        clearance = 0.0
    if stages["model"].mesh is not None:
        from .meshcut import compose_in_mesh

        pieces, joints, stages["plan"], mesh_report = compose_in_mesh(stages, spec.joints, tolerance, jobs, timer,
                                                                      progress, face_clearance=clearance)
        gaps = sum(joint_gap_volume(j) for j in joints)
        face_gaps = mesh_report.pop("face_clearance_mm3", 0.0)
        expected = stages["model_report"]["volume_mm3"] - gaps - face_gaps
        pieces, labels, engraved, checks = finish(pieces, joints, expected)
    else:
        from .compose import face_clearance_volume

        gaps = sum(joint_gap_volume(j) for j in joints)
        for attempt in range(3):
            with timer("compose", progress):
                pieces = compose(stages["tiling"], stages["fmap"], joints, tolerance, jobs=jobs,
                                 progress=progress.piece, face_clearance=clearance)
            face_gaps = face_clearance_volume(pieces.sampling, clearance)
            expected = stages["model_report"]["volume_mm3"] - gaps - face_gaps
            pieces, labels, engraved, checks = finish(pieces, joints, expected)
            deficit_only = (checks["all_closed"] and checks["max_overlap_mm3"] <= checks["overlap_limit_mm3"]
                            and checks["volume_error"] < -0.005)
            if checks["passed"] or not deficit_only or attempt == 2:
                break
            # Chords inside a convex surface lose volume in proportion to the chord error. The user's tolerance is
            # an upper bound, so tessellating finer still honours it while making the volumes add up.
            tolerance *= max(0.2, 0.6 * 0.005 / abs(checks["volume_error"]))
    _require_joined(spec, pieces, joints, stages.get("contacts") or ())
    checks["joint_gaps_mm3"] = round(gaps, 3)
    checks["face_clearance_mm"] = clearance
    checks["face_clearance_mm3"] = round(face_gaps, 3)
    checks["labels_engraved_mm3"] = round(engraved, 3)
    checks["tessellation_tolerance_mm"] = round(tolerance, 6)
    sampling = getattr(pieces, "sampling", None)
    if sampling is not None:
        checks["max_surface_error_mm"] = round(float(sampling.max_error_mm), 6)
    assert_passed(checks)
    for warning in _fit(spec, joints, clearance)["warnings"]:
        print(f"warning: {warning}", file=sys.stderr)
    dowels = []
    if spec.joints.style == "dowel":
        from .geometry import to_trimesh
        from .joint import dowel_solid
        from .layout import lay_dowels_flat

        dowels = [(f"dowel-{i:02d}", to_trimesh(dowel_solid(j))) for i, j in enumerate(joints)]
        dowels, dowel_poses = lay_dowels_flat(dowels, joints)
        state["poses"] = {**state["poses"], **dowel_poses}
    assembly = _assembly(stages["plan"], pieces, joints, timer, progress, allow=spec.joints.allow,
                         randomized=spec.randomize is not None)
    colors = piece_colors(len(pieces))
    pins = pin_triangles(pieces, joints)
    texture, texture_report = _texture(spec, stages, pieces, tolerance, timer, progress)
    with timer("layout", progress):
        placements, plates, extras = _layout(spec, pieces, dowels, joints, colors, pins, texture,
                                             state["poses"], assembly.get("steps"))
    ext = spec.output.format
    place_of = {pl.name: pl for pl in placements}
    entries = []
    for p in pieces:
        entry = report_piece_entry(p, f"pieces/{p.id}.{ext}")
        entry["plate"] = place_of[p.id].plate if p.id in place_of else None
        entry["label"] = labels.get(p.id)
        entry["joints"] = piece_joints_report(joints, p.cell)
        entry["print"] = _print_entry(p, state["poses"].get(p.id), place_of.get(p.id))
        entries.append(entry)
    under = [e["id"] for e in entries if e["print"] and e["print"]["bed_contact_mm2"] < BED_MIN_MM2]
    if under:  # `volpuzzle check` would refuse the folder: so does the build, before writing it
        raise GeometryError(f"{spec.name}: {bed_contact_problem(under)} even with a base cut of "
                            f"{max(state['poses'][pid].base_cut_mm for pid in under):g} mm (expected at least "
                            f"{BED_MIN_MM2:g} mm^2 each; try another grid or randomize.seed)")
    pictures = [f"steps/step-{n:02d}.png" for n in range(1, len(assembly["steps"]) + 1)]
    report = {
        "volpuzzle_version": __version__,
        "spec": spec_to_dict(spec),
        "model": stages["model_report"],
        "randomize": stages["randomize_report"],
        "pieces": entries,
        "joints": [j.to_report() for j in joints],
        "contacts": stages.get("contacts"),
        "checks": checks,
        "fit": _fit(spec, joints, clearance),
        "plates": [{"file": pl.file, "pieces": list(pl.names), "fill_ratio": pl.fill_ratio} for pl in plates],
        "assembly_order": assembly.pop("assembly_order"),
        "assembly": dict(assembly, pictures=pictures),
        "timings_s": timer.timings,
    }
    if mesh_report is not None:
        report["mesh"] = mesh_report
    if texture_report is not None:
        report["texture"] = texture_report
    with timer("check", progress):
        # what `volpuzzle check` will judge of the folder (bed contact, the gap between facing cut faces, pin sizes,
        # labels) is judged before it is written, so a build never passes what its own check refuses
        report["checks"]["printability"] = check_printability(report, {p.id: p.mesh for p in pieces})
    if report["checks"]["printability"]["failures"]:
        raise GeometryError(f"{spec.name}: not printable as laid out: "
                            f"{'; '.join(report['checks']['printability']['failures'])}")
    with timer("export", progress):
        report["timings_s"] = timer.timings
        write_build(target, pieces, report, fmt=ext, force=force, dowels=dowels, colors=colors, extras=extras,
                    pin_triangles=pins, triangle_colors=texture)
    report["timings_s"] = dict(timer.timings, total=round(time.perf_counter() - t_start, 3))
    progress.done()
    return report


def _require_joined(spec, pieces, joints, contacts):
    """The final pieces must all carry a joint and hang together (volpuzzle.joint.graph_problem), unless allowed."""
    from .grid import piece_id
    from .joint import graph_problem

    problem = graph_problem([p.id for p in pieces], [(piece_id(j.pin_cell), piece_id(j.hole_cell)) for j in joints],
                            contacts or (), spec.joints.style, spec.joints.allow, spec.grid)
    if problem:
        raise SpecError(problem, source=spec.source)


def _assembly(plan, pieces, joints, timer, progress, allow=(), randomized=False):
    """Disassembly replayed on the real meshes, reversed. -> dict with assembly_order, steps, words, welded, stuck.
    A welded puzzle fails the build unless joints.allow has 'welded' (then it is a warning)."""
    from .assembly import steps_in_words, verify_disassembly

    if plan is None:
        return {"assembly_order": [p.id for p in pieces], "steps": [], "words": [], "welded": False, "stuck": []}
    with timer("assembly", progress):
        res = verify_disassembly(pieces, joints, plan)
    if res["welded"]:
        stuck = ", ".join(res["stuck"][:6]) + (f" and {len(res['stuck']) - 6} more" if len(res["stuck"]) > 6 else "")
        if "welded" not in tuple(allow):
            tries = "another grid (more pieces along a curved axis)" + (
                ", a smaller randomize.amplitude, another randomize.seed" if randomized else "")
            raise GeometryError(f"assembly: the puzzle is welded: {stuck} cannot be taken out along their pins "
                                f"(got {len(res['stuck'])} stuck pieces, expected none; try {tries}, or "
                                f"joints.allow: [welded])")
        print(f"warning: the puzzle is welded: {stuck} cannot be taken out along their pins", file=sys.stderr)
    return {"assembly_order": res["assembly_order"], "steps": res["steps"], "words": steps_in_words(res),
            "welded": bool(res["welded"]), "stuck": list(res["stuck"])}


def _poses(pieces, joints):
    """{piece id: layout.Pose}: how each piece is printed, planned before labels and base cuts."""
    from .layout import joint_directions, plan_pose

    pins, openings = joint_directions(joints)
    return {p.id: plan_pose(p.mesh, pins.get(p.id, ()), openings.get(p.id, ())) for p in pieces}


def _bed_labels(pieces, labels, poses):
    """Pieces left without a label get it mirrored on their bed side (after the base cut, which would take it off).
    Updates labels in place. -> (pieces, mm^3 removed)"""
    import dataclasses

    from .geometry import from_trimesh, to_trimesh
    from .label import engrave_bed

    out, removed = [], 0.0
    for k, p in enumerate(pieces):
        entry = labels.get(p.id)
        pose = poses.get(p.id)
        if (entry or {}).get("text") or pose is None:
            out.append(p)
            continue
        body = from_trimesh(p.mesh, p.id)
        for text in (p.id, str(k + 1)):
            new, site = engrave_bed(body, pose.rotation, text, what=p.id)
            if site is not None:
                volume = float(new.volume())
                mesh = to_trimesh(new)
                removed += p.volume - volume
                p = dataclasses.replace(p, mesh=mesh, volume=volume, triangles=int(len(mesh.faces)))
                labels[p.id] = site
                break
        out.append(p)
    return _like(pieces, out), removed


def _base_cuts(pieces, poses):
    """Each piece with the flat cut its pose asks for -> (pieces, mm^3 removed in all)."""
    import dataclasses

    from .layout import base_cut

    out, removed = [], 0.0
    for p in pieces:
        pose = poses.get(p.id)
        if pose is None or pose.base_cut_mm <= 0:
            out.append(p)
            continue
        mesh, v = base_cut(p.mesh, pose, p.id)
        removed += v
        out.append(dataclasses.replace(p, mesh=mesh, volume=p.volume - v, triangles=int(len(mesh.faces))))
    return _like(pieces, out), removed


def _print_entry(piece, pose, placement):
    """report.json "print" of a piece: its pose, the (4, 4) transform to its plate, its bed contact there."""
    from .layout import bed_contact

    if pose is None or placement is None:
        return None
    entry = pose.to_report()
    entry["plate_transform"] = np.round(placement.transform, 6).tolist()
    entry["bed_contact_mm2"] = round(bed_contact(piece.mesh.vertices, piece.mesh.faces, placement.transform), 2)
    return entry


def _like(pieces, out):
    """`out` as the same kind of list as `pieces` (compose's Pieces carries .sampling and .seconds)."""
    if not hasattr(pieces, "sampling"):
        return out
    kept = type(pieces)(out)
    kept.sampling, kept.seconds = pieces.sampling, getattr(pieces, "seconds", None)
    return kept


def _printable(pieces):
    """Pieces exactly as STL and 3MF store them: float32 vertices. Rounding can merge the ends of micro-edges that
    booleans and tessellation leave; those edges are collapsed (exact duplicates merged, triangles that repeat a
    vertex dropped) so the checks judge the very mesh that is written."""
    import dataclasses

    import trimesh

    from .check import closed_problem, signed_volume
    from .geometry import weld

    out = []
    for p in pieces:
        # + 0 turns -0.0 into 0.0, so that equal coordinates have equal bytes; a byte-wise unique is ~3x faster
        # than np.unique(axis=0)
        v32 = np.ascontiguousarray(np.asarray(p.mesh.vertices, dtype=np.float32) + np.float32(0.0))
        _, first, inverse = np.unique(v32.view(np.dtype((np.void, 12))).ravel(), return_index=True,
                                      return_inverse=True)
        v, f = weld(v32[first].astype(np.float64), inverse.reshape(-1)[p.mesh.faces], 0.0)
        mesh = trimesh.Trimesh(v, f, process=False)
        problem = closed_problem(mesh)
        if problem:
            raise GeometryError(f"{p.id}: the piece is no longer one closed solid at the float32 precision of STL and "
                                f"3MF files ({problem}); try a smaller output.tolerance")
        out.append(dataclasses.replace(p, mesh=mesh, volume=signed_volume(v, f), triangles=int(len(f))))
    out = _like(pieces, out)
    return out


def _label(spec, stages, pieces, joints, timer, progress, poses=None):
    """Engrave each piece's id on an inner face no joint uses, off its bed side. -> (pieces, {id: label report or
    None}, mm^3 removed)"""
    import dataclasses

    from .geometry import from_trimesh, to_trimesh
    from .label import label_piece, site_on_joint_face

    if not spec.output.labels:
        return pieces, {}, 0.0
    tiling, fmap = stages["tiling"], stages["fmap"]

    poses = poses or {}

    def one(k, p):
        pose = poses.get(p.id)
        # the piece id, else its number in the piece list (report.md gives the key)
        texts = (p.id, str(k + 1))
        try:
            body, site, note = label_piece(from_trimesh(p.mesh, p.id), tiling.cell(p.cell), tiling, fmap, joints,
                                           what=p.id, texts=texts, avoid=None if pose is None else pose.down)
        except GeometryError as e:
            # A label is a convenience: a piece too thin to take the groove keeps its material and says why.
            return p, {"skipped": str(e)}, 0.0
        if site is None:
            return p, {"skipped": note}, 0.0
        mesh = to_trimesh(body)
        volume = float(body.volume())  # the engine's own sum, as compose measured p.volume; trimesh's costs more
        entry = site.to_report()
        entry["on_joint_face"] = bool(entry["on_joint_face"] or site_on_joint_face(site, joints, p.cell))
        return (dataclasses.replace(p, mesh=mesh, volume=volume, triangles=int(len(mesh.faces))),
                entry, p.volume - volume)

    with timer("label", progress):
        results = [one(k, p) for k, p in enumerate(pieces)]
    out = [r[0] for r in results]
    sites = {p.id: r[1] for p, r in zip(pieces, results, strict=True)}
    removed = sum(r[2] for r in results)
    out = _like(pieces, out)
    return out, sites, removed


def pin_triangles(pieces, joints):
    """{piece id: (m,) uint8, 1 for triangles on one of its pins}: those outside the piece's face, within the pin's
    outer radius (a snap pin swells) and length. For the second (pin) material of 3MF files."""
    from .joint import outer_radius

    out = {}
    for p in pieces:
        mine = [j for j in joints if j.style == "pin" and tuple(j.pin_cell) == tuple(p.cell)]
        if not mine:
            continue
        c = p.mesh.triangles_center
        flag = np.zeros(len(c), np.uint8)
        for j in mine:
            d = np.asarray(j.direction, float)
            rel = c - np.asarray(j.center, float)
            t = rel @ d
            radial = np.linalg.norm(rel - t[:, None] * d, axis=1)
            reach = outer_radius(j.radius, j.shape) + 1e-3
            flag |= ((t > 1e-3) & (t <= j.length + 1e-3) & (radial <= reach)).astype(np.uint8)
        out[p.id] = flag
    return out


def _texture(spec, stages, pieces, tolerance, timer, progress):
    """Per-triangle texture colours of every piece, or (None, None) without a texture."""
    if spec.texture is None:
        return None, None
    from .texture import texture_pieces

    with timer("texture", progress):
        colors, report = texture_pieces(spec.texture, stages["model"].volume, pieces, tolerance)
    if spec.output.format == "stl":
        report["note"] = ("STL cannot hold colour: the pieces/*.stl files are plain; the texture is in puzzle.3mf, "
                          "the plates and preview.png (output.format: 3mf gives coloured piece files too)")
        print(f"warning: texture: {report['note']}", file=sys.stderr)
    return colors, report


def _layout(spec, pieces, dowels, joints, colors, pins=None, texture=None, poses=None, steps=None):
    """Plates and preview as writers for the export stage. -> (placements, plates, {relative path: writer})"""
    from .io.threemf import write_3mf
    from .layout import joint_directions, layout
    from .preview import plan_offsets, render_preview

    pin_dirs, openings = joint_directions(joints)
    parts = [(p.id, p.mesh) for p in pieces] + list(dowels)
    rgb = {p.id: c for p, c in zip(pieces, colors, strict=True)}
    placements, plates = layout(parts, spec.output.plate, spec.output.spacing, pin_dirs, margin=spec.output.margin,
                                poses=poses, hole_openings=openings)
    meshes = dict(parts)
    extras = {}
    for pl in plates:
        def write_plate(path, pl=pl):
            objs = []
            for place in placements:
                if place.plate != pl.index:
                    continue
                m = meshes[place.name]
                v = m.vertices @ place.transform[:3, :3].T + place.transform[:3, 3]
                objs.append((place.name, v, m.faces, rgb.get(place.name, (200, 200, 200)), None))
            write_3mf(path, objs, materials=[(pins or {}).get(o[0]) for o in objs],
                      colors=None if texture is None else [texture.get(o[0]) for o in objs])
        extras[pl.file] = write_plate
    if texture is not None:
        from .texture import face_colors

    def write_preview(path):
        # pins a shade darker than their piece, so that they stand out
        shaded = []
        for p, c in zip(pieces, colors, strict=True):
            flag = (pins or {}).get(p.id)
            if texture is None and flag is None:
                shaded.append(np.asarray(c, np.uint8))
                continue
            tri = (np.array(face_colors(c, texture[p.id]), np.uint8) if texture is not None
                   else np.tile(np.asarray(c, np.uint8), (len(p.mesh.faces), 1)))
            if flag is not None:
                tri[flag.astype(bool)] = (tri[flag.astype(bool)] * 0.55).astype(np.uint8)
            shaded.append(tri)
        index = {p.id: k for k, p in enumerate(pieces)}
        on_plate = [(index[pl.name], pl.transform) for pl in placements if pl.plate == 1 and pl.name in index]
        offsets = plan_offsets([p.mesh for p in pieces], [p.id for p in pieces], steps) if steps else None
        render_preview(path, [p.mesh for p in pieces], shaded, title=spec.name, offsets=offsets,
                       plate=(on_plate, tuple(spec.output.plate)))

    extras["preview.png"] = write_preview
    if steps:
        from .preview import render_steps

        extras["steps"] = lambda path: render_steps(path, [p.mesh for p in pieces], [p.id for p in pieces],
                                                    colors, steps)
    return placements, plates, extras


def validate(spec_path, allow_large=False):
    """`volpuzzle validate`: the spec, the model and every cross-check, without building. -> summary dict"""
    from .spec import load_spec, with_overrides

    spec = with_overrides(load_spec(spec_path), allow_large=allow_large)
    stages = prepare(spec)
    _check_plate(spec, stages["tiling"], stages["fmap"])  # build refuses a small plate before meshing: so does this
    clearance = spec.output.face_clearance
    return {"name": spec.name, "pieces": math.prod(spec.grid), "joints": len(stages["joints"]),
            "model": stages["model_report"], "randomize": stages["randomize_report"],
            "fit": _fit(spec, stages["joints"], clearance)}


def _fit(spec, joints, face_clearance):
    """Pin size and fit of the planned joints (the thinnest and shortest, when the joint stage sized them per
    face) and the face clearance applied, with warnings below the printable minimum (check.pin_fit)."""
    from .check import pin_fit

    j = spec.joints
    if not joints:
        return pin_fit("none", 0.0, 0.0, j.clearance, j.axial_clearance, face_clearance)
    return pin_fit(j.style, min(float(x.radius) for x in joints), min(float(x.length) for x in joints),
                   max(float(x.clearance) for x in joints), max(float(x.axial_clearance) for x in joints),
                   face_clearance)
