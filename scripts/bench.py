"""Build benchmark: builds specs/twisted-torus.yaml (and the bunny when its spec exists) and prints per-stage times,
triangles, output size and peak memory. Prints figures; asserts nothing.

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
        bench(spec, args.jobs)


if __name__ == "__main__":
    main()
