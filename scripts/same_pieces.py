"""Do two versions of volpuzzle give byte-identical pieces? A refactoring must say yes for the paper specs.

    python scripts/same_pieces.py                    # all specs/*.yaml, main against the working tree
    python scripts/same_pieces.py --quick            # quarter-torus and twisted-torus only
    python scripts/same_pieces.py --base adc725c specs/quarter-torus.yaml

The base ref is checked out into a temporary git worktree and built from there (its own package on PYTHONPATH,
this checkout's virtualenv for the dependencies); the other side is the current tree as it is on disk, edits
included. Each spec is built by the CLI with the same --jobs on both sides, and the sha256 of every file under
pieces/ and plates/ is compared. Prints one row per file, then a summary; exits 1 on any difference or failed
build, 0 when every file is the same.
"""

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
QUICK = ("specs/quarter-torus.yaml", "specs/twisted-torus.yaml")
COMPARED = ("pieces", "plates")


def _git(*args, cwd=ROOT):
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def build(tree, spec, out, jobs):
    """Build `spec` (a path relative to the tree) with the volpuzzle package of `tree` into `out`. -> error or None"""
    env = dict(os.environ, PYTHONPATH=str(tree), VOLPUZZLE_NO_PROGRESS="1")
    cmd = [sys.executable, "-c", "from volpuzzle.cli import cli; cli()", "build", str(tree / spec), "-o", str(out),
           "--force", "--jobs", str(jobs)]
    run = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    return None if run.returncode == 0 else (run.stderr.strip().splitlines() or [f"exit {run.returncode}"])[-1]


def digests(out):
    """{path relative to out: sha256 hex} of every file under pieces/ and plates/."""
    found = {}
    for sub in COMPARED:
        for path in sorted((out / sub).rglob("*")) if (out / sub).is_dir() else ():
            if path.is_file():
                found[str(path.relative_to(out))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return found


def compare(name, base, head):
    """Rows (spec, file, base sha, head sha, verdict) and the number of differences."""
    rows, bad = [], 0
    for f in sorted(set(base) | set(head)):
        a, b = base.get(f), head.get(f)
        verdict = "same" if a == b else ("missing in head" if b is None else "missing in base" if a is None
                                         else "DIFFERENT")
        bad += verdict != "same"
        rows.append((name, f, (a or "-")[:12], (b or "-")[:12], verdict))
    if not rows:  # no files on either side: nothing was compared, which is no proof of sameness
        rows.append((name, "(no files under pieces/ or plates/)", "-", "-", "NOTHING COMPARED"))
        bad += 1
    return rows, bad


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("specs", nargs="*", help="spec files relative to the repository (default: specs/*.yaml)")
    ap.add_argument("--quick", action="store_true", help="only " + " and ".join(QUICK))
    ap.add_argument("--base", default="main", help="git ref built from a temporary worktree (default: main)")
    ap.add_argument("--jobs", type=int, default=1, help="--jobs of every build, the same on both sides (default 1)")
    args = ap.parse_args(argv)
    specs = args.specs or (list(QUICK) if args.quick else sorted(str(p.relative_to(ROOT))
                                                                  for p in (ROOT / "specs").glob("*.yaml")))
    base_commit = _git("rev-parse", "--short", args.base)
    head_commit = _git("rev-parse", "--short", "HEAD")
    dirty = " (with uncommitted edits)" if _git("status", "--porcelain", "--untracked-files=no") else ""
    print(f"base {args.base} = {base_commit}; head = working tree at {head_commit}{dirty}; jobs {args.jobs}")
    rows, bad = [], 0
    with tempfile.TemporaryDirectory(prefix="same-pieces-") as tmp:
        tmp = Path(tmp)
        base_tree = tmp / "base"
        _git("worktree", "add", "--detach", "--quiet", str(base_tree), args.base)
        try:
            for spec in specs:
                name = Path(spec).stem
                result = {}
                for side, tree in (("base", base_tree), ("head", ROOT)):
                    out = tmp / side / name
                    error = build(tree, spec, out, args.jobs)
                    result[side] = error or digests(out)
                if isinstance(result["base"], str) or isinstance(result["head"], str):
                    for side in ("base", "head"):
                        if isinstance(result[side], str):
                            rows.append((name, f"build failed at {side}: {result[side]}", "-", "-", "FAILED"))
                            bad += 1
                    continue
                more, n = compare(name, result["base"], result["head"])
                rows += more
                bad += n
                print(f"{name}: {len(more)} files, {n} differ", file=sys.stderr, flush=True)
        finally:
            _git("worktree", "remove", "--force", str(base_tree))
    widths = [max(len(str(r[k])) for r in rows + [("spec", "file", "base", "head", "verdict")]) for k in range(5)]
    for r in [("spec", "file", "base", "head", "verdict")] + rows:
        print("  ".join(str(x).ljust(w) for x, w in zip(r, widths, strict=True)).rstrip())
    same = sum(1 for r in rows if r[4] == "same")
    print(f"{same} of {len(rows)} files byte-identical" + ("" if bad == 0 else f"; {bad} differ or failed"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
