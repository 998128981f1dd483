"""Where the check and assembly stages spend their time (issue 13): prints figures, asserts nothing.

    .venv/bin/python scripts/bench_checks.py [SPEC] [--repeat N]

Builds SPEC (default specs/twisted-torus.yaml) once in this process, keeping the finished pieces, joints and plan,
then runs on exactly those, each N times: the overlap check (check_pieces), the face-gap check (check._face_gaps),
the pin-in-hole check (check_joints) and the assembly replay (verify_disassembly), with the CPU seconds of each and
of the engine calls inside it (Booleans, min_gap). Last, the engine's unit costs on one pair of neighbours: an
intersection as the pieces lie, one moved by a hair (as check_pieces measures), min_gap, and an intersection with
the neighbours composed into one operand. These say how far fewer Python calls can go: at 32 pieces the stages are
mostly engine time.
"""

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _counting(module, name, counts, seconds):
    """Wrap module.name so that its calls and CPU seconds are added to counts[name], seconds[name]."""
    inner = getattr(module, name)

    def wrapped(*args, **kwargs):
        t = time.process_time()
        try:
            return inner(*args, **kwargs)
        finally:
            counts[name] += 1
            seconds[name] += time.process_time() - t

    setattr(module, name, wrapped)
    return inner


def capture(spec, out):
    """Build spec -> (pieces [(id, trimesh)], joints, plan, report dict), from inside the build."""
    from volpuzzle import assembly, pipeline

    got = {}
    inner = assembly.verify_disassembly

    def keep(pieces, joints, plan, **kwargs):
        got.update(pieces=list(pieces), joints=list(joints), plan=plan)
        return inner(pieces, joints, plan, **kwargs)

    assembly.verify_disassembly = keep
    try:
        report = pipeline.build(spec, output_dir=out, force=True, progress=pipeline.Progress(False))
    finally:
        assembly.verify_disassembly = inner
    return [(p.id, p.mesh) for p in got["pieces"]], got["joints"], got["plan"], report


def unit_costs(meshes, shared, repeat=10):
    """CPU seconds of single engine calls on the first pair of neighbours."""
    import manifold3d

    from volpuzzle.check import piece_solid

    a, b = sorted(sorted(shared, key=sorted)[0])
    sa, sb = piece_solid(meshes[a], a), piece_solid(meshes[b], b)
    others = [piece_solid(meshes[k], k) for pair in shared if a in pair for k in pair if k != a]
    composed = manifold3d.Manifold.compose(others)
    cases = {
        "intersection as they lie": lambda: (sa ^ sb).volume(),
        "intersection, one moved 1e-3 mm": lambda: (sa ^ sb.translate((1e-3, 0.0, 0.0))).volume(),
        "min_gap(search 0.45 mm)": lambda: sa.min_gap(sb, 0.45),
        f"intersection with {len(others)} neighbours composed": lambda: (sa ^ composed).volume(),
        f"{len(others)} intersections one by one": lambda: [(sa ^ o).volume() for o in others],
    }
    print(f"\nengine unit costs ({a} and {b}: {len(meshes[a].faces)} and {len(meshes[b].faces)} triangles), CPU ms:")
    for name, run in cases.items():
        run()
        t = time.process_time()
        for _ in range(repeat):
            run()
        print(f"  {name:<44} {1e3 * (time.process_time() - t) / repeat:8.2f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spec", nargs="?", default=str(REPO / "specs" / "twisted-torus.yaml"))
    ap.add_argument("--repeat", type=int, default=1, help="runs of each stage part (default 1)")
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))
    from volpuzzle import assembly, check, geometry

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        pieces, joints, plan, report = capture(args.spec, str(Path(tmp) / "out"))
        print(f"{args.spec}: {len(pieces)} pieces, built in {time.perf_counter() - t:.1f} s wall; report timings "
              f"check {report['timings_s'].get('check')} s, assembly {report['timings_s'].get('assembly')} s")
    meshes = dict(pieces)
    expected = report["checks"]["expected_volume_mm3"]
    clearance = float(report["checks"].get("face_clearance_mm") or 0.0)
    shared = check._shared_faces(report.get("contacts"))
    counts, seconds = Counter(), Counter()
    _counting(check, "overlap_volume", counts, seconds)
    _counting(assembly, "_overlap", counts, seconds)
    _counting(geometry, "manifold_from_mesh", counts, seconds)
    parts = {
        "check_pieces (overlaps)": lambda: check.check_pieces(pieces, expected),
        "_face_gaps (one min_gap per neighbour pair)": lambda: check._face_gaps(meshes, clearance, shared),
        "check_joints (pins in holes)": lambda: check.check_joints(meshes, report.get("joints") or []),
        "verify_disassembly (replay)": lambda: assembly.verify_disassembly(dict(pieces), joints, plan),
    }
    print(f"\n{'part':<42} {'CPU s':>7}   engine calls inside (CPU s)")
    for name, run in parts.items():
        counts.clear()
        seconds.clear()
        t = time.process_time()
        for _ in range(args.repeat):
            run()
        cpu = (time.process_time() - t) / args.repeat
        inside = ", ".join(f"{k} x{counts[k] // args.repeat} ({seconds[k] / args.repeat:.2f})" for k in sorted(counts))
        print(f"{name:<42} {cpu:7.2f}   {inside}")
    if shared:
        unit_costs(meshes, shared)


if __name__ == "__main__":
    main()
