"""Build benchmark: builds specs/twisted-torus.yaml (and the bunny when its spec exists) and prints per-stage times,
triangles, output size and peak memory, and the joint figures (touching pairs, those with room, pinned, pieces
without a joint, joint-graph parts, largest/smallest piece volume). Prints figures; asserts nothing.

Targets on a 2-core machine: twisted torus <= 10 s wall and <= 1.5 GB peak for the whole build.
"""

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import volpuzzle  # noqa: E402


def folder_size(path):
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


def bench(spec, jobs):
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        t0 = time.perf_counter()
        report = volpuzzle.build(spec, output_dir=out, jobs=jobs, force=True)
        wall = time.perf_counter() - t0
        size = folder_size(out)
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    print(f"== {Path(spec).name}: {len(report['pieces'])} pieces, jobs={jobs}")
    print(f"wall             {wall:8.2f} s")
    for stage, t in report["timings_s"].items():
        print(f"  {stage:<14} {t:8.3f} s")
    print(f"triangles        {sum(p['triangles'] for p in report['pieces']):8d}")
    print(f"output size      {size / 1e6:8.2f} MB")
    print(f"peak memory      {max(self_kb, child_kb) / 1024:8.0f} MB (largest process; main {self_kb / 1024:.0f} MB,"
          f" largest worker {child_kb / 1024:.0f} MB)")
    print(f"volume error     {report['checks']['volume_error']:8.2e}")
    print_joint_figures(report)


def print_joint_figures(report):
    """The puzzle's joint figures (volpuzzle.joint.report_figures): does it hold together, and how well pinned."""
    from volpuzzle.joint import report_figures

    fig = report_figures(report)

    def show(x):
        return "-" if x is None else str(x)

    share = ""
    if fig["with_room"]:
        share = f" ({100.0 * fig['pinned_with_room'] / fig['with_room']:.0f}% of those with room)"
    print(f"touching pairs   {show(fig['touching_pairs']):>8}")
    print(f"  with room      {show(fig['with_room']):>8}")
    print(f"  pinned         {show(fig['pinned']):>8}{share}")
    loose = fig["pieces_without_joint"]
    print(f"without a joint  {len(loose):8d}" + (f" ({', '.join(loose[:6])})" if loose else ""))
    print(f"joint-graph parts{fig['parts']:8d}")
    if fig["largest_volume_mm3"] is not None:
        ratio = fig["largest_volume_mm3"] / max(fig["smallest_volume_mm3"], 1e-12)
        print(f"piece volume     {fig['largest_volume_mm3']:8.0f} to {fig['smallest_volume_mm3']:.0f} mm^3 "
              f"(largest/smallest {ratio:.1f})")


def machine_probe():
    """Seconds for a fixed pure-Python loop: this sandbox's speed drifts by up to ~40% between runs, so the build
    figures are printed next to it."""
    t = time.perf_counter()
    s = 0
    for i in range(5_000_000):
        s += i
    return time.perf_counter() - t


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--jobs", type=int, default=None)
    parser.add_argument("specs", nargs="*")
    args = parser.parse_args()
    specs = args.specs or [str(REPO / "specs" / "twisted-torus.yaml")]
    bunny = REPO / "specs" / "bunny-cage.yaml"
    if not args.specs and bunny.exists():
        specs.append(str(bunny))
    print(f"machine probe    {machine_probe():8.3f} s (a fixed Python loop; larger means a slower machine right now)")
    for spec in specs:
        try:
            bench(spec, args.jobs)
        except volpuzzle.VolpuzzleError as e:  # one failed example must not hide the others' figures
            print(f"== {Path(spec).name}: the build failed: {e}")


if __name__ == "__main__":
    main()
