"""The build's worker pool: results in item order and the same wherever an item ran, the shared input read once per
worker, errors keeping their kind and message, a dead worker as one GeometryError, no pool where it cannot pay or
must not start, no wait at close; and a whole build byte-identical with --jobs 1 and --jobs 2."""

import errno
import functools
import hashlib
import json
import multiprocessing
import os
import threading
import time

import numpy as np
import pytest
import trimesh
from helpers_build import example_spec

import volpuzzle
from volpuzzle import workers as W
from volpuzzle.errors import GeometryError, SpecError


def _square_plus(shared, item):
    time.sleep(shared.get("pause", 0.0))  # an item that takes as long as a piece, so that both sides get some
    return os.getpid(), id(shared), item * item + shared["offset"]


def _fails_on_three(_shared, item):
    if item == 3:
        raise SpecError("grid: item three is refused (got 3, expected anything else)")
    return item


def _dies_on_two(_shared, item):
    if item == 2 and multiprocessing.parent_process() is not None:
        os._exit(3)
    return item


def _mesh_volume(_shared, ref):
    return W.MeshRef(ref.mesh.copy()), float(ref.mesh.volume)


def _sigint_state(_shared, _item):
    import signal

    return signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []), signal.getsignal(signal.SIGINT)


@pytest.fixture(scope="module")
def pool():
    with W.Workers(2) as workers:
        deadline = time.monotonic() + 120
        while not workers.started and time.monotonic() < deadline:
            time.sleep(0.05)
        assert workers.started == 1
        yield workers


@pytest.mark.parametrize("main_takes", [False, True])
def test_results_come_in_item_order_and_the_shared_input_travels_once(pool, monkeypatch, main_takes):
    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", main_takes)
    shared = {"offset": 7, "ballast": np.arange(10_000), "pause": 0.05}
    seen = []
    out = pool.map_pieces(_square_plus, list(range(12)), shared=shared, what="test",
                          done=lambda k, _r: seen.append(k))
    assert [r[2] for r in out] == [k * k + 7 for k in range(12)]
    assert seen == list(range(1, 13))
    elsewhere = [r for r in out if r[0] != os.getpid()]
    assert elsewhere, "no item ran in the worker"
    assert len({r[1] for r in elsewhere}) == 1  # one unpickled copy of the shared input in the worker
    if not main_takes:
        assert len(elsewhere) == 12


def test_this_process_never_waits_for_a_slow_worker(pool):
    busy = pool.submit(_sleep, 2.0)  # the worker is held up (as on a machine busy with other work)
    t0 = time.perf_counter()
    out = pool.map_pieces(_square_plus, list(range(6)), shared={"offset": 1}, what="test")
    assert time.perf_counter() - t0 < 1.5
    assert [r[2] for r in out] == [k * k + 1 for k in range(6)]
    assert {r[0] for r in out} == {os.getpid()}  # the items given to the worker were done here as well
    assert busy.result() == 2.0


def test_a_worker_gets_runs_of_items_that_shrink_towards_the_end(pool, monkeypatch):
    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    runs = []
    submit = pool._executor.submit

    def counted(fn, *args):
        if fn is W._run:
            runs.append(len(args[2]))  # (fn, handle, items)
        return submit(fn, *args)

    monkeypatch.setattr(pool._executor, "submit", counted)
    out = pool.map_pieces(_square_plus, list(range(200)), shared={"offset": 2}, what="test")
    assert [r[2] for r in out] == [k * k + 2 for k in range(200)]
    assert sum(runs) == 200 and max(runs) == W._MOST_PER_TASK  # a small item travels with others
    assert runs[-1] == 1 and runs == sorted(runs, reverse=True)  # the last ones given out are short


def test_this_process_does_a_busy_workers_runs_itself(pool):
    busy = pool.submit(_sleep, 2.0)
    t0 = time.perf_counter()
    out = pool.map_pieces(_square_plus, list(range(64)), shared={"offset": 3}, what="test")
    assert time.perf_counter() - t0 < 1.5
    assert [r[2] for r in out] == [k * k + 3 for k in range(64)]
    assert {r[0] for r in out} == {os.getpid()}
    assert busy.result() == 2.0


