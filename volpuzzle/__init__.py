"""volpuzzle: turn a freeform volumetric model into a 3D-printable volumetric puzzle.

After G. Elber, "On the Construction of Freeform Volumetric 3D Puzzles", Modelling 2025, 6(3), 90.
"""

__version__ = "0.1.0"

from .errors import ExportError, GeometryError, ModelError, SpecError, VolpuzzleError  # noqa: E402


def load_model(path, patch=0):
    """Read a trivariate model in any supported format (SPEC section 2) -> Volume."""
    from .io import load_model as _load

    return _load(path, patch=patch)


def build(spec_path, output_dir=None, **options):
    """Run the whole pipeline as `volpuzzle build` does; returns the report as a dict."""
    from .pipeline import build as _build

    return _build(spec_path, output_dir=output_dir, **options)


__all__ = ["load_model", "build", "VolpuzzleError", "SpecError", "ModelError", "GeometryError", "ExportError",
           "__version__"]
