"""Test-session set-up: XLA compiles the tests' programs with its cheaper optimisation level.

The suite is compile-bound: most tests run a small filter once, so compiling it costs more
than running it. Unless ``XLA_FLAGS`` is already set (to test with other flags, or with
XLA's defaults: ``XLA_FLAGS= python -m pytest ...``), the tests, their pytest-xdist workers and
the commands they start as subprocesses (which inherit the environment) compile with
``--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true``: about a
fifth less wall time on a 2-core machine. The programs compute the same things with less
optimised machine code (float rounding may differ in the last bits where operations are
ordered or contracted differently); every process of a test run uses the same flags. Timings
the suite prints are not benchmarks either way (``gslam bench`` and experiments/ are, run
without it).
"""

from __future__ import annotations

import os
import sys

TEST_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"


def pytest_configure(config) -> None:
    if "XLA_FLAGS" in os.environ:
        return
    if "jax" in sys.modules and "jax._src.xla_bridge" in sys.modules:
        # XLA reads its flags when the backend starts; too late to change them here
        return
    os.environ["XLA_FLAGS"] = TEST_XLA_FLAGS