def test_meshes_travel_as_arrays_and_come_back_equal(pool, monkeypatch):
    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    boxes = [trimesh.creation.box(extents=(1.0 + k, 2.0, 3.0)) for k in range(3)]
    out = pool.map_pieces(_mesh_volume, [W.MeshRef(b) for b in boxes], what="test")
    for box, (ref, volume) in zip(boxes, out, strict=True):
        assert np.array_equal(ref.mesh.vertices, box.vertices) and np.array_equal(ref.mesh.faces, box.faces)
        assert volume == pytest.approx(box.volume)


def _slab(x0, x1, y=0.0):
    """A 10 x 10 box from x0 to x1 along x, moved by y across, its faces triangulated every ~1.25 mm."""
    box = trimesh.creation.box([x1 - x0, 10, 10]).subdivide().subdivide().subdivide()
    return box.apply_translation([(x0 + x1) / 2, y, 0])


@pytest.mark.parametrize("per_task", [1, 2, 8])
def test_face_gaps_in_the_workers_are_the_serial_ones(pool, monkeypatch, per_task):
    from volpuzzle import check

    # p0 | p1 touch; p2 stands 0.1 mm off p1 but half a vertex spacing across, so its closest vertices (what the
    # serial rule keeps after a touching pair) are ~0.51 mm apart: a chunk measured apart from the touching pair
    # must still give that, not the engine's 0.1
    meshes = {"p0": _slab(0, 10), "p1": _slab(10, 20), "p2": _slab(20.1, 30, 0.5), "p3": _slab(30.3, 40)}
    serial = check._face_gaps(meshes, 0.3)
    assert [g[:2] for g in serial] == [("p0", "p1"), ("p1", "p2"), ("p2", "p3")]
    assert serial[0][3] == 0.0 and serial[1][3] > 0.4
    monkeypatch.setattr(check, "_GAP_PAIRS_PER_TASK", per_task)
    for main_takes in (False, True):
        monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", main_takes)
        assert check._face_gaps(meshes, 0.3, workers=pool) == serial
    del meshes["p0"]  # without the touching pair every gap is the engine's, wherever measured
    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    assert [g[3] for g in check._face_gaps(meshes, 0.3, workers=pool)] == pytest.approx([0.1, 0.3], abs=1e-9)


def _solid_of_shared(shared, k):
    from volpuzzle.check import piece_solid

    mesh = shared[k].mesh
    return os.getpid(), id(mesh), id(piece_solid(mesh, f"p{k}")), np.asarray(mesh.bounds).tolist()


def test_a_worker_keeps_one_mesh_and_its_solid_per_content_across_stages(pool, monkeypatch):
    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    boxes = [trimesh.creation.box(extents=(1.0 + k, 2.0, 3.0)) for k in range(3)]
    first, again = (pool.map_pieces(_solid_of_shared, [0, 1, 2], shared=[W.MeshRef(b) for b in boxes], what="test")
                    for _ in range(2))
    assert all(a[0] != os.getpid() for a in first)
    # the second stage's copies are the first's objects, with the solids already built
    assert [a[1:3] for a in again] == [a[1:3] for a in first]
    boxes[1].apply_translation([5.0, 0.0, 0.0])  # new content: a new object, its own solid
    moved = pool.map_pieces(_solid_of_shared, [0, 1, 2], shared=[W.MeshRef(b) for b in boxes], what="test")
    assert moved[1][1] != first[1][1] and moved[1][3] == np.asarray(boxes[1].bounds).tolist()
    assert [m[1] for m in moved[::2]] == [a[1] for a in first[::2]]
    # in this process meshes received never merge: two equal meshes stay two objects
    back = pool.map_pieces(_mesh_volume, [W.MeshRef(boxes[0]), W.MeshRef(boxes[0].copy())], what="test")
    assert back[0][0].mesh is not back[1][0].mesh


