"""SIGTERM as a clean end of a command, like Ctrl-C.

The default action of SIGTERM ends the process at once and leaves staged outputs behind. While
:func:`sigterm_as_exit` is active, SIGTERM raises :class:`Terminated` (a ``SystemExit`` with
code 143) in the main thread instead, so that every staged output is removed on the way out.
``gslam``'s ``main`` returns 143 for it and the ``gslam`` script then ends the process with
``os._exit``: the interpreter's teardown, with XLA's threads still compiling or running the
filter, can crash (SIGSEGV), and a supervisor would see a crash instead of a termination.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from typing import Iterator

__all__ = ["Terminated", "sigterm_as_exit"]


class Terminated(SystemExit):
    """The command was ended by SIGTERM (exit code 128 + 15)."""


@contextlib.contextmanager
def sigterm_as_exit() -> Iterator[None]:
    """While active, SIGTERM raises :class:`Terminated` in the main thread after saying that
    no results were written. Installed only from the main thread and over the default action
    (a handler of the caller's own, or an enclosing ``sigterm_as_exit``, is kept)."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def terminate(signum: int, frame: object) -> None:
        print("gslam: terminated (SIGTERM); no results were written", file=sys.stderr)
        raise Terminated(128 + signum)

    signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
