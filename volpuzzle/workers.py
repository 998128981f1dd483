"""One pool of worker processes for a whole build, shared by its per-piece stages (compose, label, ...).

Why one pool, started first. A spawned worker costs ~2.5 s of CPU (a fresh interpreter importing numpy, trimesh,
manifold3d and the stage modules) before it does any work. Started as the build starts, that start-up runs on the
second core while this process imports, loads, verifies and plans the joints (~4 s for the twisted torus), so by
the time the first per-piece stage runs the worker is warm; a pool per stage would pay the start-up again each time,
in the critical path.

Why spawn. manifold3d's and numba's thread pools are running in this process; a forked child would inherit their
locks in whatever state they were (unsafe). Inside a daemonic process (a Dask worker) no pool is started: daemons
may not have children, and the cluster already spreads the work.

How work is shared (map_pieces). This process takes items from the front of the list while the workers take them
from the back, in runs of up to _MOST_PER_TASK items that shrink towards the end, two runs queued each, and only once
a worker has started, so this process never waits for a start-up; a run still queued when the front reaches it is
taken back. Every item goes through the same function wherever it runs, and the results come back in item order, so
where an item ran never changes the result. The big inputs every item needs (`shared`: the tiling, the map, the
joints) are pickled once into a file that each worker reads once (cached by token), not sent with every item.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import hashlib
import itertools
import multiprocessing
import os
import pickle
import shutil
import signal
import tempfile
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from . import stop
from .errors import GeometryError

# A pool pays when the per-piece stages hold enough work to share out: the twisted torus of 32 pieces spends ~9 CPU s
# in compose, label, check, assembly and export, the 8-piece quarter torus ~2 s, less than a worker's start-up.
MIN_PIECES = 16
_MAIN_TAKES_ITEMS = True  # False: the workers run every item (tests use it to see them do so)
_QUEUED_PER_WORKER = 2  # one running, one waiting, so that a worker never idles while this process is busy
# Items per hand-out: a worker is refilled only between this process's own items (and while manifold3d holds the
# GIL, no thread of this process can refill it), so a worker given one small item at a time idles. Rounding 1024
# pieces (~2 ms each) on two processes took 1.31-1.64 s one at a time, 1.16-1.25 s four at a time. Runs shrink
# towards the end of the list, so that the last ones given out are short.
_MOST_PER_TASK = 8
_RUNS_LEFT = 16  # a run is at most this fraction of the items still pending


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the system tells it, else every core)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def wanted(jobs: int | None, pieces: int) -> bool:
    """Whether a build of `pieces` pieces with `jobs` processes starts a pool: more than one job, enough pieces for
    the start-up to pay, and not inside a daemonic process (a Dask worker), which may not start children."""
    if jobs is None or jobs <= 1 or pieces < MIN_PIECES:
        return False
    return not multiprocessing.current_process().daemon


@dataclass(frozen=True)
class _Handle:
    """A shared input as the workers see it: its token and the file that holds it pickled."""

    token: int
    path: str


_CACHE: dict[int, object] = {}  # in a worker: the shared inputs read so far, by token (the last two are kept)
_IN_WORKER = False  # set by _init_worker


@contextlib.contextmanager
def _sigint_blocked():
    """SIGINT blocked in this thread while worker processes are started, which keep the mask: Ctrl-C reaches the whole
    process group, and a worker still importing its modules (before _init_worker) printed a KeyboardInterrupt
    traceback. This process receives a Ctrl-C of those moments once the block ends (or on another thread at once)."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _init_worker():
    # Ctrl-C reaches the whole process group: this process handles it (and ends the workers), a worker would only
    # print a traceback (started with SIGINT blocked, it never sees it where pthread_sigmask exists)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    global _IN_WORKER
    _IN_WORKER = True