def test_printable_pieces_from_the_workers_come_with_their_hull_points_for_the_layout(pool, monkeypatch):
    # the workers find each printable mesh's hull points where they make it; the layout then uses them as they are,
    # and they are the ones this process would find
    from volpuzzle import export, geometry
    from volpuzzle.compose.piece import Piece

    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    boxes = [trimesh.creation.icosphere(subdivisions=2, radius=3.0 + k).apply_translation([10.0 * k, 0.0, 0.0])
             for k in range(3)]
    pieces = [Piece(f"p{k}-0-0", (k, 0, 0), b, float(b.volume), float(b.volume), len(b.faces))
              for k, b in enumerate(boxes)]
    out = export.printable(pieces, workers=pool)
    fresh = [geometry._hull_points(p.mesh) for p in out]
    monkeypatch.setattr(geometry, "_hull_points", lambda _mesh: pytest.fail("the hull points were found again"))
    for p, want in zip(out, fresh, strict=True):
        assert np.array_equal(geometry.hull_points_of(p.mesh), want) and len(want) > 12


def test_an_error_in_a_worker_keeps_its_kind_and_message(pool, monkeypatch):
    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    with pytest.raises(SpecError, match=r"^grid: item three is refused \(got 3, expected anything else\)$"):
        pool.map_pieces(_fails_on_three, list(range(6)), what="test")


@pytest.mark.slow
def test_a_worker_that_dies_gives_one_geometry_error(monkeypatch):
    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    with W.Workers(2) as workers, pytest.raises(GeometryError, match=r"^label: a worker process died while working "
                                                                     r"on item 3 of 5 .*try --jobs 1"):
        workers.map_pieces(_dies_on_two, list(range(5)), what="label")
    # the first run given out holds the last 8 items; the message names them all
    with W.Workers(2) as workers, pytest.raises(GeometryError, match=r"on one of items 193-200 of 200 "):
        workers.map_pieces(_dies_on_two, [(k + 3) % 200 for k in range(200)], what="label")


def test_a_run_of_items_is_named_as_its_items():
    assert W._which([2]) == "item 3"
    assert W._which([11, 10, 9]) == "one of items 10-12"
    assert W._which([7, 2]) == "one of items 3, 8"


def _pid_and_square(x):
    return os.getpid(), x * x


def _sleep(seconds):
    time.sleep(seconds)
    return seconds


def test_a_prefetch_runs_ahead_in_a_worker(pool):
    ahead = pool.prefetch(_pid_and_square, 9)
    deadline = time.monotonic() + 60
    while not ahead._future.done() and time.monotonic() < deadline:
        time.sleep(0.02)
    pid, value = ahead.result()
    assert value == 81 and pid != os.getpid()


def test_a_prefetch_no_worker_began_is_computed_here(pool):
    busy = pool.submit(_sleep, 1.0)  # the one worker is busy: the prefetch waits in its queue
    ahead = pool.prefetch(_pid_and_square, 5)
    pid, value = ahead.result()  # asked for at once: claimed here, and the worker skips it later
    assert value == 25 and pid == os.getpid()
    assert busy.result() == 1.0
    assert ahead._future.result() == (False, None)


def test_a_prefetch_runs_meanwhile_here_only_while_a_worker_computes_it(pool):
    calls = []
    ahead = pool.prefetch(_sleep, 0.5)
    deadline = time.monotonic() + 60
    while not os.path.exists(ahead._claim) and time.monotonic() < deadline:  # until the worker has begun it
        time.sleep(0.01)
    assert ahead.result(meanwhile=lambda: calls.append(ahead._future.done())) == 0.5
    assert calls == [False]  # called once, before the worker had finished
    busy = pool.submit(_sleep, 1.0)
    queued = pool.prefetch(_pid_and_square, 4)  # not begun: computed here at once, nothing to do meanwhile
    assert queued.result(meanwhile=lambda: calls.append("queued"))[1] == 16
    assert busy.result() == 1.0
    done = pool.prefetch(_pid_and_square, 3)
    while not done._future.done() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert done.result(meanwhile=lambda: calls.append("done"))[1] == 9
    assert calls == [False]


