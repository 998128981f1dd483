"""What a build shows while it runs: its progress line (Progress), its warnings (warn) on lines of their own, and how
long each stage took (Timer, for report.json timings_s)."""

import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

from . import stop

_line_open = False  # a progress line is on the terminal, not yet ended by a newline


def show_line(text: str) -> None:
    """Replace the progress line on stderr with text (no newline: the next one overwrites it)."""
    global _line_open
    print(f"\r\033[K{text}", end="", file=sys.stderr, flush=True)
    _line_open = True


def end_line() -> None:
    """Clear a progress line left on the terminal, so that what is printed next starts a line of its own (a warning,
    or the one-line message of an error or a stop)."""
    global _line_open
    if _line_open:
        print("\r\033[K", end="", file=sys.stderr, flush=True)
        _line_open = False


def warn(message: str) -> None:
    """"warning: message" on stderr, on a line of its own: the one way the stages tell the user of a warning."""
    end_line()
    print(f"warning: {message}", file=sys.stderr, flush=True)


class Progress:
    """Stage and piece progress on a terminal; silent when stderr is not a terminal (CI, pipes)."""

    def __init__(self, enabled=None):
        if enabled is None:
            enabled = sys.stderr.isatty() and not os.environ.get("VOLPUZZLE_NO_PROGRESS")
        self.enabled = enabled

    def stage(self, name):
        if self.enabled:
            show_line(f"{name} ...")

    def piece(self, i, n, piece_id):
        if self.enabled:
            show_line(f"compose {i}/{n} {piece_id}")

    def done(self):
        end_line()


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
