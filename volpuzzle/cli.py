"""The command line. The only module that imports click."""

import json
import os
import sys
import traceback

import click

from . import __version__
from .errors import VolpuzzleError


def _run(func, *args, **kwargs):
    """Expected failures become one line on stderr and exit 1; a bug says so in one line (VOLPUZZLE_DEBUG=1 for more)."""
    try:
        return func(*args, **kwargs)
    except VolpuzzleError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        sys.exit(130)
    except Exception as e:  # noqa: BLE001 - the user must never see a bare traceback
        if os.environ.get("VOLPUZZLE_DEBUG"):
            traceback.print_exc()
        click.echo(f"internal error: {type(e).__name__}: {e} (please report it; set VOLPUZZLE_DEBUG=1 for details)",
                   err=True)
        sys.exit(2)


@click.group()
@click.version_option(__version__, prog_name="volpuzzle")
def cli():
    """Turn a freeform volumetric model into a 3D-printable volumetric puzzle."""


@cli.command()
@click.argument("spec", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output_dir", type=click.Path(file_okay=False), help="Output folder (default: out/<name>).")
@click.option("--format", "fmt", type=click.Choice(["stl", "3mf"]), help="File format of the pieces.")
@click.option("--seed", type=int, help="Override randomize.seed.")
@click.option("--jobs", type=click.IntRange(min=1), help="Pieces built in parallel (default: the number of cores).")
@click.option("--force", is_flag=True, help="Replace an existing output folder.")
def build(spec, output_dir, fmt, seed, jobs, force):
    """Run the whole pipeline and write the output folder."""
    from .pipeline import build as run_build

    report = _run(run_build, spec, output_dir=output_dir, fmt=fmt, seed=seed, jobs=jobs, force=force)
    checks = report["checks"]
    click.echo(f"built {len(report['pieces'])} pieces, {len(report['joints'])} joints in "
               f"{report['timings_s'].get('total', 0):.1f} s -> {report['spec']['output']['directory']} "
               f"(volume error {checks['volume_error']:.3%}, max overlap {checks['max_overlap_mm3']:.3g} mm^3)")


@cli.command()
@click.argument("spec", type=click.Path(dir_okay=False))
def validate(spec):
    """Check the spec and the model without building."""
    from .pipeline import validate as run_validate

    summary = _run(run_validate, spec)
    click.echo(f"{spec}: valid — {summary['pieces']} pieces, {summary['joints']} joints, model "
               f"{summary['model']['volume_mm3']:.6g} mm^3, {summary['model']['handedness']}-handed")
    if summary.get("fit"):
        from .check import fit_line

        click.echo(f"fit: {fit_line(summary['fit'])}")
        for warning in summary["fit"]["warnings"]:
            click.echo(f"warning: {warning}", err=True)


@cli.command()
@click.argument("model", type=click.Path(dir_okay=False))
@click.option("--patch", type=int, default=0, show_default=True, help="Patch of a multi-patch file.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def info(model, patch, as_json):
    """Degrees, control points, knots, periodic axes, bounding box, volume, Jacobian range."""
    from .info import format_info, model_info
    from .io import load_model

    def run():
        return model_info(load_model(model, patch=patch), path=model, patch=patch)

    data = _run(run)
    click.echo(json.dumps(data) if as_json else format_info(data))


@cli.command()
@click.argument("directory", type=click.Path(file_okay=False))
def check(directory):
    """Verify a built puzzle from its files alone."""
    from .check import check_directory

    result = _run(check_directory, directory)
    click.echo(f"{directory}: all checks hold ({result.get('summary', '')})")
    for warning in (result.get("printability") or {}).get("warnings", []):
        click.echo(f"warning: {warning}", err=True)


def main():
    cli(prog_name="volpuzzle")


if __name__ == "__main__":
    main()