def test_a_worker_never_sees_ctrl_c(pool, monkeypatch):
    # Ctrl-C reaches the whole process group; a worker still importing its modules printed a KeyboardInterrupt
    # traceback. Workers start with SIGINT blocked (pthread_sigmask) and ignore it once started
    import signal

    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    (blocked, handler), = pool.map_pieces(_sigint_state, [0], shared={})
    assert blocked and handler == signal.SIG_IGN
    # and this process's own mask is as it was
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])


def _swallows_a_stop_on_one(shared, item):
    from volpuzzle import stop

    shared.setdefault("ran", []).append(item)
    if item == 1:
        try:
            stop.ask(stop.Terminated)
        except BaseException:  # noqa: BLE001 - as trimesh does
            pass
    return item


def test_a_stop_swallowed_inside_an_item_ends_the_stage_after_it():
    # a per-piece stage asks for a stop after every item: a SIGTERM whose raise a library swallowed must not let the
    # stage (and the build) run on
    from volpuzzle import stop

    shared = {}
    try:
        with pytest.raises(stop.Terminated):
            W.map_pieces(None, _swallows_a_stop_on_one, [0, 1, 2, 3], shared=shared)
    finally:
        stop.restore(None)
    assert shared["ran"] == [0, 1]
    assert W.map_pieces(None, _swallows_a_stop_on_one, [5], shared={}) == [5]  # forgotten once restored


def test_a_pool_only_where_it_pays_and_may_start():
    assert not W.wanted(1, 1000)  # one job: everything here
    assert not W.wanted(2, W.MIN_PIECES - 1)  # too little work for a worker's start-up
    assert W.wanted(2, W.MIN_PIECES)
    assert W.start(1, 1000) is None


def test_one_worker_per_sixteen_pieces_at_most(monkeypatch):
    sizes = []
    monkeypatch.setattr(W, "Workers", lambda jobs: sizes.append(jobs - 1))
    W.start(16, 32)
    W.start(3, 1000)
    assert sizes == [2, 2]


def _wanted_in_a_daemon(queue):
    queue.put(W.wanted(4, 1000))


def test_no_pool_inside_a_daemonic_process():
    # a Dask worker process is daemonic (and batch passes jobs=1 anyway): daemons may not have children
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    p = ctx.Process(target=_wanted_in_a_daemon, args=(queue,), daemon=True)
    p.start()
    assert queue.get(timeout=60) is False
    p.join(30)


def test_close_does_not_wait_for_a_starting_worker():
    workers = W.Workers(2)
    processes = list(workers._executor._processes.values())
    t0 = time.perf_counter()
    workers.close()
    assert time.perf_counter() - t0 < 1.0
    for p in processes:
        p.join(10)
        assert not p.is_alive()


_EXIT_SCRIPT = """
import os, time
from volpuzzle import workers as W
if __name__ == "__main__":
    w = W.Workers(2)
    while not w.started:
        time.sleep(0.01)
    w.submit(os.getpid).result()
    t0 = time.perf_counter()
    w.close()
    print(time.perf_counter() - t0)
"""


@pytest.mark.slow
def test_a_process_exits_at_once_and_silently_after_close(tmp_path):
    # idle workers left to exit on their own held the exit up ~0.6 s; ending them raced the executor's clean-up
    # against the interpreter's exit, which printed an "Exception ignored" traceback
    import subprocess
    import sys

    script = tmp_path / "close_then_exit.py"
    script.write_text(_EXIT_SCRIPT)
    for _ in range(2):
        run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                             cwd=os.getcwd())
        assert run.returncode == 0 and run.stderr == ""
        assert float(run.stdout) < 0.5


def _without_times(x):
    if isinstance(x, dict):
        return {k: _without_times(v) for k, v in x.items() if not (k.endswith("_s") or k == "seconds")}
    if isinstance(x, list):
        return [_without_times(v) for v in x]
    return x


