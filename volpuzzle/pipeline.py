"""Runs the stages in order: spec -> load -> verify -> randomize -> tile -> joint -> compose -> layout/label -> check
-> report -> export. Each stage lives in its own module; this one only calls them, times them and passes their
results on in one Stages record."""

from __future__ import annotations

import dataclasses
import math
import os
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import ModelError
from .load import load_model_for, with_closed_axes
from .progress import Progress, Timer, warn

if TYPE_CHECKING:  # the stage modules load trimesh and the geometry engine: only after the limits pass
    from .assembly import AssemblyPlan
    from .compose import Piece
    from .compose.ahead import Ahead
    from .joint import Joint
    from .layout import Pose
    from .load import Model
    from .mapping import Map
    from .tile import Tiling

__all__ = ["Progress", "Stages", "Timer", "build", "prepare", "validate"]


@dataclass(frozen=True, eq=False)
class Stages:
    """The stage results of one build. prepare fills the first block (all `validate` needs); compose fills the
    second (dataclasses.replace, so earlier results never change under a later stage)."""

    model: Model
    tiling: Tiling
    fmap: Map  # F = M o R, domain -> mm
    joints: list[Joint]  # as placed on the tiling (volume models) or on the final pieces (mesh models)
    plan: AssemblyPlan | None
    contacts: list[dict] | None  # joint.Layout.contacts report records; None in mesh mode (report "mesh" has them)
    model_report: dict  # report.json "model"
    randomize_report: dict  # report.json "randomize"
    pieces: list[Piece] = field(default_factory=list)  # as the files store them (labelled, base cut, float32)
    poses: dict[str, Pose] = field(default_factory=dict)  # by piece id
    labels: dict[str, dict | None] = field(default_factory=dict)  # label report by piece id
    engraved_mm3: float = 0.0  # removed by the labels
    checks: dict = field(default_factory=dict)  # report.json "checks" (check.check_pieces and the figures behind it)
    tolerance: float = 0.0  # mm, the tessellation tolerance finally used (at most output.tolerance)
    face_clearance: float = 0.0  # mm, the gap between mating cut faces actually applied
    mesh_report: dict | None = None  # mesh mode: meshcut.compose_in_mesh's report
    ahead: Ahead | None = None  # compose's Sampling at output.tolerance and cell surfaces, begun while joints plan
    face_gaps: list = field(default_factory=list)  # check.neighbour_gaps of the pieces, for check_printability


def prepare(spec, timer=None, progress=None, workers=None):
    """Every stage up to joints, without meshes: what `validate` runs. -> Stages (pieces not yet built). With
    workers, a worker samples the cell faces for compose meanwhile, then makes cell surfaces (Stages.ahead)."""
    from .limits import check_model_limits, check_spec_limits

    check_spec_limits(spec)  # refuse work that cannot fit before any of it is done (or its libraries load)
    timer = timer or Timer()
    with timer("load", progress):
        model = load_model_for(spec)
        check_model_limits(spec, model.volume)
    # the geometry engine and trimesh (about 2 s to import) only once the work is known to fit
    from .joint import place_planned_joints
    from .mapping import Map
    from .report import model_report
    from .spline.seams import find_seams
    from .tile import check_grid_vs_tolerance, seams_for, tile
    from .verify import verify_model

    vol = model.volume
    found = find_seams(vol)
    spec = with_closed_axes(spec, model, found)
    with timer("verify", progress):
        try:
            model_check = verify_model(vol)
        except ModelError as exc:  # verify sees only the spline: say which file (and patch) folds
            raise ModelError(f"{_model_source(spec)}: {exc}") from None
    seams, all_seams = seams_for(spec, vol, found)
    warp, rand_report = _warp(spec, vol, seams, timer, progress)
    fmap = Map(vol, warp, -1 if model_check["handedness"] == "left" else 1)
    with timer("tile", progress):
        mass = None
        if model.mesh is not None and "balanced" in spec.splits:
            from .cage import mesh_mass

            mass = mesh_mass(fmap, model.mesh)  # through the warp too: the cells are cut from the randomized cage
        tiling = tile(vol, spec.grid, spec.splits, spec.periodic, seams, mass)
    check_grid_vs_tolerance(spec, tiling, fmap)
    ahead = None
    if workers is not None and model.mesh is None:  # the sampling needs no joints: a worker begins it now
        from .compose.ahead import begin

        ahead = begin(workers, tiling, fmap, spec.output.tolerance, _planned_clearance(spec))
    plan, joints, contacts = None, [], None
    if model.mesh is None:  # in mesh mode the joints go on the contacts of the final pieces, known after composing
        with timer("joint", progress):
            layout, plan = place_planned_joints(tiling, fmap, spec.joints)
        joints, contacts = list(layout.joints), list(layout.contacts)
    return Stages(model, tiling, fmap, joints, plan, contacts, model_report(model, model_check, all_seams),
                  rand_report, ahead=ahead)


