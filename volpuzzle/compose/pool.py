"""Pieces built in parallel: this process and spawned worker processes together, each piece by the same function,
so where a piece is built does not change it."""

import concurrent.futures
import multiprocessing
import os
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import trimesh

from ..errors import GeometryError
from .piece import Piece, build_piece

# A spawned worker costs ~2.5 s of CPU (imports, pickling) before it builds anything. This process keeps building
# meanwhile (see _pooled), but on a busy machine the start-up takes 10 s of wall time, and the pieces handed to the
# workers then can hold up the end: measured with the 256-piece twisted torus (compose ~2.7 CPU s) the pool was
# slower than serial, so serial below this estimate.
_POOL_MIN_PIECES = 16
_POOL_MIN_SECONDS = 5.0
_MAIN_TAKES_PIECES = True  # False: the workers build every piece (tests use it to see them do so)
_SECONDS_PER_TRIANGLE = 1e-5  # building, checking and converting one piece triangle (measured, 2 cores, loaded)
_SECONDS_PER_JOINT = 0.005  # the booleans of one pin and its hole


@dataclass(frozen=True, eq=False)
class BuildJob:
    """What every piece is built from: the Tiling, the Sampling of its faces, the Map F, the Joint list and the face
    clearance in mm. Pickled once into each worker (its initializer's argument)."""

    tiling: object
    sampling: object
    fmap: object
    joints: list
    face_clearance: float


class _PieceRecord(NamedTuple):
    """A built piece as plain data (which travels between processes more cheaply and predictably than a trimesh
    object): id, cell index, vertices (n, 3) mm, faces (m, 3), volume and body_volume mm^3, build seconds."""

    id: str
    cell: tuple
    vertices: np.ndarray
    faces: np.ndarray
    volume: float
    body_volume: float
    seconds: float


_WORKER_JOB = None  # the BuildJob of this worker process, set by _init_worker


def _init_worker(job):
    global _WORKER_JOB
    _WORKER_JOB = job


def _warm_worker():
    """Load what every piece needs (the compiled kernels, from numba's cache) before the worker is given pieces,
    so that its first piece does not hold up the end of compose. -> the worker's pid"""
    cell = next(iter(_WORKER_JOB.tiling.cells.values()))
    _WORKER_JOB.fmap.evaluate(np.repeat(np.asarray(cell.center, float)[None], 512, axis=0))
    return os.getpid()


def build_record(job, index):
    """Cell `index` of the job -> _PieceRecord."""
    t0 = time.perf_counter()
    p = build_piece(job.tiling.cell(index), job.sampling, job.fmap, job.joints, face_clearance=job.face_clearance)
    return _PieceRecord(p.id, p.cell, np.asarray(p.mesh.vertices), np.asarray(p.mesh.faces), p.volume,
                        p.body_volume, time.perf_counter() - t0)


def _build_in_worker(index):
    return build_record(_WORKER_JOB, index)


def piece_from(record):
    """_PieceRecord -> Piece."""
    mesh = trimesh.Trimesh(vertices=record.vertices, faces=record.faces, process=False)
    return Piece(record.id, tuple(record.cell), mesh, record.volume, record.body_volume, int(len(record.faces)))


def use_pool(jobs, n, sampling, joints):
    """A pool only pays when there is enough work: many pieces, and many triangles or booleans to share out."""
    if jobs is None or jobs <= 1 or n <= 1 or n < _POOL_MIN_PIECES:
        return False
    seconds = 2 * sampling.counts[1] * _SECONDS_PER_TRIANGLE + len(joints) * _SECONDS_PER_JOINT
    return seconds >= _POOL_MIN_SECONDS


def build_pooled(order, jobs, job, progress):
    """Pieces built by this process and jobs - 1 spawned workers together -> {cell index: _PieceRecord}. This process
    takes pieces from the front while the workers start (~2.5 s of imports that it would otherwise wait for) and
    then take pieces from the back, two queued each; a piece still queued when the front reaches it is built
    here. Every piece is built by the same function, so where it is built does not change it."""
    records, n = {}, len(order)
    pending = list(order)
    running = {}

    def finished(fut, index):
        try:
            records[index] = fut.result()
        except concurrent.futures.process.BrokenProcessPool as e:
            raise GeometryError(f"compose: a worker process died while building {job.tiling.cell(index).id} ({e}); "
                                f"try --jobs 1") from e
        if progress:
            progress(len(records), n, records[index].id)

    ctx = multiprocessing.get_context("spawn")
    pool = concurrent.futures.ProcessPoolExecutor(max_workers=jobs - 1, mp_context=ctx, initializer=_init_worker,
                                                  initargs=(job,))
    # Pieces go to the workers only once one has started: queued behind a worker's start-up they could keep this
    # process waiting at the end for as long as the start-up takes (10 s on a busy machine).
    started = pool.submit(_warm_worker)
    try:
        while pending or running:
            for fut in [f for f in running if f.done()]:
                finished(fut, running.pop(fut))
            # the last pending piece is this process's own, so it never idles while workers start
            # (a pool that could not start leaves every piece to this process)
            while (started.done() and started.exception() is None and pending[_MAIN_TAKES_PIECES:]
                   and len(running) < 2 * (jobs - 1)):
                index = pending.pop()
                running[pool.submit(_build_in_worker, index)] = index
            if _MAIN_TAKES_PIECES:
                if pending:
                    index = pending.pop(0)
                    records[index] = build_record(job, index)
                    if progress:
                        progress(len(records), n, records[index].id)
                    continue
                # nothing left here: take back what no worker has started
                pending += [running.pop(f) for f in [f for f in running if f.cancel()]]
                if pending:
                    continue
            if not (pending or running):
                break
            if not running and started.done():  # pieces left that only workers take, and no worker started
                raise GeometryError(f"compose: the worker processes did not start ({started.exception()}); "
                                    f"try --jobs 1")
            concurrent.futures.wait(list(running) or [started], return_when=concurrent.futures.FIRST_COMPLETED)
    finally:
        # without waiting for workers still starting: they exit when they find the pool shut
        pool.shutdown(wait=False, cancel_futures=True)
    return records