@pytest.mark.slow
def test_a_build_is_byte_identical_with_one_and_two_jobs(tmp_path, monkeypatch):
    # the pool forced on below its threshold, and the workers given every item they can take
    monkeypatch.setattr(W, "MIN_PIECES", 1)  # 0 would divide by zero in the size cap (start)
    monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", False)
    used = []
    original = W.Workers.map_pieces

    def counted(self, fn, items, **kw):
        used.append(kw.get("what"))
        return original(self, fn, items, **kw)

    monkeypatch.setattr(W.Workers, "map_pieces", counted)
    ahead = []
    prefetch = W.Workers.prefetch

    def begun(self, fn, *args):
        ahead.append(getattr(fn, "__name__", type(fn).__name__))
        return prefetch(self, fn, *args)

    monkeypatch.setattr(W.Workers, "prefetch", begun)
    # the paper's quarter torus, randomized, in 2 x 1 x 2 coarse pieces
    spec = example_spec("quarter-torus", tmp_path, tolerance=0.8, grid=[2, 1, 2])
    files, reports, md = {}, {}, {}
    root = tmp_path / "out" / "quarter-torus"
    for jobs in (1, 2):  # into the same folder, so that the reports name the same one
        volpuzzle.build(spec, jobs=jobs, force=True)
        files[jobs] = {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
                       for p in sorted(root.rglob("*")) if p.is_file() and p.name not in ("report.json", "report.md")}
        reports[jobs] = _without_times(json.loads((root / "report.json").read_text()))
        md[jobs] = (root / "report.md").read_text().split("## Timings")[0]
    assert {"compose", "label"} <= set(used)
    # the step pictures were begun in a worker once the assembly was known, before the export
    assert "_step_pictures" in ahead and any(f.startswith("steps/") for f in files[1])
    assert files[1] == files[2] and any(f.startswith("pieces/") for f in files[1])
    assert reports[1] == reports[2]
    assert md[1] == md[2]


def _write_picture(path, text, pause):
    time.sleep(pause)
    with open(path, "w", encoding="utf-8") as f:
        f.write(f"{text} {os.getpid()}")


@pytest.mark.parametrize("worker_busy", [False, True])
def test_pictures_are_the_same_files_wherever_they_are_drawn(pool, tmp_path, worker_busy):
    from test_export import make_pieces, make_report

    from volpuzzle.export import write_build

    pieces = make_pieces()
    busy = pool.submit(_sleep, 1.0) if worker_busy else None
    extras = {"a.txt": W.Remote(_write_picture, "first", 0.3), "steps/b.txt": W.Remote(_write_picture, "second", 0.3)}
    out = write_build(tmp_path / "c", pieces, make_report(pieces), extras=extras, workers=pool)
    drawn = {rel: (out / rel).read_text(encoding="utf-8").split() for rel in extras}
    assert [d[0] for d in drawn.values()] == ["first", "second"]
    where = [int(d[1]) == os.getpid() for d in drawn.values()]
    # the first is drawn here; the worker begins the other, or, held up, leaves it to be drawn here, not waited for
    assert where[0] and (where[1] or not worker_busy)
    if busy is not None:
        assert busy.result() == 1.0


def _write_where(path, text, pause):
    time.sleep(pause)
    with open(path, "w", encoding="utf-8") as f:
        f.write(f"{text} {os.getpid()} {threading.current_thread().name}")


@pytest.mark.parametrize("worker_busy", [False, True])
def test_plates_are_written_by_the_workers_from_the_first_and_on_the_3mf_thread_from_the_last(pool, tmp_path,
                                                                                            worker_busy):
    from test_export import make_pieces, make_report

    from volpuzzle.export import write_build

    pieces = make_pieces()
    busy = pool.submit(_sleep, 2.0) if worker_busy else None
    plates = [f"plates/plate-{k:02d}.3mf" for k in range(1, 5)]
    extras = {"preview.png": W.Remote(_write_where, "preview", 0.0),
              **{rel: W.Remote(_write_where, rel, 0.15) for rel in plates}}
    out = write_build(tmp_path / "c", pieces, make_report(pieces), extras=extras, workers=pool)
    drawn = {rel: (out / rel).read_text(encoding="utf-8").split() for rel in extras}
    assert all(d[0] == rel for rel, d in drawn.items() if rel != "preview.png")
    here = {rel: int(d[1]) == os.getpid() for rel, d in drawn.items()}
    # the preview is this process's own; lib3mf writes one file at a time in a process, so a plate is never
    # written on this process's main thread, beside the puzzle's 3MF on the 3MF thread
    assert here["preview.png"] and drawn["preview.png"][2] == "MainThread"
    assert all(drawn[rel][2].startswith("volpuzzle-3mf") for rel in plates if here[rel])
    if worker_busy:  # none begun by a worker: all here, none waited for
        assert all(here[rel] for rel in plates)
        assert busy.result() == 2.0
    else:
        assert not here[plates[0]] and here[plates[-1]]


