"""The build's report: what report.json holds (and report.md, export.render_report_md, renders from it).

Assembled from the stage results once every stage has run; the keys are the outside contract (SPEC.md), so a new
figure goes into the section it belongs to rather than into a new top-level key.
"""

import numpy as np

from . import __version__
from .errors import GeometryError
from .grid import AXES


def model_report(model, model_check, seams_found):
    """report.json "model": volume, bounding box, handedness and notes of the model, the closed axes found and what
    the loader said of it. model: load.Model; model_check: verify.verify_model's dict; seams_found: {axis: seam}."""
    from .spline.measure import bbox
    from .spline.measure import volume as volume_of

    if model.mesh is not None:
        lo, hi = model.mesh.bounds
        model_volume = float(model.mesh.volume)
    else:
        lo, hi = model.bbox if model.bbox is not None else bbox(model.volume)
        model_volume = float(volume_of(model.volume))
    return {
        "volume_mm3": model_volume,
        "bbox_mm": [np.round(lo, 4).tolist(), np.round(hi, 4).tolist()],
        "handedness": model_check["handedness"],
        "degenerate": bool(model_check.get("degenerate", False)),
        "notes": list(model_check.get("notes", [])),
        "periodic_axes_found": [AXES[a] for a in sorted(seams_found)],
        **model.info,
    }


def randomize_report(rand, certificate=None):
    """report.json "randomize": the spec's seed, amplitude and control points with verify_warp's certificate; the
    identity when rand is None or its amplitude is 0."""
    if certificate is None:
        return {"seed": None, "amplitude": 0.0, "jacobian_min_coefficient": None, "bijective": True}
    return {"seed": rand.seed, "amplitude": rand.amplitude, "control_points": rand.control_points, **certificate}


def fit(spec, joints, face_clearance):
    """Pin size and fit of the planned joints (the thinnest and shortest, when the joint stage sized them per
    face) and the face clearance applied, with warnings below the printable minimum (check.pin_fit)."""
    from .check import pin_fit

    j = spec.joints
    if not joints:
        return pin_fit("none", 0.0, 0.0, j.clearance, j.axial_clearance, face_clearance)
    out = pin_fit(j.style, min(float(x.radius) for x in joints), min(float(x.length) for x in joints),
                  max(float(x.clearance) for x in joints), max(float(x.axial_clearance) for x in joints),
                  face_clearance)
    # a size the user wrote and did not get is said, not only left in each joint's "shrunk" flag
    shrunk = [x for x in joints if (j.radius is not None and float(x.radius) < j.radius)
              or (j.length is not None and float(x.length) < j.length)]
    if shrunk:
        out["shrunk"] = {"joints": len(shrunk), "of": len(joints), "asked_radius_mm": j.radius,
                         "asked_length_mm": j.length}
    return out


def piece_entries(stages, placements, ext):
    """report.json "pieces": one entry per piece with its file, plate, label, joints and print pose."""
    from .export import report_piece_entry
    from .joint import cell_joints, piece_joints_report
    from .layout import print_entry

    place_of = {pl.name: pl for pl in placements}
    entries = []
    touching = cell_joints(stages.joints)
    for p in stages.pieces:
        entry = report_piece_entry(p, f"pieces/{p.id}.{ext}")
        entry["plate"] = place_of[p.id].plate if p.id in place_of else None
        entry["label"] = stages.labels.get(p.id)
        entry["joints"] = piece_joints_report(touching.get(tuple(p.cell), ()), p.cell)
        entry["print"] = print_entry(p, stages.poses.get(p.id), place_of.get(p.id))
        entries.append(entry)
    return entries


def require_bed_contact(spec, entries, poses):
    """`volpuzzle check` would refuse a folder with a piece that barely touches its bed: so does the build, before
    writing it. Raises GeometryError naming the pieces."""
    from .check import BED_MIN_MM2, bed_contact_problem

    under = [e["id"] for e in entries if e["print"] and e["print"]["bed_contact_mm2"] < BED_MIN_MM2]
    if under:
        raise GeometryError(f"{spec.name}: {bed_contact_problem(under)} even with a base cut of "
                            f"{max(poses[pid].base_cut_mm for pid in under):g} mm (expected at least "
                            f"{BED_MIN_MM2:g} mm^2 each; try another grid or randomize.seed)")


def build_report(spec, stages, assembly, placements, plates, texture_report, timings):
    """The report dict of a build (report.json), without checks.printability (judged on it, see require_printable).
    stages: pipeline.Stages after compose; assembly: assembly.replay_assembly's dict; timings: Timer.timings, the
    same dict, so that the export stage's time still lands in it."""
    from .spec import spec_to_dict

    entries = piece_entries(stages, placements, spec.output.format)
    require_bed_contact(spec, entries, stages.poses)
    assembly = dict(assembly)
    pictures = [f"steps/step-{n:02d}.png" for n in range(1, len(assembly["steps"]) + 1)]
    report = {
        "volpuzzle_version": __version__,
        "spec": spec_to_dict(spec),
        "model": stages.model_report,
        "randomize": stages.randomize_report,
        "pieces": entries,
        "joints": [j.to_report() for j in stages.joints],
        "contacts": stages.contacts,
        "checks": stages.checks,
        "fit": fit(spec, stages.joints, stages.face_clearance),
        "plates": [{"file": pl.file, "pieces": list(pl.names), "fill_ratio": pl.fill_ratio} for pl in plates],
        "assembly_order": assembly.pop("assembly_order"),
        "assembly": dict(assembly, pictures=pictures),
        "timings_s": timings,
    }
    if stages.mesh_report is not None:
        report["mesh"] = stages.mesh_report
    if texture_report is not None:
        report["texture"] = texture_report
    return report


def require_printable(spec, report):
    """A build never passes what its own check refuses: raise GeometryError with report.checks.printability's
    failures, all on one line."""
    failures = report["checks"]["printability"]["failures"]
    if failures:
        raise GeometryError(f"{spec.name}: not printable as laid out: {'; '.join(failures)}")
