"""The base of every error that reports bad input (a file, field, frame or option).

``gslam`` catches ``InputError`` and prints its message instead of a traceback; each module
raises its own subclass (``ConfigError``, ``RunError``, ``GpsLogError``, ...), whose message
names the file, field or frame at fault. The public Python API (``gslam_jax.Online``,
``simulate_run``, ...) checks its arguments with the helpers here and raises ``ArgumentError``
naming the function, the argument and why, as the command line names an option. Light on
purpose: no JAX, no OpenCV (NumPy only inside the helpers).
"""

from __future__ import annotations

import numbers
from typing import Any

__all__ = ["InputError", "DatasetError", "RunError", "ArgumentError", "integer_argument",
           "number_argument", "array_argument"]


class InputError(ValueError):
    """Bad input from the user: the message says what and where."""


class DatasetError(InputError):
    """A dataset's file (frame list, times, poses, IMU or ground-truth log) is unusable; the
    message names the file and, where known, the line or frame."""


class RunError(InputError):
    """A Run (or a Run file) is malformed; the message names the file, field and frame."""


class ArgumentError(InputError):
    """A bad argument to a public function; the message names the function, the argument
    and why (e.g. "simulate_run: seed must be an integer in [0, 2^32), got -1")."""


def integer_argument(value: Any, where: str, low: int = 0, high: int | None = None,
                     bounds: str | None = None) -> int:
    """``value`` as an int in [low, high) (None: no upper bound), else ArgumentError naming
    ``where`` ("function: argument"); a bool or a fractional number is refused, not rounded.
    ``bounds`` describes the range in the message (default "an integer >= low" or "in [low,
    high)")."""
    bounds = bounds or (f"an integer >= {low}" if high is None else
                        f"an integer in [{low}, {high})")
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ArgumentError(f"{where} must be {bounds}, got {value!r} "
                            f"({type(value).__name__})")
    if value < low or (high is not None and value >= high):
        raise ArgumentError(f"{where} must be {bounds}, got {value}")
    return int(value)


def number_argument(value: Any, where: str) -> float:
    """``value`` as a finite float, else ArgumentError naming ``where``."""
    import math

    if isinstance(value, bool) or not isinstance(value, numbers.Real) or \
            not math.isfinite(float(value)):
        raise ArgumentError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def array_argument(value: Any, where: str, shape: tuple[int | None, ...], what: str):
    """``value`` as a float64 NumPy array of ``shape`` (None: any length on that axis) with
    finite entries, else ArgumentError naming ``where`` and ``what`` it should hold (e.g. "3
    numbers (dx, dy, dtheta)")."""
    import numpy as np

    try:
        array = np.asarray(value)
        array = array.astype(np.float64) if array.dtype.kind in "iuf" else None
    except (TypeError, ValueError):  # ragged nested lists
        array = None
    if array is None:
        raise ArgumentError(f"{where} must be {what} (real numbers), got {value!r:.80}")
    if array.ndim != len(shape) or any(n is not None and n != m
                                       for n, m in zip(shape, array.shape)):
        want = "[" + ", ".join("N" if n is None else str(n) for n in shape) + "]"
        raise ArgumentError(f"{where} must be {what}, shape {want}, got shape "
                            f"{list(array.shape)}")
    if not np.isfinite(array).all():
        at = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
        raise ArgumentError(f"{where} must be finite, got {array[at]} at index "
                            f"{at[0] if len(at) == 1 else at}")
    return array
