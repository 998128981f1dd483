"""`volpuzzle batch`: many specs built on a Dask cluster (dask.distributed), one `build` per task.

Without a scheduler address the cluster is a LocalCluster of worker processes started with `spawn`: manifold3d's
and numba's thread pools make a forked worker unsafe. With one (--scheduler, or DASK_SCHEDULER_ADDRESS) the specs
go to that cluster; its workers must read the specs and their model files at the same paths and write the output
folders where the client expects them (a shared file system), as a LocalCluster does.

Each task is exactly `volpuzzle build SPEC` in a worker process, so each folder is the one `build` writes; only the
measured times in report.json and report.md (timings_s, checks.overlap_time_s) differ from run to run.
"""

import contextlib
import os
import signal
import sys
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

from .errors import ExportError, SpecError, one_line

SCHEDULER_ENV = "DASK_SCHEDULER_ADDRESS"


@dataclass(frozen=True)
class Result:
    """One spec's outcome: the folder written (or None) and the one-line error (or None)."""

    spec: str
    name: str
    directory: str | None
    pieces: int | None
    seconds: float
    error: str | None = None

    @property
    def ok(self):
        return self.error is None


def build_one(spec_path, output_dir, force, name):
    """One build in a worker -> Result. Every failure becomes its one-line message, as `build` prints it."""
    from .errors import VolpuzzleError
    from .pipeline import Progress, build

    t0 = time.perf_counter()
    try:
        report = build(spec_path, output_dir=output_dir, force=force, jobs=1, progress=Progress(False))
    except VolpuzzleError as e:
        return Result(spec_path, name, None, None, time.perf_counter() - t0, f"error: {one_line(e)}")
    except Exception as e:  # noqa: BLE001 - one spec's bug must not stop the batch, nor print a traceback
        return Result(spec_path, name, None, None, time.perf_counter() - t0,
                      f"internal error: {type(e).__name__}: {one_line(e)} (please report it)")
    return Result(spec_path, name, report["spec"]["output"]["directory"], len(report["pieces"]),
                  time.perf_counter() - t0)


def _targets(specs, output_root):
    """(spec path, output folder, name) per spec, all absolute; a spec that cannot be read gets no folder (its
    build reports why). Two specs writing one folder are refused before any work."""
    from .errors import VolpuzzleError
    from .spec import load_spec

    out, seen = [], {}
    for s in specs:
        path = str(Path(s).resolve())
        try:
            spec = load_spec(path)
        except VolpuzzleError:
            out.append((path, None, Path(s).stem))
            continue
        folder = Path(output_root) / spec.name if output_root is not None else Path(spec.output.directory)
        folder = str(folder.resolve())
        if folder in seen:
            raise SpecError(f"name: {s} and {seen[folder]} would both write {folder} (got the same name "
                            f"{spec.name!r} twice, expected one folder per spec)")
        seen[folder] = s
        out.append((path, folder, spec.name))
    return out


