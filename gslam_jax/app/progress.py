"""A console progress bar for long work (simulation, front-end, filter, search, tuning).

Hand-written rather than tqdm: it needs only ``progress(done, total)`` callbacks, writes one
final line when stderr is not a terminal (a log file stays readable), and adds no dependency.
"""

from __future__ import annotations

import sys
import time

__all__ = ["ProgressBar"]


class ProgressBar:
    """A one-line console progress bar on stderr; when stderr is not a terminal (a log file, a
    pipe) only one final line is written."""

    def __init__(self, label: str, stream=None):
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        isatty = getattr(self.stream, "isatty", None)
        self.tty = bool(isatty()) if callable(isatty) else False
        self.start = time.perf_counter()
        self.last = -1.0
        self.finished = False

    def __call__(self, done: int, total: int) -> None:
        now = time.perf_counter()
        if not self.tty:
            if done >= total and not self.finished:
                self.finished = True
                self.stream.write(f"{self.label}: {done}/{total} in {now - self.start:.1f}s\n")
                self.stream.flush()
            return
        if done < total and now - self.last < 0.2:
            return
        self.last = now
        frac = done / max(total, 1)
        bar = "#" * int(30 * frac)
        end = "\n" if done >= total else ""
        self.stream.write(f"\r{self.label} [{bar:<30}] {done}/{total} "
                          f"{now - self.start:6.1f}s{end}")
        self.stream.flush()