def _model_source(spec):
    """The spec key and file of the spline verify_model checks, for its messages: 'model.nurbs: PATH (patch K)'."""
    m = spec.model
    if m.nurbs is not None:
        return f"model.nurbs: {m.nurbs}" + (f" (patch {m.patch})" if m.patch else "")
    if m.cage is not None and m.cage.nurbs is not None:
        return f"model.cage.nurbs: {m.cage.nurbs}" + (f" (patch {m.cage.patch})" if m.cage.patch else "")
    if m.shell is not None:
        return f"model.shell.surface: {m.shell.surface}"
    if m.builtin is not None:
        return f"model.builtin ({m.builtin.get('type')})"
    return f"model.cage ({m.cage.type})" if m.cage is not None else "model"


def _warp(spec, vol, seams, timer, progress):
    """The random map R of spec.randomize and its verified certificate -> (Volume or None, report "randomize")."""
    import numpy as np

    from .randomize import family_from_spec
    from .report import randomize_report
    from .verify import verify_warp

    rand = spec.randomize
    if rand is None or rand.amplitude <= 0:
        return None, randomize_report(rand)
    with timer("randomize", progress):
        family = family_from_spec(vol.domain_array, rand, np.random.default_rng(rand.seed), seams)
        warp = family(rand.amplitude)
    with timer("verify", progress):
        certificate = verify_warp(family, rand.amplitude)
    return warp, randomize_report(rand, certificate)


def build(spec_path, output_dir=None, fmt=None, seed=None, jobs=None, force=False, progress=None,
          allow_large=False):
    """The whole `volpuzzle build`. Returns the report dict; raises VolpuzzleError on any expected failure."""
    t_start = time.perf_counter()  # the total includes loading the geometry libraries, which the user waits for too
    from .export import check_target, spec_inputs
    from .precompile import start as compile_ahead
    from .spec import load_spec, with_overrides
    from .workers import start as start_workers

    progress = progress if progress is not None else Progress()
    spec = with_overrides(load_spec(spec_path), output_dir=output_dir, fmt=fmt, seed=seed, allow_large=allow_large)
    if seed is not None and spec.randomize is None:  # a user passing a seed expects it to change the pieces
        warn(f"--seed {seed} changes nothing: the spec does not randomize (got no randomize or amplitude 0, "
             f"expected randomize: {{amplitude: 0.25}} for a seed to matter)")
    target = check_target(Path(spec.output.directory), force, protect=spec_inputs(spec))
    jobs = jobs or os.cpu_count() or 1
    # started first, so that the workers' start-up runs on the other cores while this process loads and plans
    workers = start_workers(jobs, math.prod(spec.grid))
    compile_ahead(jobs)  # on a new machine, the later stages' kernels compile on another core meanwhile
    try:
        return _build(spec, target, jobs, force, progress, workers, t_start)
    finally:
        if workers is not None:
            workers.close()


