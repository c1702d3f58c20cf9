"""Test-session set-up: no persistent compilation cache, crashed workers end the run, file order.

No persistent JAX compilation cache by default, in the test processes or in the ``gslam``
commands they start (``GSLAM_JAX_CACHE`` is set empty for those). Reading a cached program
once crashed an xdist worker in CI (a segmentation fault in the executable's deserialisation),
and the cache did not pay for itself: the whole suite took about as long without it
(docs/notebook/test-suite.md has the figures). ``GSLAM_TEST_JAX_CACHE=DIR`` turns it on in
DIR, for this process and every subprocess; a cache the user set
(``JAX_COMPILATION_CACHE_DIR``) is left as it is.

XLA's CPU compiler runs with its classic loop emitters (``--xla_cpu_use_fusion_emitters=false``
added to ``XLA_FLAGS``, for this process and every subprocess). Compilation is most of the
suite's time, and this about halves it; the compiled programs compute the same IEEE
operations and run slower, but the suite as a whole is faster (docs/notebook/test-suite.md
has the figures).
The flag is added only where a probe shows the installed jaxlib accepts it (an unknown flag
aborts the process); ``GSLAM_TEST_XLA_DEFAULTS=1`` keeps XLA's defaults, as ``gslam`` uses them.

A worker that crashes ends the run (``--max-worker-restart 0``) with the test it ran named:
with ``--dist loadfile``, pytest-xdist's replacement worker can wait forever for work (its
issues 784 and 1378), so a crash would otherwise hold CI until its time limit.

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

import os
import subprocess
import sys


def _cache_dir() -> str:
    """The folder of ``GSLAM_TEST_JAX_CACHE``; empty when it is unset or empty (no cache)."""
    return os.environ.get("GSLAM_TEST_JAX_CACHE", "").strip()


# Environment variables, before JAX is imported: this process and every subprocess read them.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    if _cache_dir():
        os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache_dir()
        os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")
        os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    else:
        os.environ.setdefault("GSLAM_JAX_CACHE", "")  # and no user cache in ``gslam`` commands


CLASSIC_EMITTERS = "--xla_cpu_use_fusion_emitters=false"


def _xla_accepts(flag: str) -> bool:
    """Whether a JAX process starts and computes with ``flag`` added to ``XLA_FLAGS`` (XLA
    aborts on a flag it does not know, so it is tried in a subprocess first)."""
    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip(),
               JAX_PLATFORMS="cpu")
    probe = "import jax.numpy as jnp; jnp.exp(jnp.arange(3.0)).block_until_ready()"
    try:
        done = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                              timeout=120)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


# Every worker inherits the controller's environment, so only the first process probes.
if (not os.environ.get("GSLAM_TEST_XLA_DEFAULTS", "").strip()
        and "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", "")
        and _xla_accepts(CLASSIC_EMITTERS)):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {CLASSIC_EMITTERS}".strip()


def pytest_configure(config) -> None:
    """Keep the collection order below as the order pytest-xdist hands out files
    (``--no-loadscope-reorder``; by default it orders them by number of tests alone), and end
    the run at a worker's crash (``--max-worker-restart 0`` unless given)."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False
    if getattr(config.option, "maxworkerrestart", "") is None:
        config.option.maxworkerrestart = 0


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
