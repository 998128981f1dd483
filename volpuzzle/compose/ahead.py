"""Compose work begun in a worker while this process places the joints: the Sampling, then the cell surfaces.

Neither needs the joints. The Sampling comes back to this process (a Prefetch). The worker then makes cell surfaces,
the last cells first (map_pieces hands a worker its items from the back of the list), until compose stops it; the
surfaces are then kept both there and here, each process using them for the pieces it builds. At 1024 pieces the
worker finished the sampling ~4 s before the joints were placed and then idled; a cell's surface is ~40 % of its
piece (3.2 of 8 ms), the rest being the joints' Booleans. A surface is cell_surface's, of the same cell, sampling,
map and clearance, wherever it is made, so the pieces do not change.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .sampling import sample_parameters
from .surface import cell_surface

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..workers import Background, Prefetch, Workers

@dataclass
class _Kept:
    """What a process keeps under a build's token: the inputs the surfaces are made from (tiling, map, Sampling; in
    the process that sampled, until its surfaces are made) and the surfaces, {(cell index, clearance): (vertices,
    faces)}."""

    inputs: tuple | None = None
    surfaces: dict = field(default_factory=dict)


_KEPT: dict[str, _Kept] = {}  # token -> _Kept; one build's at a time


@dataclass(frozen=True, eq=False)
class Ahead:
    """What begin() started: the Sampling's Prefetch, the token the surfaces are kept under and the worker's
    Background that makes them (None without a known clearance)."""

    token: str
    sampling: Prefetch
    surfaces: Background | None

    def stop(self) -> None:
        """Stop the worker making surfaces (compose is about to hand it pieces); keep here a copy of those it made,
        for the pieces this process builds."""
        made = self.surfaces.stop() if self.surfaces is not None else None
        if made:
            _KEPT.setdefault(self.token, _Kept()).surfaces.update(made)


def begin(workers: Workers, tiling, fmap, tolerance: float, clearance: float | None) -> Ahead:
    """The Sampling at `tolerance` prefetched in a worker, then, while it would idle, the surfaces of the cells in
    reverse order with `clearance` mm of face clearance (None: no surfaces, the clearance is not known yet)."""
    token = uuid.uuid4().hex
    sampling = workers.prefetch(_sample, token, tiling, fmap, tolerance)
    surfaces = (workers.background(_surfaces, token, float(clearance), sorted(tiling.cells)[::-1])
                if clearance is not None else None)
    return Ahead(token, sampling, surfaces)


def _sample(token, tiling, fmap, tolerance):
    """sample_parameters, its inputs and result kept under `token` in the process that ran it, for _surfaces."""
    sampling = sample_parameters(tiling, fmap, tolerance)
    _KEPT.clear()
    _KEPT[token] = _Kept((tiling, fmap, sampling))
    return sampling


def _surfaces(stopped: Callable[[], bool], token, clearance, cells):
    """In the process that sampled under `token`: cell_surface of each cell in turn, kept, until stopped(). -> the
    surfaces made ({(cell index, clearance): (vertices, faces)}; none in another process). This process uses them
    for the pieces it builds, and the one that stopped it for its own."""
    kept = _KEPT.get(token)
    if kept is None or kept.inputs is None:
        return {}
    tiling, fmap, sampling = kept.inputs
    for index in cells:
        if stopped():
            break
        kept.surfaces[(tuple(index), clearance)] = cell_surface(tiling.cell(index), sampling, fmap, clearance)
    kept.inputs = None  # the build's: not held here any longer
    return dict(kept.surfaces)


def surface(token: str | None, index, clearance: float):
    """The surface made ahead for cell `index` at `clearance` in this process, taken out (vertices, faces), or None."""
    if token is None:
        return None
    kept = _KEPT.get(token)
    if kept is None:
        if _KEPT:  # another build's, done with
            _KEPT.clear()
        return None
    return kept.surfaces.pop((tuple(index), float(clearance)), None)


def forget(token: str) -> None:
    """Drop what was kept under `token` in this process."""
    _KEPT.pop(token, None)
