"""A stop the user asked for (SIGTERM or Ctrl-C), remembered as well as raised.

Raised alone it can be lost: trimesh catches every exception (`except BaseException`) in many places, and a signal
that lands inside one of them is swallowed there, so the build would run on and write its output. The stop is
therefore also kept here, and `check()` raises it again at each stage, each piece and before the output folder is
put in place."""

from __future__ import annotations

import signal


class Terminated(BaseException):
    """SIGTERM, raised where the program is, so that it unwinds like Ctrl-C (a BaseException, like
    KeyboardInterrupt, so no `except Exception` swallows it)."""


_asked: type[BaseException] | None = None


def ask(kind: type[BaseException]) -> None:
    """Remember a stop of this kind and raise it here."""
    global _asked
    _asked = kind
    raise kind()


def check() -> None:
    """Raise the stop asked for, if any (again, when a library swallowed the first raise)."""
    if _asked is not None:
        raise _asked()


def install() -> dict | None:
    """SIGTERM -> Terminated and Ctrl-C -> KeyboardInterrupt, both remembered. -> the previous handlers, for
    restore(); None when not on the main thread (e.g. a test runner's worker), where signals are left alone."""
    handlers = {signal.SIGTERM: lambda _signum, _frame: ask(Terminated),
                signal.SIGINT: lambda _signum, _frame: ask(KeyboardInterrupt)}
    previous = {}
    try:
        for signum, handler in handlers.items():
            previous[signum] = signal.signal(signum, handler)
    except ValueError:
        restore(previous)
        return None
    return previous


def restore(previous: dict | None) -> None:
    """Put back the handlers install() replaced and forget any stop asked for."""
    global _asked
    _asked = None
    for signum, handler in (previous or {}).items():
        if handler is not None:  # None: a handler not set from Python, which cannot be put back from it
            signal.signal(signum, handler)