def test_settling_a_prefetch_after_its_pool_closed_says_nothing():
    # a failed export settles its prefetches; once the pool is closed (its folder and workers gone) nothing runs
    workers = W.Workers(2)
    ahead = workers.prefetch(_sleep, 0.5)
    workers.close()
    ahead.settle()


def _write_slowly(path, flags, pause):
    # a writer that makes its own folder (as one nested deeper could): begun, it would recreate a removed folder
    path.parent.mkdir(parents=True, exist_ok=True)
    (flags / "begun").touch()
    time.sleep(pause)
    path.write_text("late", encoding="utf-8")
    (flags / "written").touch()


def _full_disk_once_begun(flags, path):
    deadline = time.monotonic() + 60
    while not (flags / "begun").exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    raise OSError(errno.ENOSPC, "No space left on device", os.fspath(path))


def test_a_failed_export_leaves_no_folder_behind_while_a_worker_still_writes_into_it(pool, tmp_path):
    # the disk fills while a worker draws a picture into the temporary folder: the folder is removed only once that
    # worker is done with it, so nothing is written into it afterwards and no half-written folder is left
    from test_export import make_pieces, make_report

    from volpuzzle.errors import ExportError
    from volpuzzle.export import write_build

    flags = tmp_path / "flags"
    flags.mkdir()
    pieces = make_pieces()
    extras = {"a.txt": W.Remote(_write_picture, "first", 0.0),
              "steps/b.txt": W.Remote(_write_slowly, flags, 0.5),
              "z.txt": functools.partial(_full_disk_once_begun, flags)}
    with pytest.raises(ExportError, match="No space left on device"):
        write_build(tmp_path / "c", pieces, make_report(pieces), extras=extras, workers=pool)
    deadline = time.monotonic() + 60
    while not (flags / "written").exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert (flags / "written").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flags"]


@pytest.mark.parametrize("per_task", [1, 2])
def test_joint_checks_in_the_workers_are_the_serial_ones(pool, monkeypatch, per_task):
    import manifold3d as m3

    from volpuzzle import check

    def mesh(solid):
        out = solid.to_mesh()
        return trimesh.Trimesh(out.vert_properties[:, :3], out.tri_verts, process=True)

    pin = m3.Manifold.cylinder(3.0, 1.0, 1.0, 48)
    below = m3.Manifold.cube([10, 10, 5], True).translate([0, 0, -2.5])
    above = m3.Manifold.cube([10, 10, 5], True).translate([0, 0, 2.5])
    meshes = {"a": mesh(below + pin), "b": mesh(above - m3.Manifold.cylinder(3.3, 1.15, 1.15, 48)),
              "c": mesh(above.translate([20, 0, 0])), "d": mesh(below.translate([20, 0, 0]))}
    joint = {"center_mm": [0, 0, 0], "direction": [0, 0, 1], "radius_mm": 1.0, "length_mm": 3.0,
             "clearance_mm": 0.15, "style": "pin", "shape": "cylinder"}
    joints = [dict(joint, pin_piece="a", hole_piece="b"),  # fits
              dict(joint, pin_piece="d", hole_piece="c", center_mm=[20, 0, 0]),  # no pin, no hole
              dict(joint, pin_piece="a", hole_piece="x"),  # a piece not given: not tested
              dict(joint, pin_piece="a", hole_piece="c", center_mm=[20, 0, 0])]  # no pin there, c in the way
    serial = check.check_joints(meshes, joints)
    assert len(serial) == 4 and "the pin of d is missing" in serial[0] and "hole in c" in serial[1]
    monkeypatch.setattr(check, "_PIECES_PER_TASK", per_task)
    for main_takes in (False, True):
        monkeypatch.setattr(W, "_MAIN_TAKES_ITEMS", main_takes)
        assert check.check_joints(meshes, joints, workers=pool) == serial