def _warm() -> int:
    """The first task of each worker: what compose loads on first use (the first work a build gives a worker),
    done before any item arrives, while this process is still loading and planning. -> pid"""
    import manifold3d  # noqa: F401
    import trimesh  # noqa: F401

    from . import compose  # noqa: F401
    from .spline.volume import Volume

    # numba's one-off set-up, ~0.7 s at the first compiled kernel it loads. A tricubic polynomial cube, as the
    # randomized maps are: its kernel is one the build uses (a trilinear one compiled a version nothing else needed,
    # seconds on an empty cache)
    knots = np.repeat([0.0, 1.0], 4)
    s = np.linspace(0.0, 1.0, 4)
    cube = Volume((3, 3, 3), (knots, knots, knots), np.stack(np.meshgrid(s, s, s, indexing="ij"), axis=-1), None)
    cube.evaluate_with_derivatives(np.full((8, 3), 0.5))
    return os.getpid()


def warm_rest():
    """What the later stages load on first use (matplotlib's text outlines for the labels, ~0.4 s): in a worker,
    queued behind the first work it is given so as not to hold it up; in this process, while it waits for a
    prefetch (Prefetch.result's meanwhile), work it would otherwise do later."""
    from . import assembly, check, export, label, preview  # noqa: F401

    label.min_height_mm("p0-0-0")


def _shared(handle: _Handle | None):
    if handle is None:
        return None
    if handle.token not in _CACHE:
        with open(handle.path, "rb") as f:
            obj = pickle.load(f)
        for old in sorted(_CACHE)[:-1]:  # the stages run one after another: older inputs are done with
            del _CACHE[old]
        _CACHE[handle.token] = obj
    return _CACHE[handle.token]


def _which(ks) -> str:
    """The items of a run (0-based indices), as a message names them: "item 3", "one of items 5-12"."""
    ks = sorted(k + 1 for k in ks)
    if len(ks) == 1:
        return f"item {ks[0]}"
    if ks[-1] - ks[0] == len(ks) - 1:
        return f"one of items {ks[0]}-{ks[-1]}"
    return "one of items " + ", ".join(map(str, ks))


def _run(fn, handle, items):
    shared = _shared(handle)
    return [fn(shared, item) for item in items]


