"""The compiling child of a first build (volpuzzle.precompile): its signatures are the ones a build calls with, so a
build after it loads each of its kernels from numba's cache; it starts only when the cache lacks one of them, on more
than one core, and a child that cannot start is no error."""

import json
import os
import subprocess
import sys

import pytest
from conftest import REPO
from helpers_build import example_spec

from volpuzzle import precompile, workers
from volpuzzle.pipeline import build


def _builds_only_declared_signatures(spec) -> set:
    """Build spec -> the names of the kernels first compiled by it, having checked that every kernel of KERNELS was
    only ever compiled in this process for its declared types."""
    before = {name: set(precompile.kernel(m, name).signatures) for m, name, _ in precompile.KERNELS}
    build(spec, jobs=1)
    for module, name, signature in precompile.KERNELS:
        # nothing else: a kernel compiled for other types than declared would be compiled again by the build
        assert set(precompile.kernel(module, name).signatures) <= {precompile.argument_types(signature)}, name
    return {name for m, name, _ in precompile.KERNELS if set(precompile.kernel(m, name).signatures) - before[name]}


def test_the_declared_signatures_are_the_ones_a_build_calls_with(tmp_path, monkeypatch):
    # the check's and the replay's kernels are used from 256 pieces on (or once ready): here on the quarter torus's 8
    from volpuzzle import assembly, check

    monkeypatch.setattr(check, "_SHORTCUT_MIN_PIECES", 1)
    monkeypatch.setattr(assembly, "_KERNEL_MIN_PIECES", 1)
    _builds_only_declared_signatures(example_spec("quarter-torus", tmp_path, tolerance=0.5))
    for module, name, signature in precompile.KERNELS:  # the quarter torus calls every one
        assert precompile.argument_types(signature) in precompile.kernel(module, name).signatures, name


# A kernel called with other argument types by the build than by the child is compiled by both at once, and numba's
# cache index, rewritten without a lock, could then file one's machine code under the other's signature: every kind
# of model (a mesh in a cage, a shell) must call with the declared types too
@pytest.mark.slow
@pytest.mark.parametrize("name", ["bunny-cage", "duck"])
def test_mesh_and_shell_builds_call_with_the_declared_signatures(tmp_path, name):
    _builds_only_declared_signatures(example_spec(name, tmp_path, tolerance=0.2))


def test_no_child_when_the_cache_holds_every_kernel(monkeypatch):
    monkeypatch.setattr(precompile, "_CHILD", None)
    monkeypatch.setattr(workers, "usable_cores", lambda: 2)
    monkeypatch.setattr(precompile, "missing", lambda: False)
    assert precompile.start() is None


def test_no_child_on_one_core(monkeypatch):
    monkeypatch.setattr(precompile, "_CHILD", None)
    monkeypatch.setattr(workers, "usable_cores", lambda: 1)
    monkeypatch.setattr(precompile, "missing", lambda: True)
    assert precompile.start() is None


def test_no_child_when_one_process_is_asked_for(monkeypatch):
    # --jobs 1 (and every build of `volpuzzle batch`, whose cluster spreads the work) keeps to one process
    monkeypatch.setattr(precompile, "_CHILD", None)
    monkeypatch.setattr(workers, "usable_cores", lambda: 2)
    monkeypatch.setattr(precompile, "missing", lambda: True)
    started = []
    monkeypatch.setattr(precompile.subprocess, "Popen", lambda *a, **_: started.append(a) or "a child")
    assert precompile.start(1) is None and not started
    assert precompile.start(2) is not None and len(started) == 1


def test_a_child_that_cannot_start_is_no_error(monkeypatch, tmp_path):
    monkeypatch.setattr(precompile, "_CHILD", None)
    monkeypatch.setattr(workers, "usable_cores", lambda: 2)
    monkeypatch.setattr(precompile, "missing", lambda: True)
    monkeypatch.setattr(sys, "executable", str(tmp_path / "no-such-python"))
    assert precompile.start() is None
    assert precompile.join(0) is None


_CHILD_FILLS_THE_CACHE = """
from volpuzzle import precompile
assert precompile.missing()
child = precompile.start()
assert child is not None
assert precompile.join(300) == 0
assert not precompile.missing()
assert precompile.start() is None
"""

_BUILD_AND_COUNT = """
import json, sys
from volpuzzle import precompile
from volpuzzle.pipeline import build
build(sys.argv[1], jobs=1)
print(json.dumps({name: [sum(precompile.kernel(m, name).stats.cache_hits.values()),
                         sum(precompile.kernel(m, name).stats.cache_misses.values())]
                  for m, name, _ in precompile.KERNELS}))
"""


@pytest.mark.slow
def test_a_build_after_the_child_compiles_none_of_its_kernels(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"), PYTHONPATH=str(REPO))
    subprocess.run([sys.executable, "-c", _CHILD_FILLS_THE_CACHE], env=env, check=True, timeout=300)
    spec = example_spec("quarter-torus", tmp_path, tolerance=0.5)
    out = subprocess.run([sys.executable, "-c", _BUILD_AND_COUNT, str(spec)], env=env, check=True, timeout=300,
                         capture_output=True, text=True).stdout
    counts = json.loads(out.strip().splitlines()[-1])
    # each loaded once, none compiled; the face gaps' kernel only from 256 pieces on, whether cached or not (the
    # figures of a folder then do not depend on the machine's cache)
    assert counts == {name: [0, 0] if name == "surface_gap" else [1, 0] for _, name, _ in precompile.KERNELS}


_READY = """
import sys
from volpuzzle import precompile
from volpuzzle._check_kernels import cylinder_side
before = precompile.ready(cylinder_side)
if sys.argv[1] == "compile":
    sig = [s for m, n, s in precompile.KERNELS if n == "cylinder_side"][0]
    cylinder_side.compile(precompile.argument_types(sig))
print(before, precompile.ready(cylinder_side))
"""


def test_a_kernel_is_ready_once_compiled_or_in_the_cache(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"), PYTHONPATH=str(REPO))

    def ready(step):
        out = subprocess.run([sys.executable, "-c", _READY, step], env=env, check=True, timeout=300,
                             capture_output=True, text=True).stdout
        return out.split()

    assert ready("compile") == ["False", "True"]  # a new machine: not until compiled here
    assert ready("look") == ["True", "True"]  # the next process finds it in the cache
