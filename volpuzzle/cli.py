"""The command line. The only module that imports click."""

import json
import math
import os
import signal
import sys
import traceback

import click

from . import __version__, stop
from .errors import VolpuzzleError, one_line
from .progress import end_line, warn


def _run(func, *args, **kwargs):
    """func(*args, **kwargs), where expected failures become one line on stderr and exit 1, a stop "interrupted" or
    "terminated", and a bug one line too (VOLPUZZLE_DEBUG=1 for more). A command imports the stage modules inside
    func: a Ctrl-C during those imports (half a second) is then a stop like any other, not a traceback."""
    previous = stop.install()
    try:
        return func(*args, **kwargs)
    except VolpuzzleError as e:
        end_line()  # the message on a line of its own, not after a progress line
        click.echo(f"error: {one_line(e)}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        end_line()
        click.echo("interrupted", err=True)
        sys.exit(130)
    except stop.Terminated:
        end_line()
        click.echo("terminated", err=True)
        sys.exit(128 + signal.SIGTERM)
    except MemoryError:
        end_line()
        click.echo("error: out of memory (the machine has too little for this model, grid and tolerance; try a "
                   "coarser output.tolerance or a smaller grid)", err=True)
        sys.exit(1)
    except Exception as e:  # noqa: BLE001 - the user must never see a bare traceback
        end_line()
        if os.environ.get("VOLPUZZLE_DEBUG"):
            traceback.print_exc()
        click.echo(f"internal error: {type(e).__name__}: {one_line(e)} (please report it; set VOLPUZZLE_DEBUG=1 for "
                   f"details)", err=True)
        sys.exit(2)
    finally:
        stop.restore(previous)


@click.group()
@click.version_option(__version__, prog_name="volpuzzle")
def cli():
    """Turn a freeform volumetric model into a 3D-printable volumetric puzzle."""


@cli.command()
@click.argument("spec", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output_dir", type=click.Path(file_okay=False),
              help="Output folder (default: out/<name>).")
@click.option("--format", "fmt", type=click.Choice(["stl", "3mf"]), help="File format of the pieces.")
@click.option("--seed", type=int, help="Override randomize.seed.")
@click.option("--jobs", type=click.IntRange(min=1), help="Pieces built in parallel (default: the number of cores).")
@click.option("--force", is_flag=True, help="Replace an existing output folder that volpuzzle wrote.")
@click.option("--allow-large", is_flag=True, help="Lift the resource limits (pieces, triangles, control points).")
def build(spec, output_dir, fmt, seed, jobs, force, allow_large):
    """Run the whole pipeline and write the output folder."""
    def run():
        from .pipeline import build as run_build

        return run_build(spec, output_dir=output_dir, fmt=fmt, seed=seed, jobs=jobs, force=force,
                         allow_large=allow_large)

    report = _run(run)
    checks = report["checks"]
    click.echo(f"built {len(report['pieces'])} pieces, {len(report['joints'])} joints in "
               f"{report['timings_s'].get('total', 0):.1f} s -> {report['spec']['output']['directory']} "
               f"(volume error {checks['volume_error']:.3%}, max overlap {checks['max_overlap_mm3']:.3g} mm^3)")
    _leave_at_once()


@cli.command()
@click.argument("spec", type=click.Path(dir_okay=False))
@click.option("--allow-large", is_flag=True, help="Lift the resource limits (pieces, triangles, control points).")
def validate(spec, allow_large):
    """Check the spec and the model without building."""
    def run():
        from .pipeline import validate as run_validate

        return run_validate(spec, allow_large=allow_large)

    summary = _run(run)
    click.echo(f"{spec}: valid — {summary['pieces']} pieces, {summary['joints']} joints, model "
               f"{summary['model']['volume_mm3']:.6g} mm^3, {summary['model']['handedness']}-handed")
    if summary.get("fit"):
        from .check import fit_line

        click.echo(f"fit: {fit_line(summary['fit'])}")
        for warning in summary["fit"]["warnings"]:
            warn(warning)


@cli.command()
@click.argument("model", type=click.Path(dir_okay=False))
@click.option("--patch", type=int, default=0, show_default=True, help="Patch of a multi-patch file.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def info(model, patch, as_json):
    """Degrees, control points, knots, periodic axes, bounding box, volume, Jacobian range."""
    def run():
        from .info import model_info
        from .io import load_model

        return model_info(load_model(model, patch=patch), path=model, patch=patch)

    data = _run(run)
    from .info import format_info

    # JSON has no Infinity or NaN: a figure that is not finite is null
    click.echo(json.dumps(_finite(data), allow_nan=False) if as_json else format_info(data))


def _finite(x):
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


@cli.command()
@click.argument("directory", type=click.Path(file_okay=False))
def check(directory):
    """Verify a built puzzle from its files alone."""
    def run():
        from .check import check_directory

        return check_directory(directory)

    result = _run(run)
    click.echo(f"{directory}: all checks hold ({result.get('summary', '')})")
    for warning in (result.get("printability") or {}).get("warnings", []):
        warn(warning)


@cli.command()
@click.argument("specs", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output_root", type=click.Path(file_okay=False),
              help="Parent folder: each spec is built into DIR/<name> (default: each spec's own folder).")
@click.option("--jobs", type=click.IntRange(min=1), help="Worker processes of the local cluster (default: cores).")
@click.option("--scheduler", envvar="DASK_SCHEDULER_ADDRESS", help="A running Dask scheduler to build on.")
@click.option("--force", is_flag=True, help="Replace existing output folders.")
def batch(specs, output_root, jobs, scheduler, force):
    """Build many specs on a Dask cluster; a failed spec does not stop the others."""
    def run():
        from .batch import run_batch, terminal_progress

        return run_batch(list(specs), output_root=output_root, jobs=jobs, scheduler=scheduler, force=force,
                         progress=terminal_progress())

    results = _run(run)
    from .batch import summary_table

    click.echo(summary_table(results))
    if not all(r.ok for r in results):
        sys.exit(1)


_ENTRY = []  # set by main(): this process is the `volpuzzle` command itself, not a caller of `cli` (tests, scripts)


def _leave_at_once():
    """After a finished build, as the command: exit without the interpreter's teardown of the build's heap and
    libraries (numba, manifold3d, trimesh: 0.5-1.4 s wall measured on a busy 2-core machine, with nothing left to
    do). The output is in place, the workers ended (pipeline.build closes the pool) and every file closed."""
    if not _ENTRY:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def main():
    _ENTRY.append(True)
    cli(prog_name="volpuzzle")


if __name__ == "__main__":
    main()
