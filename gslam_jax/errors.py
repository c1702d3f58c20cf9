"""The base of every error that reports bad input (a file, field, frame or option).

``gslam`` catches ``InputError`` and prints its message instead of a traceback; each module
raises its own subclass (``ConfigError``, ``RunError``, ``GpsLogError``, ...), whose message
names the file, field or frame at fault. Light on purpose: no JAX, no OpenCV.
"""

from __future__ import annotations

__all__ = ["InputError", "DatasetError", "RunError"]


class InputError(ValueError):
    """Bad input from the user: the message says what and where."""


class DatasetError(InputError):
    """A dataset's file (frame list, times, poses, IMU or ground-truth log) is unusable; the
    message names the file and, where known, the line or frame."""


class RunError(InputError):
    """A Run (or a Run file) is malformed; the message names the file, field and frame."""
