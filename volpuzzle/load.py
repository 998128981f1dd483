"""The load stage: the model M read from its file, built in, or a shell or a closed mesh in its cage, in mm."""

from dataclasses import dataclass

import numpy as np

from .errors import SpecError
from .progress import warn


@dataclass(frozen=True, eq=False)
class Model:
    """The model M in mm, ready for the stages, and what the report says of it."""

    volume: object  # spline.Volume, control points in mm (the cage, in mesh mode)
    scale: float  # mm per model unit, including `size`
    info: dict
    mesh: object = None  # trimesh.Trimesh in mm, in mesh mode: each piece is finally intersected with it
    bbox: object = None  # (2, 3) mm, the box of `volume` when the loader measured it (to size the model), else None


def _scaled(vol, factor):
    return vol if factor == 1.0 else vol.scaled(factor)


def load_model_for(spec):
    """Read or construct M, scale it to mm (units, then size). -> Model"""
    from .io import load_model_with_meta
    from .spline.measure import bbox

    model_spec = spec.model
    if model_spec.builtin is not None:
        from .models import make_builtin

        vol, meta = make_builtin(model_spec.builtin), {"format": "builtin", "units": "mm"}
    elif model_spec.nurbs is not None:
        vol, meta = load_model_with_meta(model_spec.nurbs, patch=model_spec.patch)
    elif model_spec.shell is not None:
        from .shell import load_shell

        # the thickness is mm of the printed object, so the surface is sized before it is offset
        shell, scale, meta = load_shell(model_spec.shell, model_spec.unit_scale, model_spec.size, spec.output.tolerance)
        return Model(shell.volume, scale, {"format": meta.get("format"), "scale_mm_per_unit": scale,
                                           "shell": shell.info})
    else:
        return _load_mesh_model(spec)
    scale = model_spec.unit_scale
    vol = _scaled(vol, scale)
    box = None
    if model_spec.size is not None:
        lo, hi = bbox(vol)
        largest = float(np.max(np.asarray(hi) - np.asarray(lo)))
        factor = model_spec.size / largest
        vol = _scaled(vol, factor)
        scale *= factor
        # the sized model's box is the measured one scaled (a uniform scale about the origin), so the report need not
        # measure it again (18 bounded searches, ~0.16 CPU s)
        box = np.stack([np.asarray(lo, float), np.asarray(hi, float)]) * factor
    return Model(vol, scale, {"format": meta.get("format"), "scale_mm_per_unit": scale}, bbox=box)


def _load_mesh_model(spec):
    """A closed mesh in mm and the cage fitted around it (paper section 5)."""
    import sys

    from .cage import check_inside, make_cage
    from .io.mesh import load_mesh_scaled, simplify_dense

    model_spec = spec.model
    if spec.joints.space == "domain" and spec.joints.style != "none":
        raise SpecError("joints.space: pins built in the domain are not supported with a mesh model "
                        "(got domain, expected physical)", source=spec.source)
    mesh, scale = load_mesh_scaled(model_spec.mesh, unit_scale=model_spec.unit_scale, size=model_spec.size,
                                   repair=model_spec.repair)
    # a quarter of the tolerance: the cut faces' chords and the float32 files take their share of it too
    mesh, simplified = simplify_dense(mesh, spec.output.tolerance / 4)
    if simplified:
        print(f"note: model.mesh: {simplified['triangles_in']:,} triangles simplified to {simplified['triangles']:,}, "
              f"within {simplified['max_deviation_mm']:.3g} mm of the original (a quarter of output.tolerance "
              f"{spec.output.tolerance:g} mm)", file=sys.stderr)
    cage, cage_info = make_cage(mesh, model_spec.cage, scale=scale,
                                balance_grid=spec.grid if "balanced" in spec.splits else None)
    check_inside(mesh, cage)
    info = {"format": "mesh", "scale_mm_per_unit": scale, "mesh_triangles": int(len(mesh.faces)),
            "cage": {k: v for k, v in cage_info.items() if isinstance(v, (int, float, str, list, tuple))}}
    if simplified:
        info["mesh_simplified"] = simplified
    return Model(cage, scale, info, mesh)


def with_closed_axes(spec, model, found=()):
    """The spec with the axes the model closes on itself added to spec.periodic: a shell's closed direction is
    periodic whether or not the spec says so, and so is any volume model's axis whose min and max faces coincide
    (found: those axes, spline.seams.find_seams), with a warning: left unjoined, the pieces either side of the seam
    would touch face to face, with neither a face clearance nor a pin. A mesh's cage is left as its spec says (its
    pieces are joined on their real contacts)."""
    import dataclasses

    from .grid import AXES

    closed = [AXES.index(a) for a in model.info.get("shell", {}).get("closed_axes", [])]
    unlisted = sorted(set(found) - set(spec.periodic) - set(closed)) if model.mesh is None else []
    if unlisted:
        names = ", ".join(AXES[a] for a in unlisted)
        warn(f"periodic: the model closes on itself along {names} (its min and max faces coincide), so "
             f"its pieces are joined across that seam (got periodic {[AXES[a] for a in spec.periodic]}, expected "
             f"{[AXES[a] for a in sorted(set(spec.periodic) | set(unlisted))]}; write it so to silence this)")
    closed = sorted(set(closed) | set(unlisted))
    if not closed:
        return spec
    return dataclasses.replace(spec, periodic=tuple(sorted(set(spec.periodic) | set(closed))))
