"""Small specs for end-to-end tests: write a YAML spec into a temporary folder."""

from pathlib import Path

import yaml
from conftest import REPO


def write_spec(tmp_path: Path, spec: dict, name="spec.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def example_spec(name, tmp_path, tolerance=1.0, grid=None, **overrides):
    """specs/NAME.yaml made coarse: absolute model paths, the output folder in tmp_path."""
    spec = yaml.safe_load((REPO / "specs" / f"{name}.yaml").read_text())
    model = spec["model"]
    for key in ("nurbs", "mesh"):
        if key in model:
            model[key] = str((REPO / "specs" / model[key]).resolve())
    if isinstance(model.get("cage"), dict) and "nurbs" in model["cage"]:
        model["cage"]["nurbs"] = str((REPO / "specs" / model["cage"]["nurbs"]).resolve())
    if isinstance(model.get("shell"), dict):
        model["shell"]["surface"] = str((REPO / "specs" / model["shell"]["surface"]).resolve())
    if isinstance(spec.get("texture"), dict):
        spec["texture"]["image"] = str((REPO / "specs" / spec["texture"]["image"]).resolve())
    spec.setdefault("output", {})["tolerance"] = tolerance
    spec["output"]["directory"] = str(tmp_path / "out" / name)
    if grid is not None:
        spec["grid"] = grid
    spec.update(overrides)
    return write_spec(tmp_path, spec, f"{name}.yaml")
