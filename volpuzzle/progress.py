"""What a build shows while it runs (Progress) and how long each stage took (Timer, for report.json timings_s)."""

import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

from . import stop


class Progress:
    """Stage and piece progress on a terminal; silent when stderr is not a terminal (CI, pipes)."""

    def __init__(self, enabled=None):
        if enabled is None:
            enabled = sys.stderr.isatty() and not os.environ.get("VOLPUZZLE_NO_PROGRESS")
        self.enabled = enabled

    def stage(self, name):
        if self.enabled:
            print(f"\r\033[K{name} ...", end="", file=sys.stderr, flush=True)

    def piece(self, i, n, piece_id):
        if self.enabled:
            print(f"\r\033[Kcompose {i}/{n} {piece_id}", end="", file=sys.stderr, flush=True)

    def done(self):
        if self.enabled:
            print("\r\033[K", end="", file=sys.stderr, flush=True)


@dataclass
class Timer:
    timings: dict = field(default_factory=dict)

    @contextmanager
    def __call__(self, name, progress=None):
        if progress is not None:
            progress.stage(name)
        stop.check()  # every stage begins and ends with a look for a stop that a library swallowed
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = round(self.timings.get(name, 0.0) + time.perf_counter() - t0, 3)
        stop.check()
