"""Facts about the machine: CPU model, usable cores, physical (or container) memory, the
accelerator's memory limit, and the environment printed beside every figure this project reports;
and the one call on the process's memory that goes with them, handing the C heap's free pages
back to the system (``release_free_heap``).

Its own module so that the host driver (``slam``: the map-memory check) and the benchmarks
(``bench``, ``search``, ``table1``, ``tiled.compare``, experiments) read them without importing
each other.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np

__all__ = ["cpu_model", "usable_cpus", "physical_memory", "process_memory_limit",
           "device_memory_limit", "environment", "release_free_heap", "CGROUP_LIMITS",
           "ENV_VARS"]

ENV_VARS = ("XLA_FLAGS", "JAX_PLATFORMS")  # reported when set: they change what is measured


def cpu_model(cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """The CPU model: the first "model name" of ``cpuinfo`` where present (Linux x86), else
    ``platform.processor()`` (empty on Linux), else the machine type."""
    try:
        for line in Path(cpuinfo).read_text(errors="replace").splitlines():
            name, sep, value = line.partition(":")
            if sep and name.strip() == "model name" and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def usable_cpus() -> int | None:
    """Cores this process may run on (its affinity mask), else ``os.cpu_count()``."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count()


def environment() -> dict:
    """Machine and versions, printed beside every figure this project reports: the CPU model,
    the cores the machine has (``cpus``) and those this process may use (``usable_cpus``), and
    ``XLA_FLAGS`` / ``JAX_PLATFORMS`` when set."""
    import cv2
    import optax

    env = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": platform.machine(),
        "processor": cpu_model(),
        "cpus": os.cpu_count(),
        "usable_cpus": usable_cpus(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": jax.lib.__version__ if hasattr(jax.lib, "__version__") else "",
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "optax": optax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
    }
    env.update({k: os.environ[k] for k in ENV_VARS if os.environ.get(k)})
    return env


CGROUP_LIMITS = ("/sys/fs/cgroup/memory.max",                    # cgroup v2
                 "/sys/fs/cgroup/memory/memory.limit_in_bytes")  # cgroup v1


def physical_memory() -> int:
    """Bytes of memory this process may use: physical memory (sysconf), lowered to a container's
    cgroup limit where one is set; a large number where unknown."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 1 << 62
    for path in CGROUP_LIMITS:
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit():  # "max" (v2) means no limit; v1 writes a huge number instead
            total = min(total, int(text))
    return total


def process_memory_limit() -> int | None:
    """Bytes of address space this process may use (``ulimit -v``, RLIMIT_AS), or None when
    unlimited or unknown."""
    try:
        import resource
        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):
        return None
    return None if soft in (resource.RLIM_INFINITY, -1) or soft <= 0 else int(soft)


def device_memory_limit() -> int | None:
    """Bytes the first device reports as its limit (accelerators), or None (CPU backends
    report none or do not implement ``memory_stats``)."""
    try:
        limit = (jax.devices()[0].memory_stats() or {}).get("bytes_limit")
    except Exception:  # noqa: BLE001 - CPU backends may not implement memory_stats
        return None
    return int(limit) if limit else None


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's ``malloc_trim``, or None where the C library has none (macOS, musl)."""
    name = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(name), "malloc_trim", None) if name else None
    except OSError:
        return None


def release_free_heap() -> bool:
    """Return the C heap's free pages to the system (glibc's ``malloc_trim(0)``); False where
    there is no such call. XLA's compiler frees its working memory once a program is built, but
    glibc keeps it mapped as part of the process's resident memory (docs/particle-budget.md,
    "2026-12-07 (night)", has the figures)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
