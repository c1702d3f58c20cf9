"""JAX's persistent compilation cache for the ``gslam`` command, on by default.

Every ``gslam`` process compiles the filter's programs; JAX can keep the compiled programs on
disk and load them on the next run with the same programs, flags, JAX version and device (a
hit is the program a fresh compilation gives, so the results are unchanged). ``gslam`` turns
this on in the user's cache folder unless told otherwise:

- ``JAX_COMPILATION_CACHE_DIR`` set (by the user, or by the test suite): left as it is.
- ``GSLAM_JAX_CACHE`` set and empty: no cache. Set to a folder: that folder.
- otherwise ``$XDG_CACHE_HOME/gslam-jax/jax`` (``~/.cache/gslam-jax/jax`` without
  ``XDG_CACHE_HOME``).

The folder is bounded: at start-up the least recently used entries (by their access or
modification time, whichever is later) beyond ``GSLAM_JAX_CACHE_MAX_MB`` megabytes (default
``DEFAULT_MAX_MB``; 0: no cache) are removed. Programs that compiled in under
``MIN_COMPILE_SECONDS`` are not kept (``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``, unless
set). JAX's own bound (``jax_compilation_cache_max_size``) needs the
``filelock`` package, which is not a dependency. Light on purpose (no JAX import): the
variables must be set before JAX is imported.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from pathlib import Path

__all__ = ["CACHE_ENV", "MAX_MB_ENV", "DEFAULT_MAX_MB", "MIN_COMPILE_SECONDS", "cache_folder",
           "prune",
           "enable_compile_cache"]

CACHE_ENV = "GSLAM_JAX_CACHE"
MAX_MB_ENV = "GSLAM_JAX_CACHE_MAX_MB"
DEFAULT_MAX_MB = 1024
_JAX_DIR = "JAX_COMPILATION_CACHE_DIR"
_MIN_COMPILE_ENV = "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"
MIN_COMPILE_SECONDS = "0.2"  # programs compiled faster than this are not kept


def cache_folder(environ: MutableMapping[str, str] | None = None) -> Path | None:
    """The folder ``gslam`` caches compiled programs in, by the rules of the module docstring;
    None when ``GSLAM_JAX_CACHE`` is set and empty."""
    env = os.environ if environ is None else environ
    chosen = env.get(CACHE_ENV)
    if chosen is not None:
        return Path(chosen).expanduser() if chosen.strip() else None
    base = env.get("XDG_CACHE_HOME") or str(Path(env.get("HOME") or Path.home()) / ".cache")
    return Path(base).expanduser() / "gslam-jax" / "jax"


def _max_bytes(environ: MutableMapping[str, str]) -> int:
    """``GSLAM_JAX_CACHE_MAX_MB`` in bytes (default ``DEFAULT_MAX_MB``); ValueError naming the
    variable for a value that is not a number >= 0."""
    text = environ.get(MAX_MB_ENV, "").strip()
    if not text:
        return DEFAULT_MAX_MB * 1_000_000
    try:
        mb = float(text)
    except ValueError:
        mb = -1.0
    if not mb >= 0 or mb == float("inf"):
        raise ValueError(f"{MAX_MB_ENV}={text!r}: expected a number of megabytes >= 0")
    return int(mb * 1_000_000)


def prune(folder: Path, max_bytes: int) -> int:
    """Remove the least recently used files of ``folder`` until at most ``max_bytes`` remain;
    returns the number removed. Files that vanish or cannot be removed are skipped."""
    entries = []
    for path in folder.iterdir():
        try:
            st = path.stat()
        except OSError:
            continue
        if path.is_file():
            entries.append((max(st.st_atime, st.st_mtime), st.st_size, path))
    total = sum(size for _, size, _ in entries)
    removed = 0
    for _, size, path in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        try:
            path.unlink()
        except OSError:
            continue
        total -= size
        removed += 1
    return removed


def enable_compile_cache(environ: MutableMapping[str, str] | None = None) -> Path | None:
    """Point JAX's persistent cache at ``cache_folder`` (through ``environ``, default
    ``os.environ``, before JAX is imported) and prune it to its bound; returns the folder, or
    None when the cache is off, the user chose JAX's own folder, or the folder cannot be made
    (the run goes on without a cache)."""
    env = os.environ if environ is None else environ
    if env.get(_JAX_DIR):
        return None
    folder = cache_folder(env)
    if folder is None:
        return None
    max_bytes = _max_bytes(env)
    if max_bytes == 0:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        prune(folder, max_bytes)
    except OSError:
        return None
    env[_JAX_DIR] = str(folder)
    # JAX's default keeps only programs that took a second to compile; the filter's smaller
    # ones add up too (the test suite's conftest uses the same bound)
    env.setdefault(_MIN_COMPILE_ENV, MIN_COMPILE_SECONDS)
    return folder
