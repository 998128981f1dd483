"""The compose stage: every cell of the tiling -> Piece, serially or on the process pool when it pays."""

from .ahead import forget
from .pool import BuildJob, build_records, piece_from, use_pool
from .sampling import sample_parameters


class Pieces(list):
    """The pieces in cell-index order, with the Sampling they were built on (.sampling.max_error_mm for the report)
    and the build time of each piece in seconds (.seconds, by piece id)."""

    sampling = None
    seconds = None


def compose(tiling, fmap, joints, tolerance, jobs=1, progress=None, sampling=None, face_clearance=0.0, workers=None,
            ahead=None):
    """Every cell -> Piece, in cell-index order (a list, with .sampling and .seconds). jobs > 1 builds in a process
    pool when the work is large enough to pay for one (same results as jobs=1); progress(i, n, piece_id) is called
    as pieces finish. Pass `sampling` to reuse one from sample_parameters. face_clearance (mm): the gap left
    between mating cut faces, half on each side. workers: the build's volpuzzle.workers.Workers, used whatever
    the estimate (its start-up is paid already); ahead: the token of the cell surfaces a worker made meanwhile
    (compose.ahead.begin), which that worker uses for the pieces it builds."""
    sampling = sampling if sampling is not None else sample_parameters(tiling, fmap, tolerance)
    order = sorted(tiling.cells)
    n = len(order)
    job = BuildJob(tiling, sampling, fmap, list(joints or []), face_clearance, ahead)
    if workers is not None and n > 1:
        records = build_records(order, workers, job, progress)
    elif use_pool(jobs, n, sampling, job.joints):
        from ..workers import Workers

        with Workers(int(jobs)) as own:
            records = build_records(order, own, job, progress)
    else:
        records = build_records(order, None, job, progress)
    if ahead is not None:  # what the worker made ahead and did not use is let go
        forget(ahead)
        if workers is not None:
            for _ in range(workers.size):
                workers.submit(forget, ahead)
    out = Pieces(piece_from(records[index]) for index in order)
    out.sampling = sampling
    out.seconds = {records[index].id: records[index].seconds for index in order}
    return out