def test_items_go_in_runs_of_neighbours_about_a_fixed_number_of_tasks():
    # a few items keep to runs of the least size; many are cut into about _TASKS runs, so that pairs sharing a piece
    # mostly go to one process; the runs keep every item once, in order
    few, many = list(range(50)), list(range(10_000))
    assert [len(r) for r in W.in_tasks(few, 8)] == [8] * 6 + [2]
    runs = W.in_tasks(many, 8)
    assert len(runs) <= W._TASKS and min(len(r) for r in runs[:-1]) > 8
    assert [x for r in runs for x in r] == many and W.in_tasks([], 8) == []


def _steps_until_stopped(stopped, pause):
    steps = 0
    while not stopped():
        time.sleep(pause)
        steps += 1
    return os.getpid(), steps


def test_work_on_the_side_runs_until_stopped_and_gives_what_it_did(pool):
    side = pool.background(_steps_until_stopped, 0.01)
    deadline = time.monotonic() + 60
    while not os.path.exists(side._begun) and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.2)
    pid, steps = side.stop()
    assert pid != os.getpid() and steps > 0


def test_work_on_the_side_not_begun_is_dropped_without_waiting(pool):
    busy = pool.submit(_sleep, 1.0)  # the one worker is busy: the work waits in its queue
    side = pool.background(_steps_until_stopped, 0.01)
    t0 = time.monotonic()
    assert side.stop() is None
    assert time.monotonic() - t0 < 0.5  # not kept waiting for the worker
    assert busy.result() == 1.0
    assert side._future.result() is None  # the worker got to it after the stop: it did nothing


def test_cell_surfaces_made_ahead_are_cell_surfaces_and_build_the_same_pieces(pool, tmp_path, monkeypatch):
    from volpuzzle.compose import ahead as A
    from volpuzzle.compose import cell_surface, compose
    from volpuzzle.pipeline import prepare
    from volpuzzle.spec import load_spec

    s = prepare(load_spec(example_spec("quarter-torus", tmp_path, tolerance=0.8, grid=[2, 1, 2])))
    begun = A.begin(pool, s.tiling, s.fmap, 0.8, 0.15)
    deadline = time.monotonic() + 60
    while not begun.sampling._future.done() and time.monotonic() < deadline:  # sampled in the worker
        time.sleep(0.01)
    sampling = begun.sampling.result()
    while not os.path.exists(begun.surfaces._begun) and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(1.0)  # a few surfaces a second at least
    begun.stop()
    made = A._KEPT[begun.token].surfaces
    cells = sorted(s.tiling.cells)
    # the last cells first, each exactly cell_surface's
    assert made and sorted(made) == [(c, 0.15) for c in cells[len(cells) - len(made):]]
    for (index, clearance), (v, f) in made.items():
        v0, f0 = cell_surface(s.tiling.cell(index), sampling, s.fmap, clearance)
        assert np.array_equal(v, v0) and np.array_equal(f, f0)
    used = []
    surface = A.surface
    monkeypatch.setattr(A, "surface", lambda *args: used.append(surface(*args)) or used[-1])
    with_ahead = compose(s.tiling, s.fmap, s.joints, 0.8, sampling=sampling, face_clearance=0.15, workers=pool,
                         ahead=begun.token)
    assert any(u is not None for u in used)  # this process built pieces on the worker's surfaces
    assert begun.token not in A._KEPT  # used here, and let go
    alone = compose(s.tiling, s.fmap, s.joints, 0.8, sampling=sampling, face_clearance=0.15)
    for p, q in zip(with_ahead, alone, strict=True):
        assert p.id == q.id and np.array_equal(p.mesh.vertices, q.mesh.vertices)
        assert np.array_equal(p.mesh.faces, q.mesh.faces)