def _client(jobs, scheduler):
    """A distributed.Client on the given scheduler, or on a new LocalCluster of `jobs` spawned processes."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError:
        raise ExportError("volpuzzle batch: dask.distributed is not installed (got no module 'distributed', "
                          "expected pip install 'volpuzzle[batch]')") from None
    if scheduler:
        try:
            return Client(scheduler, timeout="10s"), None
        except (OSError, TimeoutError, ValueError) as e:
            raise ExportError(f"--scheduler: no Dask scheduler answers at {scheduler} ({e}; expected the address of "
                              f"a running scheduler, such as tcp://host:8786)") from None
    with dask.config.set({"distributed.worker.multiprocessing-method": "spawn",
                          "distributed.worker.daemon": False}), warnings.catch_warnings():
        # the scheduler's HTTP server asks for port 8787 even without a dashboard, and warns on stderr in three lines
        # when another cluster (a notebook's, a second batch) holds it; any free port serves
        warnings.filterwarnings("ignore", message="Port .* is already in use", category=UserWarning)
        # one build per worker process at a time: a build keeps both of its cores busy on its own
        with _workers_deaf_to_ctrl_c():
            cluster = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=50, env={"VOLPUZZLE_NO_PROGRESS": "1"})
    return Client(cluster), cluster


@contextlib.contextmanager
def _workers_deaf_to_ctrl_c():
    """Ctrl-C ignored in this process while the LocalCluster starts its worker processes, which keep it ignored for
    good: an ignored signal stays ignored across exec, and neither Python nor asyncio then installs a handler of its
    own. Ctrl-C reaches the whole process group, and a Dask worker it caught printed a KeyboardInterrupt traceback
    (from its imports, or from its event loop at any time later), while this process ends the workers itself when
    stopped. Blocking SIGINT instead does not reach them: Dask's event-loop thread, which starts them, has it
    unblocked. A Ctrl-C in this second (the workers spawn for ~0.4 s of it) is lost; the next one stops the batch."""
    if threading.current_thread() is not threading.main_thread():  # signal.signal works in the main thread only
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old if old is not None else signal.SIG_DFL)


def run_batch(specs, output_root=None, jobs=None, scheduler=None, force=False, progress=None):
    """Build every spec on a Dask cluster -> [Result] in the order of `specs`. progress(done, total, result) is
    called as each one finishes."""
    if not specs:
        raise SpecError("SPEC: no spec given (got none, expected one or more spec files)")
    targets = _targets(specs, output_root)
    scheduler = scheduler or os.environ.get(SCHEDULER_ENV) or None
    jobs = jobs or min(len(targets), os.cpu_count() or 1)
    client, cluster = _client(jobs, scheduler)
    results = [None] * len(targets)
    try:
        from distributed import as_completed

        futures = {}
        for k, (path, folder, name) in enumerate(targets):
            # pure=False: a rebuild of the same spec is new work, not a cached result
            f = client.submit(build_one, path, folder, force, name, pure=False, key=f"volpuzzle-build-{k}-{name}")
            futures[f] = k
        for done, f in enumerate(as_completed(futures), 1):
            k = futures[f]
            try:
                results[k] = f.result()
            except Exception as e:  # noqa: BLE001 - a worker that died (KilledWorker) fails its spec only
                path, _, name = targets[k]
                results[k] = Result(path, name, None, None, 0.0, f"error: the worker building it failed "
                                                                 f"({type(e).__name__}: {one_line(e)})")
            if progress is not None:
                progress(done, len(targets), results[k])
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
            # A stopped batch (Ctrl-C, SIGTERM) ends its local workers mid-build, and a build ended in its export
            # leaves its temporary folder. The workers are gone now, so those folders are stale: removed here, as the
            # next build into each folder would. A remote cluster's builds run on, and their folders stay theirs.
            _remove_temporaries([folder for _, folder, _ in targets])
    return results


def _remove_temporaries(folders):
    """remove_stale_temporaries beside each output folder (None: a spec that could not be read)."""
    from .export import remove_stale_temporaries

    for folder in folders:
        if folder is not None:
            remove_stale_temporaries(Path(folder))


def summary_table(results):
    """The table printed at the end: one line per spec. -> str"""
    rows = [("spec", "status", "pieces", "seconds", "folder or error")]
    for r in results:
        rows.append((one_line(r.name), "ok" if r.ok else "FAILED", "" if r.pieces is None else str(r.pieces),
                     f"{r.seconds:.1f}", r.directory if r.ok else r.error))
    widths = [max(len(row[c]) for row in rows) for c in range(4)]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row[:4], widths, strict=True)) + "  " + row[4] for row in rows]
    failed = sum(not r.ok for r in results)
    lines.append(f"{len(results) - failed} built, {failed} failed")
    return "\n".join(lines)


def terminal_progress():
    """progress() for run_batch: one updating line on a terminal, nothing otherwise."""
    from .progress import end_line, show_line

    if not sys.stderr.isatty() or os.environ.get("VOLPUZZLE_NO_PROGRESS"):
        return None

    def show(done, total, result):
        show_line(f"batch {done}/{total}: {one_line(result.name)} {'ok' if result.ok else 'failed'}")
        if done == total:
            end_line()  # the summary table follows

    return show
