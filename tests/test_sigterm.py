"""SIGTERM while the filter compiles or runs: the process ends with 143, as a supervisor
(systemd, a ROS launch file, a batch scheduler) expects, leaving no results and no recording.

The signal is sent from inside the ``gslam`` process at a fixed point (during the filter's XLA
compilation: a JAX monitoring event fires when lowering ends, just before it), not after a
delay on the clock, so the test does not depend on the machine's speed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import pytest
from cached_runs import run_file

# Sends SIGTERM 0.2 s into the XLA compilation of the filter's scan (``run_slam`` compiles it
# ahead of the first chunk, ``scan_frames.lower(...).compile()``), then runs gslam.
_DRIVER = textwrap.dedent("""
    import os, signal, sys, threading
    import jax
    from gslam_jax import rbpf
    from gslam_jax.app.cli import console

    armed = []
    scan_frames = rbpf.scan_frames

    def scan_and_arm(*args, **kwargs):
        armed.append(True)
        return scan_frames(*args, **kwargs)

    def lower_and_arm(*args, **kwargs):
        armed.append(True)
        return scan_frames.lower(*args, **kwargs)

    scan_and_arm.lower = lower_and_arm

    def on_event(event, seconds, **kwargs):
        if armed and event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            armed.clear()
            threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGTERM)).start()

    rbpf.scan_frames = scan_and_arm
    jax.monitoring.register_event_duration_secs_listener(on_event)
    sys.argv = ["gslam", *sys.argv[1:]]
    console()
""")


def _gslam_terminated_in_filter(tmp_path, *args: str) -> subprocess.CompletedProcess:
    _, path = run_file(tmp_path / "r.npz")
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["JAX_ENABLE_COMPILATION_CACHE"] = "false"  # a cached program would skip the compile
    return subprocess.run([sys.executable, "-c", _DRIVER, "run", str(path), "--set",
                           "filter.particles=64", "--no-map-check", *args],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)


def test_sigterm_during_the_filter_exits_143_without_a_crash(tmp_path):
    """Before: "terminated (SIGTERM); no results were written", then a segmentation fault in
    the interpreter's teardown with XLA's threads still at work (exit -11 / 139)."""
    done = _gslam_terminated_in_filter(tmp_path, "--out", "o")
    assert done.returncode == 128 + signal.SIGTERM, done.stderr[-3000:]
    assert "terminated (SIGTERM); no results were written" in done.stderr
    assert "Segmentation fault" not in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.npz"]


def test_sigterm_leaves_no_viewer_recording(tmp_path):
    """Before: the recording was written to FILE.rrd as the run went, and a run stopped by
    SIGTERM left a partial one behind although it said that no results were written."""
    pytest.importorskip("rerun")
    done = _gslam_terminated_in_filter(tmp_path, "--out", "o", "--viewer-save", "rec.rrd")
    assert done.returncode == 128 + signal.SIGTERM, done.stderr[-3000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.npz"]
