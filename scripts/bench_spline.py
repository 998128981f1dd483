"""Throughput of the spline kernel: scattered and tensor-grid evaluation, and Jacobian certification.

Cubic 8x8x8 random (seeded) volume, 1e6 random scattered points. Prints figures; asserts nothing.
Run: python3 scripts/bench_spline.py [--rational]
"""

import argparse
import os
import statistics
import time

import numpy as np

from volpuzzle.spline import Volume
from volpuzzle.spline.jacobian import certify_positive


def best(fn, repeat=5):
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts), statistics.median(ts)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rational", action="store_true")
    ap.add_argument("--points", type=int, default=1_000_000)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    knots = [np.r_[[0.0] * 4, np.sort(rng.uniform(0, 1, 4)), [1.0] * 4] for _ in range(3)]
    grid = np.stack(np.meshgrid(*[np.linspace(0, 1, 8)] * 3, indexing="ij"), axis=-1)
    weights = rng.uniform(0.5, 2.0, (8, 8, 8)) if args.rational else None
    vol = Volume((3, 3, 3), knots, grid + 0.01 * rng.normal(size=grid.shape), weights)
    uvw = rng.random((args.points, 3))

    t = time.perf_counter()
    vol.evaluate(uvw[:10_000])
    vol.evaluate_with_derivatives(uvw[:10_000])
    vol.evaluate(uvw[:10])
    vol.evaluate_with_derivatives(uvw[:10])
    print(f"first calls (load or compile of the kernels): {time.perf_counter() - t:.2f} s")
    print(f"load average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (figures below are wall clock)")
    kind = "rational" if args.rational else "polynomial"
    n = args.points
    b, m = best(lambda: vol.evaluate(uvw))
    print(f"scattered value-only ({kind}, cubic 8^3, {n} pts): {n / b / 1e6:.2f} M pts/s (median {n / m / 1e6:.2f})")
    b, m = best(lambda: vol.evaluate_with_derivatives(uvw))
    print(f"scattered value + 3 partials:                   {n / b / 1e6:.2f} M pts/s (median {n / m / 1e6:.2f})")
    b, m = best(lambda: vol._project(*vol._numpy_sums(uvw[:100_000], True)), repeat=2)
    print(f"  (numpy reference path, value + partials:       {1e5 / b / 1e6:.2f} M pts/s)")
    from volpuzzle.spline import _fast
    for want, label in ((False, "value-only"), (True, "value + partials")):
        c = time.process_time()
        fn = _fast.kernel(vol.degrees, want)
        fn(uvw, 0, n, *vol._tables.as_args(), *vol.degrees, vol._knet,
           np.empty((n, vol._knet.shape[3])), np.empty((n, vol._knet.shape[3], 3)),
           np.empty(0) if vol._knet.shape[3] == 3 else np.empty((0, 0)))
        print(f"  serial kernel, CPU time, {label}: {n / (time.process_time() - c) / 1e6:.2f} M pts/s per core")
    g = np.linspace(0, 1, 100)
    b, m = best(lambda: vol.evaluate_grid(g, g, g))
    print(f"tensor grid 100^3 value-only:                   {1e6 / b / 1e6:.2f} M pts/s")
    b, m = best(lambda: vol.derivatives_grid(g, g, g))
    print(f"tensor grid 100^3 value + partials:             {1e6 / b / 1e6:.2f} M pts/s")
    certify_positive(vol)
    b, m = best(lambda: certify_positive(vol), repeat=7)
    cert = certify_positive(vol)
    print(f"certify_positive cubic 8^3: median {m * 1e3:.1f} ms (best {b * 1e3:.1f} ms) -> {cert.status}, "
          f"min coefficient {cert.min_coefficient:.3g}")


if __name__ == "__main__":
    main()
