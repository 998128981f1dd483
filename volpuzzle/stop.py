"""A stop the user asked for (SIGTERM or Ctrl-C), remembered as well as raised.

Raised alone it can be lost: trimesh catches every exception (`except BaseException`) in many places, and Python
cannot let one out of a finalizer (`__del__`, a weakref callback); a signal whose raise lands there is swallowed, and
the build would run on and write its output. The stop is therefore also kept here, and `check()` raises it again at
each stage, each piece and before the output folder is put in place."""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable


class Terminated(BaseException):
    """SIGTERM, raised where the program is, so that it unwinds like Ctrl-C (a BaseException, like
    KeyboardInterrupt, so no `except Exception` swallows it)."""


_asked: type[BaseException] | None = None
_unraisable: Callable | None = None  # the hook install() replaced


def ask(kind: type[BaseException]) -> None:
    """Remember a stop of this kind and raise it here."""
    global _asked
    _asked = kind
    raise kind()


def check() -> None:
    """Raise the stop asked for, if any (again, when the first raise was swallowed)."""
    if _asked is not None:
        raise _asked()


def install() -> dict | None:
    """SIGTERM -> Terminated and Ctrl-C -> KeyboardInterrupt, both remembered. -> the previous handlers, for
    restore(); None when not on the main thread (e.g. a test runner's worker), where signals are left alone."""
    global _unraisable
    handlers = {signal.SIGTERM: lambda _signum, _frame: ask(Terminated),
                signal.SIGINT: lambda _signum, _frame: ask(KeyboardInterrupt)}
    previous: dict = {}
    try:
        for signum, handler in handlers.items():
            previous[signum] = signal.signal(signum, handler)
    except ValueError:
        restore(previous)
        return None
    _unraisable, sys.unraisablehook = sys.unraisablehook, _quiet_after_a_stop
    return previous


def restore(previous: dict | None) -> None:
    """Put back what install() replaced and forget any stop asked for."""
    global _asked, _unraisable
    _asked = None
    if _unraisable is not None:
        sys.unraisablehook, _unraisable = _unraisable, None
    for signum, handler in (previous or {}).items():
        if handler is not None:  # None: a handler not set from Python, which cannot be put back from it
            signal.signal(signum, handler)


def _quiet_after_a_stop(unraisable) -> None:
    """Python prints a stop raised inside a finalizer as "Exception ignored" and goes on, and objects that the stop
    cut short may then fail in their own finalizers (numba's llvmlite objects do). Once a stop is asked these are its
    echoes: the user is told "terminated" alone. Before it, the usual report."""
    if _asked is None:
        (_unraisable or sys.__unraisablehook__)(unraisable)
