"""How ``run_slam`` holds memory: the filter's scan compiled before the particles' maps exist
(its compiler's working memory returned to the system first), and the C heap handed back."""

from __future__ import annotations

import dataclasses
import platform

import jax
import jax.monitoring
import numpy as np
from synthetic import make_run

from gslam_jax import rbpf
from gslam_jax.config import Config, FilterSection
from gslam_jax.driver import machine, slam


def test_the_scan_is_compiled_once_and_before_the_maps_are_allocated(monkeypatch):
    run, _ = make_run(seed=2, steps=12)
    config = dataclasses.replace(Config(), filter=FilterSection(particles=4,
                                                                unknown_cells="ignore"))
    events: list[str] = []
    init = rbpf.init

    def recording_init(cfg, pose, *args, **kwargs):
        events.append("trace init" if isinstance(pose, jax.core.Tracer) else "allocate maps")
        return init(cfg, pose, *args, **kwargs)

    def on_compile(event: str, seconds: float, **kwargs) -> None:
        if event.endswith("backend_compile_duration") and kwargs.get("fun_name") == \
                "jit(scan_frames)":
            events.append("compile scan")

    monkeypatch.setattr(rbpf, "init", recording_init)
    jax.monitoring.register_event_duration_secs_listener(on_compile)
    try:
        res = slam.run_slam(run, config, chunk=5)  # three chunks: one compilation
    finally:
        jax.monitoring.unregister_event_duration_listener(on_compile)
    assert events == ["trace init", "compile scan", "allocate maps"], events
    assert res.best_pose.shape == (run.num_frames, 3) and np.isfinite(res.best_pose).all()


def test_release_free_heap_calls_malloc_trim_where_glibc_has_it():
    released = machine.release_free_heap()
    assert released == (platform.system() == "Linux" and platform.libc_ver()[0] == "glibc")
