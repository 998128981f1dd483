"""Runs the stages in order: spec -> model -> tile -> joint -> randomize -> verify -> compose -> check -> export."""

import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from .errors import GeometryError
from .grid import AXES
from .load import load_model_for
from .progress import Progress, Timer


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
    from .tile import check_grid_vs_tolerance, seams_for, tile
    from .verify import verify_model, verify_warp

    vol = model.volume
    closed = [AXES.index(a) for a in model.info.get("shell", {}).get("closed_axes", [])]
    if closed:  # a shell's closed direction is periodic whether or not the spec says so
        import dataclasses

        spec = dataclasses.replace(spec, periodic=tuple(sorted(set(spec.periodic) | set(closed))))
    with timer("verify", progress):
        model_check = verify_model(vol)
    seams, all_seams = seams_for(spec, vol)
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
    check_grid_vs_tolerance(spec, tiling, fmap)
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


def build(spec_path, output_dir=None, fmt=None, seed=None, jobs=None, force=False, progress=None,
          allow_large=False):
    """The whole `volpuzzle build`. Returns the report dict; raises VolpuzzleError on any expected failure."""
    t_start = time.perf_counter()  # the total includes loading the geometry libraries, which the user waits for too
    from .assembly import replay_assembly
    from .check import BED_MIN_MM2, assert_passed, bed_contact_problem, check_pieces, check_printability
    from .compose import compose
    from .export import (
        check_target,
        piece_colors,
        pin_triangles,
        printable,
        report_piece_entry,
        spec_inputs,
        write_build,
    )
    from .joint import dowel_parts, gap_volume, piece_joints_report, require_pieces_joined
    from .label import bed_labels, label_pieces
    from .layout import base_cuts, check_plate, plan_poses, plates_and_preview, print_entry
    from .spec import load_spec, spec_to_dict, with_overrides
    from .texture import build_texture

    progress = progress if progress is not None else Progress()
    spec = with_overrides(load_spec(spec_path), output_dir=output_dir, fmt=fmt, seed=seed, allow_large=allow_large)
    target = check_target(Path(spec.output.directory), force, protect=spec_inputs(spec))
    timer = Timer()
    stages = prepare(spec, timer, progress)
    check_plate(spec, stages["tiling"], stages["fmap"])
    jobs = jobs or os.cpu_count() or 1
    joints = stages["joints"]
    tolerance = spec.output.tolerance
    mesh_report, sampling = None, None

    state = {}

    def finish(pieces, joints, expected):
        """Print orientations, labels (off the bed side), base cuts, the float32 form the files store, and the
        build's own checks on exactly that."""
        with timer("layout", progress):
            poses = plan_poses(pieces, joints)
        labels, engraved = {}, 0.0
        if spec.output.labels:
            with timer("label", progress):
                pieces, labels, engraved = label_pieces(stages["tiling"], stages["fmap"], pieces, joints, poses)
        with timer("layout", progress):
            pieces, cut = base_cuts(pieces, poses)
        if spec.output.labels:
            with timer("label", progress):
                pieces, more = bed_labels(pieces, labels, poses)
            engraved += more
        with timer("check", progress):
            pieces = printable(pieces)
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
        if clearance > 0:
            # Fragments of a cage cell are merged into the neighbour they touch and joints are kept inside two
            # touching cells: both need the cut faces closed, so the clearance would have to come after them.
            print(f"warning: output.face_clearance: not applied to a mesh model yet (got {clearance:g} mm, the cut "
                  f"faces meet)", file=sys.stderr)
            clearance = 0.0
        from .meshcut import compose_in_mesh

        pieces, joints, stages["plan"], mesh_report = compose_in_mesh(stages, spec.joints, tolerance, jobs, timer,
                                                                      progress)
        gaps = sum(gap_volume(j) for j in joints)
        face_gaps = 0.0
        expected = stages["model_report"]["volume_mm3"] - gaps - face_gaps
        pieces, labels, engraved, checks = finish(pieces, joints, expected)
    else:
        from .compose import face_clearance_volume

        gaps = sum(gap_volume(j) for j in joints)
        for attempt in range(3):
            with timer("compose", progress):
                pieces = compose(stages["tiling"], stages["fmap"], joints, tolerance, jobs=jobs,
                                 progress=progress.piece, face_clearance=clearance)
            sampling = pieces.sampling  # the finishing stages return plain lists
            face_gaps = face_clearance_volume(sampling, clearance)
            expected = stages["model_report"]["volume_mm3"] - gaps - face_gaps
            pieces, labels, engraved, checks = finish(pieces, joints, expected)
            deficit_only = (checks["all_closed"] and checks["max_overlap_mm3"] <= checks["overlap_limit_mm3"]
                            and checks["volume_error"] < -0.005)
            if checks["passed"] or not deficit_only or attempt == 2:
                break
            # Chords inside a convex surface lose volume in proportion to the chord error. The user's tolerance is
            # an upper bound, so tessellating finer still honours it while making the volumes add up.
            tolerance *= max(0.2, 0.6 * 0.005 / abs(checks["volume_error"]))
    require_pieces_joined(spec, pieces, joints, stages.get("contacts") or ())
    checks["joint_gaps_mm3"] = round(gaps, 3)
    checks["face_clearance_mm"] = clearance
    checks["face_clearance_mm3"] = round(face_gaps, 3)
    checks["labels_engraved_mm3"] = round(engraved, 3)
    checks["tessellation_tolerance_mm"] = round(tolerance, 6)
    if sampling is not None:
        checks["max_surface_error_mm"] = round(float(sampling.max_error_mm), 6)
    assert_passed(checks)
    for warning in _fit(spec, joints, clearance)["warnings"]:
        print(f"warning: {warning}", file=sys.stderr)
    dowels = dowel_parts(joints) if spec.joints.style == "dowel" else []
    if stages["plan"] is None:  # nothing to replay, and no time to report for it
        assembly = replay_assembly(None, pieces, joints)
    else:
        with timer("assembly", progress):
            assembly = replay_assembly(stages["plan"], pieces, joints, allow=spec.joints.allow,
                                       randomized=spec.randomize is not None)
    colors = piece_colors(len(pieces))
    pins = pin_triangles(pieces, joints)
    texture, texture_report = None, None
    if spec.texture is not None:
        with timer("texture", progress):
            texture, texture_report = build_texture(spec, stages["model"].volume, pieces, tolerance)
    with timer("layout", progress):
        placements, plates, extras = plates_and_preview(spec, pieces, dowels, joints, colors, pins, texture,
                                             state["poses"], assembly.get("steps"))
    ext = spec.output.format
    place_of = {pl.name: pl for pl in placements}
    entries = []
    for p in pieces:
        entry = report_piece_entry(p, f"pieces/{p.id}.{ext}")
        entry["plate"] = place_of[p.id].plate if p.id in place_of else None
        entry["label"] = labels.get(p.id)
        entry["joints"] = piece_joints_report(joints, p.cell)
        entry["print"] = print_entry(p, state["poses"].get(p.id), place_of.get(p.id))
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


def validate(spec_path, allow_large=False):
    """`volpuzzle validate`: the spec, the model and every cross-check, without building. -> summary dict"""
    from .layout import check_plate
    from .spec import load_spec, with_overrides

    spec = with_overrides(load_spec(spec_path), allow_large=allow_large)
    stages = prepare(spec)
    check_plate(spec, stages["tiling"], stages["fmap"])  # build refuses a small plate before meshing: so does this
    clearance = 0.0 if stages["model"].mesh is not None else spec.output.face_clearance  # see build
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