class Workers:
    """jobs - 1 spawned worker processes and this one. Use as a context manager, or call close()."""

    def __init__(self, jobs: int):
        self.size = int(jobs) - 1
        ctx = multiprocessing.get_context("spawn")
        self._executor = concurrent.futures.ProcessPoolExecutor(max_workers=self.size, mp_context=ctx,
                                                               initializer=_init_worker)
        # one warm-up per worker: the pool starts them one by one as tasks arrive
        with _sigint_blocked():
            self._started = [self._executor.submit(_warm) for _ in range(self.size)]
        self._tokens = itertools.count(1)
        self._dir = None
        self._warmed_rest = False

    def _warm_rest(self):
        """warm_rest once in each worker, queued behind whatever was submitted so far."""
        if not self._warmed_rest:
            self._warmed_rest = True
            for _ in range(self.size):
                try:
                    self._executor.submit(warm_rest)
                except (RuntimeError, concurrent.futures.process.BrokenProcessPool):
                    return

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def started(self) -> int:
        """How many workers have finished starting (and can take items without keeping this process waiting)."""
        return sum(1 for f in self._started if f.done() and f.exception() is None)

    def _failed_start(self):
        errors = [f.exception() for f in self._started if f.done() and f.exception() is not None]
        return errors[0] if errors and len(errors) == len(self._started) else None

    def _handle(self, obj):
        """obj pickled once into the pool's folder -> _Handle."""
        token = next(self._tokens)
        handle = _Handle(token, os.path.join(self._folder(), f"shared-{token}.pickle"))
        with open(handle.path + ".tmp", "wb") as f:
            pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(handle.path + ".tmp", handle.path)
        return handle

    def map_pieces(self, fn: Callable, items: Sequence, shared=None, what: str = "a stage",
                   done: Callable | None = None) -> list:
        """[fn(shared, item) for item in items], run here and in the workers together, in item order. fn must be a
        module-level function (the workers import it by name). done(count, result) is called as each item
        finishes, in the order they finish. A VolpuzzleError inside fn is raised here as it was raised there; a
        worker that dies gives a GeometryError naming `what` and the item."""
        self._warm_rest()
        n = len(items)
        results: list = [None] * n
        finished = [False] * n
        pending = list(range(n))
        running: dict[concurrent.futures.Future, int] = {}
        handle = None
        count = 0

        def record(k, value):
            nonlocal count
            results[k], finished[k] = value, True
            count += 1
            if done is not None:
                done(count, value)

        def died(ks, e):
            return GeometryError(f"{what}: a worker process died while working on {_which(ks)} of {n} ({e}); "
                                 f"try --jobs 1")

        def collect(fut):
            ks = running.pop(fut)
            try:
                values = fut.result()
            except concurrent.futures.process.BrokenProcessPool as e:
                raise died(ks, e) from e
            for k, value in zip(ks, values, strict=True):
                if not finished[k]:  # else this process did it too (below) and was first
                    record(k, value)

        while count < n:
            for fut in [f for f in running if f.done()]:
                collect(fut)
            # the last pending item is this process's own, so it never idles while the workers start
            while (pending[_MAIN_TAKES_ITEMS:] and self.started
                   and len(running) < _QUEUED_PER_WORKER * self.started):
                if handle is None and shared is not None:
                    handle = self._handle(shared)
                size = max(1, min(_MOST_PER_TASK, len(pending) // _RUNS_LEFT, len(pending) - _MAIN_TAKES_ITEMS))
                ks = tuple(pending.pop() for _ in range(size))  # from the back, the last item first
                try:
                    fut = self._executor.submit(_run, fn, handle, [items[k] for k in ks])
                except (RuntimeError, concurrent.futures.process.BrokenProcessPool) as e:
                    raise died(ks, e) from e
                running[fut] = ks
            if _MAIN_TAKES_ITEMS:
                if pending:
                    k = pending.pop(0)
                    record(k, fn(shared, items[k]))
                    continue
                # nothing left here: take back what no worker has started
                back = [f for f in running if f.cancel()]
                pending += sorted(k for f in back for k in running.pop(f))
                if pending:
                    continue
                # The rest is queued in or running on the workers. Rather than idle (a worker on a busy machine can
                # take many times as long), this process does the one given out last as well: it is the likeliest
                # not begun (a worker works through a run from its last item), and the same function gives the
                # same result, whichever finishes first.
                left = sorted((k, f) for f, ks in running.items() for k in ks if not finished[k])
                if left:
                    k, fut = left[0]
                    value = fn(shared, items[k])
                    if not finished[k]:
                        record(k, value)
                    if all(finished[j] for j in running[fut]):
                        running.pop(fut)  # nothing of it is wanted any more: not waited for
                    continue
            if count == n:
                break
            if not running:
                error = self._failed_start()
                if error is not None:  # items left that only workers take, and no worker could start
                    raise GeometryError(f"{what}: the worker processes did not start ({error}); try --jobs 1")
            concurrent.futures.wait(list(running) or [f for f in self._started if not f.done()] or self._started,
                                    return_when=concurrent.futures.FIRST_COMPLETED)
        assert all(finished)
        return results

    def submit(self, fn: Callable, *args) -> concurrent.futures.Future | None:
        """fn(*args) in a worker that has started -> its Future, or None when none has (do it here then)."""
        if not self.started:
            return None
        try:
            fut = self._executor.submit(fn, *args)
        except (RuntimeError, concurrent.futures.process.BrokenProcessPool):
            return None
        return fut

    def prefetch(self, fn: Callable, *args) -> Prefetch:
        """fn(*args) started in a worker now (queued behind its start-up if need be), for a result wanted later:
        Prefetch.result() gives it, or computes it here when no worker has begun it by then."""
        return Prefetch(self, fn, args)

    def background(self, fn: Callable, *args) -> Background:
        """fn(stopped, *args) queued for a worker, for work worth doing only while the worker would otherwise idle:
        stopped() turns True once this process calls Background.stop(), and fn asks it between its steps and
        returns what it has done."""
        return Background(self, fn, args)

    def _folder(self):
        if self._dir is None:
            self._dir = tempfile.mkdtemp(prefix="volpuzzle-workers-")
        return self._dir

    def close(self):
        """Shut the pool without waiting: its workers are ended at once. Left to exit on their own, idle workers
        take ~0.6 s to tear down their interpreters, which the CLI would wait for at exit; a worker still starting
        or running a task (an interrupted build) could take far longer. Nothing of theirs is needed any more, and
        the executor cleans up after workers that ended (its broken-pool path). Before Python 3.14 (which adds
        terminate_workers) the executor has no public way to end its workers, hence the two private attributes,
        read defensively."""
        processes = list((getattr(self._executor, "_processes", None) or {}).values())
        manager = getattr(self._executor, "_executor_manager_thread", None)  # shutdown() forgets it
        self._executor.shutdown(wait=False, cancel_futures=True)
        for p in processes:
            if p.is_alive():
                p.terminate()
        # The executor's own thread then notices and cleans up (a few ms). Waiting for it here keeps it from
        # closing its wake-up pipe while the interpreter's exit writes to it (an "Exception ignored" traceback).
        if manager is not None:
            manager.join(timeout=10.0)
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None


def _claim(path: str) -> bool:
    """True for the first process to claim `path` (a file created exclusively), False for any later one."""
    try:
        os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    return True


def _claimed_call(claim, fn, *args):
    """In a worker: (True, fn(*args)), or (False, None) when this process has taken the work back already."""
    return (True, fn(*args)) if _claim(claim) else (False, None)


class Background:
    """Work a worker does while it would idle (Workers.background), until this process stops it."""

    def __init__(self, workers: Workers, fn: Callable, args: tuple):
        token = next(workers._tokens)
        self._stop = os.path.join(workers._folder(), f"stop-{token}")
        self._begun = os.path.join(workers._folder(), f"begun-{token}")
        try:
            self._future = workers._executor.submit(_until, self._begun, self._stop, fn, *args)
        except (RuntimeError, concurrent.futures.process.BrokenProcessPool):
            self._future = None

    def stop(self):
        """Tell the work to stop -> what it returns, or None when it had not begun (it never will) or failed. Waits
        only for a worker that has begun it, which stops at its next step."""
        _claim(self._stop)
        if self._future is None or not os.path.exists(self._begun):
            return None
        try:
            return self._future.result()
        except Exception:  # noqa: BLE001 - work on the side: whatever went wrong, the stage does it itself
            return None


def _until(begun: str, path: str, fn, *args):
    """In a worker: Background's fn, told to stop once `path` exists (and not begun at all when it does already)."""
    _claim(begun)
    if os.path.exists(path):
        return None
    return fn(lambda: os.path.exists(path), *args)


class Prefetch:
    """A result computed ahead in a worker (Workers.prefetch). Whoever claims it first computes it: a worker when it
    gets to the task, this process when it asks for the result before any worker began; the same function either
    way, so the result does not depend on where it ran, and this process never waits for a worker's start-up."""

    def __init__(self, workers: Workers, fn: Callable, args: tuple):
        self._fn, self._args, self._what = fn, args, getattr(fn, "__name__", "a task")
        self._claim = os.path.join(workers._folder(), f"claim-{next(workers._tokens)}")
        try:
            self._future = workers._executor.submit(_claimed_call, self._claim, fn, *args)
        except (RuntimeError, concurrent.futures.process.BrokenProcessPool):
            self._future = None
        workers._warm_rest()

    def result(self, meanwhile: Callable | None = None):
        """The result, from the worker that computed it or computed here. meanwhile(): called here first when a
        worker is still computing it, so that this process does work it has to do anyway instead of idling."""
        if self._future is not None and (self._future.done() or not _claim(self._claim)):
            if meanwhile is not None and not self._future.done():
                meanwhile()
            try:
                ran, value = self._future.result()
            except concurrent.futures.process.BrokenProcessPool as e:
                raise GeometryError(f"{self._what}: a worker process died while computing it ({e}); "
                                    f"try --jobs 1") from e
            if ran:
                return value
        return self._fn(*self._args)

    def settle(self) -> None:
        """Make sure nothing of it runs after this returns, its result unwanted (a failed export removing the folder
        it writes into): claimed here, no worker begins it; one that has begun is waited for, whatever it gives."""
        if self._future is None:
            return
        try:
            if _claim(self._claim):
                return
        except OSError:  # the pool's folder is gone with the pool, whose workers were ended
            return
        try:
            self._future.result()
        except Exception:  # noqa: BLE001 - its outcome is not wanted, only its end
            pass


_TASKS = 96  # tasks a stage's items are cut into (in_tasks), at most: ~30 per process of a 2-core build


def in_tasks(items: Sequence, least: int) -> list:
    """items cut into runs of consecutive items, each of at least `least` and about _TASKS in all: for a stage whose
    items share pieces with their neighbours in the list (pairs of pieces, in id order), so that a piece mostly travels
    to one process, which builds its solid once. At 1024 pieces with two workers (fresh pools, alternated), the
    face-gap, overlap and joint checks took 0.6-1.5 s less than in runs of 8-12 (14.9/12.4/11.2 s -> 13.4/10.9/10.6
    s)."""
    size = max(int(least), -(-len(items) // _TASKS), 1)
    return [items[c:c + size] for c in range(0, len(items), size)]


def map_pieces(workers: Workers | None, fn: Callable, items: Sequence, shared=None, what: str = "a stage",
               done: Callable | None = None) -> list:
    """workers.map_pieces(fn, items, shared, what, done), or [fn(shared, item) for item in items] here when there are
    no workers: what every per-piece stage does, the same results either way. After each item a stop the user asked
    for is raised again (stop.check), in case a library swallowed its first raise."""
    def finished(count, value):
        stop.check()
        if done is not None:
            done(count, value)

    if workers is None:
        results = []
        for item in items:
            results.append(fn(shared, item))
            finished(len(results), results[-1])
        return results
    return workers.map_pieces(fn, items, shared=shared, what=what, done=finished)


def start(jobs: int | None, pieces: int) -> Workers | None:
    """A pool for a build of `pieces` pieces with `jobs` processes, or None when one would not pay (see wanted). At
    most one worker per MIN_PIECES pieces: each must earn back its own start-up (and holds ~300 MB at 32 pieces),
    so a 32-piece build on a 16-core machine starts two, not fifteen."""
    if not wanted(jobs, pieces):
        return None
    return Workers(min(int(jobs), 1 + pieces // MIN_PIECES))


class MeshRef:
    """A trimesh.Trimesh that travels to and from a worker as its two arrays (vertices (n, 3), faces (m, 3)) rather
    than with its caches; in this process it is the mesh itself, so what is remembered of it (geometry.memo) stays."""

    __slots__ = ("mesh",)

    def __init__(self, mesh):
        self.mesh = mesh

    def __reduce__(self):
        return _mesh_ref, (self.mesh.vertices.view(np.ndarray), self.mesh.faces.view(np.ndarray))


# In a worker: the meshes it received that are still held (by the shared inputs in _CACHE), by content. A piece
# travels to the workers once per stage (its overlaps, then its face gaps, its pictures); arriving as the same object
# it keeps what was found of it (geometry.memo: its solid), so a later stage does not rebuild the solids an earlier
# one built (~6 ms a piece), and the worker takes its share of the items sooner.
_RECEIVED: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def _mesh_ref(vertices, faces):
    import trimesh

    if not _IN_WORKER:  # in this process every mesh received stays its own object: they are the build's records
        return MeshRef(trimesh.Trimesh(vertices=vertices, faces=faces, process=False))
    digest = hashlib.blake2b(f"{vertices.shape}{vertices.dtype}{faces.shape}{faces.dtype}".encode(), digest_size=16)
    digest.update(np.ascontiguousarray(vertices))
    digest.update(np.ascontiguousarray(faces))
    key = digest.digest()
    mesh = _RECEIVED.get(key)
    # compared in full: a stage may have edited the mesh in place since, and a digest is no proof of equal content
    if mesh is None or not (np.array_equal(mesh.vertices, vertices) and np.array_equal(mesh.faces, faces)):
        mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
        _RECEIVED[key] = mesh
    return MeshRef(mesh)


class Remote:
    """A writer, fn(path, *args), that may run in a worker: fn is a module-level function and args plain data
    (meshes as MeshRef), so that it pickles. Called here, it is just fn(path, *args)."""

    __slots__ = ("fn", "args")

    def __init__(self, fn: Callable, *args):
        self.fn, self.args = fn, args

    def __call__(self, path):
        return self.fn(path, *self.args)
