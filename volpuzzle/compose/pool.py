"""Pieces built in parallel: this process and spawned worker processes together, each piece by the same function,
so where a piece is built does not change it."""

import time
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
import trimesh

from . import ahead
from .piece import Piece, build_piece

# Without the build's pool (compose called on its own, as mesh mode and the tests do) a pool is started for compose
# alone. A spawned worker costs ~2.5 s of CPU (imports, pickling) before it builds anything. This process keeps
# building meanwhile, but on a busy machine the start-up takes 10 s of wall time, and the pieces handed to the
# workers then can hold up the end: measured with the 256-piece twisted torus (compose ~2.7 CPU s) a pool of its own
# was slower than serial, so serial below this estimate.
_POOL_MIN_PIECES = 16
_POOL_MIN_SECONDS = 5.0
_SECONDS_PER_TRIANGLE = 1e-5  # building, checking and converting one piece triangle (measured, 2 cores, loaded)
_SECONDS_PER_JOINT = 0.005  # the booleans of one pin and its hole


@dataclass(frozen=True, eq=False)
class BuildJob:
    """What every piece is built from: the Tiling, the Sampling of its faces, the Map F, the Joint list and the face
    clearance in mm. Read once by each worker (Workers.map_pieces' shared input)."""

    tiling: object
    sampling: object
    fmap: object
    joints: list
    face_clearance: float
    ahead: str | None = None  # the token of the surfaces a worker made ahead (compose.ahead), if any

    @cached_property
    def _joints_by_cell(self):
        from ..joint import cell_joints

        return cell_joints(self.joints)

    def joints_of(self, index):
        """The joints of cell `index` (pin or hole side), in list order: a piece looks at its own few, not every
        joint of the puzzle (about 1 ms a piece at 1024 pieces)."""
        return self._joints_by_cell.get(tuple(index), [])


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


def build_record(job, index):
    """Cell `index` of the job -> _PieceRecord."""
    t0 = time.perf_counter()
    p = build_piece(job.tiling.cell(index), job.sampling, job.fmap, job.joints_of(index),
                    face_clearance=job.face_clearance, surface=ahead.surface(job.ahead, index, job.face_clearance))
    return _PieceRecord(p.id, p.cell, np.asarray(p.mesh.vertices), np.asarray(p.mesh.faces), p.volume,
                        p.body_volume, time.perf_counter() - t0)


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


def build_records(order, workers, job, progress):
    """Pieces built by this process, and the workers (volpuzzle.workers.Workers, or None) together -> {cell index:
    _PieceRecord}. This process takes pieces from the front while the workers take them from the back (see
    Workers.map_pieces); the job travels to each worker once. Every piece is built by the same function, so where it
    is built does not change it."""
    from ..workers import map_pieces

    n = len(order)
    done = (lambda k, record: progress(k, n, record.id)) if progress else None
    records = map_pieces(workers, build_record, list(order), shared=job, what="compose", done=done)
    return dict(zip(order, records, strict=True))