def _build(spec, target, jobs, force, progress, workers, t_start):
    """build() once the spec is read and the target free: every stage, then the files -> the report dict."""
    from .assembly import replay_assembly
    from .check import assert_passed, check_printability, pairs_apart
    from .export import piece_colors, pin_triangles, write_build
    from .geometry import forget
    from .joint import dowel_parts, require_pieces_joined
    from .layout import check_plate, lay_dowels_flat, plates_and_preview, step_pictures_ahead
    from .report import build_report, fit, require_printable
    from .texture import build_texture

    timer = Timer()
    s = prepare(spec, timer, progress, workers)
    check_plate(spec, s.tiling, s.fmap)
    s = _compose(spec, s, jobs, timer, progress, workers)
    require_pieces_joined(spec, s.pieces, s.joints, s.contacts or ())
    assert_passed(s.checks)
    for warning in fit(spec, s.joints, s.face_clearance)["warnings"]:
        warn(warning)
    dowels, dowel_poses = lay_dowels_flat(dowel_parts(s.joints), s.joints) if spec.joints.style == "dowel" else ([], {})
    meshes = {p.id: p.mesh for p in s.pieces}
    with timer("assembly", progress) if s.plan is not None else nullcontext():  # no plan: nothing to replay or time
        assembly = replay_assembly(s.plan, s.pieces, s.joints, spec.joints.allow, spec.randomize is not None,
                                   tiling=s.tiling, fmap=s.fmap, workers=workers,
                                   apart=pairs_apart(s.face_gaps, meshes))
    colors = piece_colors(len(s.pieces))
    pictures = step_pictures_ahead(workers, s.pieces, colors, assembly.get("steps"))
    pins = pin_triangles(s.pieces, s.joints)  # after: the worker has nothing to do until it has the steps (0.5 s)
    texture, texture_report = None, None
    if spec.texture is not None:
        with timer("texture", progress):
            texture, texture_report = build_texture(spec, s.model.volume, s.pieces, s.tolerance)
    with timer("layout", progress):
        placements, plates, extras = plates_and_preview(spec, s.pieces, dowels, s.joints, colors, pins, texture,
                                                        {**s.poses, **dowel_poses}, assembly.get("steps"), pictures)
    report = build_report(spec, s, assembly, placements, plates, texture_report, timer.timings)
    with timer("check", progress):
        # what `volpuzzle check` will judge of the folder (bed contact, the gap between facing cut faces, pin sizes,
        # labels) is judged before it is written, so a build never passes what its own check refuses
        report["checks"]["printability"] = check_printability(report, meshes, workers=workers, gaps=s.face_gaps)
    require_printable(spec, report)
    forget(p.mesh for p in s.pieces)  # from here on the pieces are only written and drawn
    with timer("export", progress):
        report["timings_s"] = timer.timings
        write_build(target, s.pieces, report, fmt=spec.output.format, force=force, dowels=dowels, colors=colors,
                    extras=extras, pin_triangles=pins, triangle_colors=texture, workers=workers)
    report["timings_s"] = dict(timer.timings, total=round(time.perf_counter() - t_start, 3))
    progress.done()
    return report


def _planned_clearance(spec):
    """The face clearance _face_clearance will apply, as far as the spec tells before the joints are placed: None
    when it depends on them (pins built in the domain)."""
    if spec.output.face_clearance > 0 and spec.joints.space == "domain" and spec.joints.style != "none":
        return None
    return float(spec.output.face_clearance)


def _face_clearance(spec, s):
    """mm of output.face_clearance that can be applied (0 with pins built in the domain, warned)."""
    clearance = spec.output.face_clearance
    if clearance > 0 and s.joints and spec.joints.space == "domain":
        # pins built in the domain are cut on the cell's own parameter box, whose faces are not set back
        warn(f"output.face_clearance: not applied with joints.space: domain (got {clearance:g} mm, the "
             f"cut faces meet)")
        clearance = 0.0
    return clearance


def _compose(spec, s, jobs, timer, progress, workers=None):
    """The pieces composed, finished (_finish) and checked -> Stages with pieces, poses, labels, checks. A volume
    model whose pieces only lack volume is composed again at a finer tessellation tolerance, up to three times."""
    from .compose import compose, face_clearance_volume
    from .joint import gap_volume
    from .workers import warm_rest

    clearance, tolerance = _face_clearance(spec, s), spec.output.tolerance
    mesh_report, sampling, face_gaps = None, None, 0.0
    if s.model.mesh is not None:
        from .meshcut import compose_in_mesh

        pieces, joints, plan, mesh_report = compose_in_mesh(s, spec.joints, tolerance, jobs, timer, progress,
                                                            face_clearance=clearance, workers=workers)
        s = dataclasses.replace(s, joints=joints, plan=plan)
        gaps = sum(gap_volume(j) for j in joints)
        face_gaps = mesh_report.pop("face_clearance_mm3", 0.0)
        done = _finish(spec, s, pieces, s.model_report["volume_mm3"] - gaps - face_gaps, clearance, timer, progress,
                       workers)
    else:
        gaps = sum(gap_volume(j) for j in s.joints)
        for attempt in range(3):
            with timer("compose", progress):
                # while a worker still samples, this process loads what the later stages need (labels' outlines)
                first = s.ahead if attempt == 0 else None
                if first is not None:
                    first.stop()  # the worker's surfaces made so far are its to use; it builds pieces now
                sampled = first.sampling.result(meanwhile=warm_rest) if first is not None else None
                pieces = compose(s.tiling, s.fmap, s.joints, tolerance, jobs=jobs, progress=progress.piece,
                                 sampling=sampled, face_clearance=clearance, workers=workers,
                                 ahead=first.token if first is not None else None)
            sampling = pieces.sampling  # the finishing stages return plain lists
            face_gaps = face_clearance_volume(sampling, clearance)
            done = _finish(spec, s, pieces, s.model_report["volume_mm3"] - gaps - face_gaps, clearance, timer,
                           progress, workers)
            checks = done.checks
            deficit_only = (checks["all_closed"] and checks["max_overlap_mm3"] <= checks["overlap_limit_mm3"]
                            and checks["volume_error"] < -0.005)
            if checks["passed"] or not deficit_only or attempt == 2:
                break
            # Chords inside a convex surface lose volume in proportion to the chord error. The user's tolerance is
            # an upper bound, so tessellating finer still honours it while making the volumes add up.
            tolerance *= max(0.2, 0.6 * 0.005 / abs(checks["volume_error"]))
    checks = done.checks
    checks["joint_gaps_mm3"] = round(gaps, 3)
    checks["face_clearance_mm"] = clearance
    checks["face_clearance_mm3"] = round(face_gaps, 3)
    checks["labels_engraved_mm3"] = round(done.engraved_mm3, 3)
    checks["tessellation_tolerance_mm"] = round(tolerance, 6)
    if sampling is not None:
        checks["max_surface_error_mm"] = round(float(sampling.max_error_mm), 6)
    return dataclasses.replace(done, tolerance=tolerance, face_clearance=clearance, mesh_report=mesh_report)


