"""Test-session set-up: one persistent JAX compilation cache for the whole session.

Most of the suite's time is XLA compiling the same filter programs again: in each xdist worker,
and in each ``gslam`` command a test runs as a subprocess. JAX's persistent cache keys an
executable on its HLO, the compiler flags, the JAX version and the device, so a hit is the same
program as a fresh compilation, and the numbers are unchanged (the determinism tests compare
bits). The cache goes to ``GSLAM_TEST_JAX_CACHE`` (unset: a folder under the system's temporary
directory; empty: no cache), and is handed to subprocesses through the environment. A cache the
user set (``JAX_COMPILATION_CACHE_DIR``) is left as it is. Compilations under 0.2 s are not
cached: caching every one was faster on two CLI-heavy files (84 s against 93 s) but not on the
whole suite in fresh-clone CI here (951 and 991 s against 904 s).

Markers (registered in pyproject.toml's ``[tool.pytest.ini_options]``):

- ``slow``: a test that compiles or runs the filter at a configuration of its own (seconds to
  tens of seconds of CPU each). For quick local work run the rest:
  ``python -m pytest -q -n auto --dist loadfile -m "not slow"``; the whole suite (the README's
  command) before a commit.

Scheduling: with ``--dist loadfile`` each test file runs on one worker, in the collection order
given here: files with the most ``slow`` tests first, then by number of tests, so that a long
file does not start last and keep one core busy while the other waits.
"""

from __future__ import annotations

import getpass
import os
import tempfile
from pathlib import Path


def _cache_dir() -> str:
    chosen = os.environ.get("GSLAM_TEST_JAX_CACHE")
    if chosen is not None:
        return chosen
    return str(Path(tempfile.gettempdir()) / f"gslam-jax-test-cache-{getpass.getuser()}")


if "JAX_COMPILATION_CACHE_DIR" not in os.environ and _cache_dir():
    # Environment variables, before JAX is imported: this process and every subprocess read them.
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache_dir()
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")


def pytest_configure(config) -> None:
    """Keep the collection order below as the order pytest-xdist hands out files
    (``--no-loadscope-reorder``; by default it orders them by number of tests alone)."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items) -> None:
    """Files with the most ``slow`` tests first, then files with more tests; the tests of a
    file keep their order."""
    slow: dict[str, int] = {}
    count: dict[str, int] = {}
    for item in items:
        path = item.nodeid.split("::")[0]
        count[path] = count.get(path, 0) + 1
        slow[path] = slow.get(path, 0) + (item.get_closest_marker("slow") is not None)
    first = {path: i for i, path in enumerate(count)}

    def rank(item) -> tuple[int, int, int]:
        path = item.nodeid.split("::")[0]
        return -slow[path], -count[path], first[path]
    items.sort(key=rank)
