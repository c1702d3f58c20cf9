"""The Run, everything the filter consumes (``container``: the arrays, their validation and
the native ``.npz`` format), and the checks its validation is made of (``checks``: the limits
float32 poses set, one check per field)."""

from gslam_jax.run.container import (Run, RunError, integrate_controls, known_positions, load_run,
                                     save_run, validate_run)

__all__ = ["Run", "RunError", "integrate_controls", "known_positions", "load_run", "save_run",
           "validate_run"]