def _finish(spec, s, pieces, expected, clearance, timer, progress, workers=None):
    """Print orientations, labels (off the bed side), base cuts, the float32 form the files store, and the build's
    own checks on exactly that -> Stages with pieces, poses, labels, checks, face gaps. expected: mm^3 the pieces add
    up to before labels and base cuts take theirs; clearance: the face clearance applied, mm."""
    from .check import check_joints, check_pieces, neighbour_gaps, pairs_apart
    from .export import printable
    from .label import bed_labels, label_pieces
    from .layout import base_cuts, plan_poses

    with timer("layout", progress):
        poses = plan_poses(pieces, s.joints, workers=workers)
    labels, engraved = {}, 0.0
    if spec.output.labels:
        with timer("label", progress):
            pieces, labels, engraved = _replaced(pieces, *label_pieces(s.tiling, s.fmap, pieces, s.joints, poses,
                                                                       workers=workers,
                                                                       cut_by_mesh=s.model.mesh is not None))
    with timer("layout", progress):
        pieces, cut = _replaced(pieces, *base_cuts(pieces, poses, workers=workers))
    if spec.output.labels:
        with timer("label", progress):
            pieces, more = _replaced(pieces, *bed_labels(pieces, labels, poses))
        engraved += more
    with timer("check", progress):
        pieces = _replaced(pieces, printable(pieces, workers=workers))[0]
        meshes = {p.id: p.mesh for p in pieces}
        # the face gaps first: a pair whose surfaces they find apart needs no overlap Boolean (pairs_apart)
        gaps = neighbour_gaps(meshes, clearance, s.contacts, workers=workers)
        checks = check_pieces(list(meshes.items()), expected - engraved - cut, workers=workers,
                              apart=pairs_apart(gaps, meshes))
        # every pin in its hole on the pieces as written, as `volpuzzle check` judges them: a label, a base cut or
        # the float32 rounding after the joints were cut must not pass here and fail there
        joint_failures = check_joints(meshes, [j.to_report() for j in s.joints], workers=workers)
        checks["failures"] = checks["failures"] + joint_failures
        checks["passed"] = checks["passed"] and not joint_failures
    checks["base_cuts_mm3"] = round(cut, 3)
    return dataclasses.replace(s, pieces=pieces, poses=poses, labels=labels, engraved_mm3=engraved, checks=checks,
                               face_gaps=gaps)


def _replaced(old, new, *rest):
    """(new, *rest), once the solids and cached arrays of the meshes in `old` that `new` no longer has are let go
    (geometry.forget): each finishing stage replaces the pieces, and at 1024 pieces every generation's solids
    held to the end would be 0.5 GB."""
    from .geometry import forget

    keep = {id(p.mesh) for p in new}
    forget(p.mesh for p in old if id(p.mesh) not in keep)
    return (new, *rest)


def validate(spec_path, allow_large=False):
    """`volpuzzle validate`: the spec, the model and every cross-check, without building. -> summary dict"""
    from .layout import check_plate
    from .report import fit
    from .spec import load_spec, with_overrides

    spec = with_overrides(load_spec(spec_path), allow_large=allow_large)
    s = prepare(spec)
    check_plate(spec, s.tiling, s.fmap)  # build refuses a small plate before meshing: so does this
    clearance = spec.output.face_clearance
    return {"name": spec.name, "pieces": math.prod(spec.grid), "joints": len(s.joints), "model": s.model_report,
            "randomize": s.randomize_report, "fit": fit(spec, s.joints, clearance)}
