"""The compose stage: every cell of the tiling -> Piece, serially or on the process pool when it pays."""

from .pool import _WORKER, _build_in_worker, _init_worker, _piece_from, _pooled, _use_pool
from .sampling import sample_parameters


class Pieces(list):
    """The pieces in cell-index order, with the Sampling they were built on (.sampling.max_error_mm for the report)
    and the build time of each piece in seconds (.seconds, by piece id)."""

    sampling = None
    seconds = None


def compose(tiling, fmap, joints, tolerance, jobs=1, progress=None, sampling=None, face_clearance=0.0):
    """Every cell -> Piece, in cell-index order (a list, with .sampling and .seconds). jobs > 1 builds in a process
    pool when the work is large enough to pay for one (same results as jobs=1); progress(i, n, piece_id) is called
    as pieces finish. Pass `sampling` to reuse one from sample_parameters. face_clearance (mm): the gap left
    between mating cut faces, half on each side."""
    sampling = sampling if sampling is not None else sample_parameters(tiling, fmap, tolerance)
    order = sorted(tiling.cells)
    n = len(order)
    joints = list(joints or [])
    recs = {}
    if not _use_pool(jobs, n, sampling, joints):
        _init_worker(tiling, sampling, fmap, joints, face_clearance)
        try:
            for k, index in enumerate(order):
                recs[index] = _build_in_worker(index)
                if progress:
                    progress(k + 1, n, recs[index][0])
        finally:
            _WORKER.clear()
    else:
        recs = _pooled(order, int(jobs), tiling, sampling, fmap, joints, progress, face_clearance)
    out = Pieces(_piece_from(recs[index]) for index in order)
    out.sampling = sampling
    out.seconds = {recs[index][0]: recs[index][6] for index in order}
    return out
