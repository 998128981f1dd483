"""Compile the later stages' kernels ahead, in a second process, when numba's cache does not hold them yet.

numba compiles a kernel at its first call and keeps it in its on-disk cache (`cache=True`). A first build on a new
machine therefore compiles every kernel in turn on the way, ~3 s of it for the kernels the joint, label, check, assembly
and preview stages first call several seconds in. When their cache files are missing, build() starts this module as a
child process: it compiles those kernels from the signatures declared below and writes them to the same cache, on the
other core, while the build loads, verifies and composes; each stage then loads its kernel from the cache instead of
compiling it. A child that is late or fails changes nothing but time: the stage compiles the kernel itself, as it always
did. numba writes its cache files whole (a temporary file, then a rename), so two processes compiling the same kernel
both leave a good one.

The signatures are the argument types the stages pass (C-contiguous arrays, 64-bit scalars); a test checks them
against what a build really compiles, since a kernel compiled for other types would only be compiled again.
"""

import os
import subprocess
import sys
from pathlib import Path

# (module, kernel, signature) in the order a build first calls them
KERNELS = (
    ("volpuzzle._joint_kernels", "face_distance",
     "(float64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], boolean[:, ::1], boolean[::1])"),
    ("volpuzzle._joint_kernels", "cylinders_apart",
     "(float64[:, ::1], float64[:, ::1], float64, float64[:, ::1], float64[:, ::1], float64[::1], float64)"),
    ("volpuzzle.label", "_refined",
     "(float64[::1], float64[:, ::1], float64, int64[:, ::1], float64[:, ::1], float64[::1], float64[::1], "
     "float64[::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[::1], float64[::1], float64[::1], "
     "float64)"),
    ("volpuzzle._check_kernels", "cylinder_side",
     "(float64[:, ::1], int64[:, ::1], float64[::1], float64[::1], float64[::1], float64[::1], float64, float64, "
     "float64, float64)"),
    ("volpuzzle._assembly_kernels", "parts_meet",
     "(float64[:, :, ::1], float64[:, :, ::1], float64[::1], float64[::1], boolean[::1])"),
    ("volpuzzle.preview", "_scan",
     "(float64[:, ::1], float64[:, ::1], float64[:, ::1], int64[::1], float64[:, ::1], boolean[::1], float64, "
     "float64, float64, int64, int64, float64, float64, int64, int64[::1])"),
    ("volpuzzle.preview", "_shade",
     "(int64[:, ::1], float64[:, :, ::1], int64[::1], int64[::1], float64, uint8[:, :, ::1], int64, int64)"),
    # last: ~8 s to compile surface_gap with its helpers, ~1.5 s more for surfaces_meet on the same helpers, and a
    # first build uses them only from 256 pieces on (check._face_gaps, assembly._use_kernel)
    ("volpuzzle._check_kernels", "surface_gap",
     "(float64[:, ::1], int64[:, ::1], float64[:, ::1], int64[:, ::1], float64[::1], float64, float64)"),
    ("volpuzzle._check_kernels", "surfaces_meet",
     "(float64[:, ::1], int64[:, ::1], float64[:, ::1], int64[:, ::1], float64[:, ::1], float64)"),
)

_CHILD = None  # the running child, so that one build at a time starts one


def kernel(module, name):
    """The numba dispatcher `name` of `module` (imported)."""
    import importlib

    return getattr(importlib.import_module(module), name)


def missing() -> bool:
    """Whether numba's cache lacks the index of any kernel in KERNELS (a new machine, or a new cache folder). An index
    that is there but stale (its source edited since) counts as present: the stage then compiles, as it always did."""
    try:
        return any(not _indexed(kernel(m, n)) for m, n, _ in KERNELS)
    except Exception:  # noqa: BLE001 - numba's cache internals differ between versions: then never start a child
        return False


def ready(dispatcher) -> bool:
    """Whether calling a kernel costs no compiling: compiled in this process already, or in numba's cache (its index
    there; a stale one counts too, as in missing). For a stage that may do without it on a new machine."""
    try:
        return bool(dispatcher.signatures) or _indexed(dispatcher)
    except Exception:  # noqa: BLE001 - numba's cache internals differ between versions: then say it is not
        return False


def usable(module, name) -> bool:
    """Whether a stage may call kernel `name` of `module` without paying to start numba or compile: numba loaded
    already (as in a build) and the kernel ready. A first build of a few pieces on a new machine, or `volpuzzle check`
    of a small folder, does the work without it instead."""
    return "numba" in sys.modules and ready(kernel(module, name))


def _indexed(dispatcher) -> bool:
    return os.path.exists(dispatcher._cache._cache_file._index_path)


def start(jobs: int = 2):
    """Start the child when the cache lacks a kernel, the build may use more than one process (`jobs`, as --jobs
    gives it) and no child of ours is still running -> Popen or None. Nothing it does can fail the build: its output
    goes nowhere and a child that cannot start is simply not there."""
    global _CHILD
    from .workers import usable_cores

    if jobs < 2 or usable_cores() < 2:
        return None  # one process asked for; on one core the child would only take turns with the build
    if (_CHILD is not None and _CHILD.poll() is None) or os.environ.get("NUMBA_DISABLE_JIT") == "1" or not missing():
        return None
    root = str(Path(__file__).resolve().parent.parent)
    try:
        _CHILD = subprocess.Popen(
            [sys.executable, "-c", f"import sys; sys.path.insert(0, {root!r}); from volpuzzle.precompile import main; "
                                   f"main()"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True)
    except OSError:
        _CHILD = None
    return _CHILD


def join(timeout=None) -> int | None:
    """Wait for the child started last (a benchmark counts its CPU time) -> its exit status, or None when there is none
    or it is still running after timeout s."""
    if _CHILD is None:
        return None
    try:
        return _CHILD.wait(timeout)
    except subprocess.TimeoutExpired:
        return None


def main():
    """Compile every kernel of KERNELS for its signature, in order, into numba's cache."""
    for module, name, signature in KERNELS:
        kernel(module, name).compile(argument_types(signature))


def argument_types(signature):
    """A signature of KERNELS -> the tuple of numba types a call with such arguments compiles for. numba files a
    kernel in its cache under the signature as compile() was given it, and a call looks it up by that tuple."""
    from numba.core import sigutils

    return tuple(sigutils.normalize_signature(signature)[0])


if __name__ == "__main__":
    main()
