"""The machine line printed beside every figure: CPU model, usable cores, JAX settings."""

import os
import platform
from pathlib import Path

import jax

from gslam_jax.driver import machine


def test_cpu_model_from_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Test CPU @ 3.00GHz\n"
                    "\nprocessor\t: 1\nmodel name\t: Test CPU @ 3.00GHz\n")
    assert machine.cpu_model(info) == "Test CPU @ 3.00GHz"
    assert machine.cpu_model(tmp_path / "absent") == (platform.processor() or platform.machine())
    (tmp_path / "arm").write_text("processor\t: 0\nBogoMIPS\t: 50.00\n")
    assert machine.cpu_model(tmp_path / "arm") == (platform.processor() or platform.machine())


def test_environment_names_the_cpu_cores_and_jax_settings(monkeypatch):
    jax.devices()  # the backend starts before the variables change (XLA reads them at start)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=AVX")
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    env = machine.environment()
    assert env["XLA_FLAGS"] == "--xla_cpu_max_isa=AVX" and "JAX_PLATFORMS" not in env
    assert env["processor"]
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists() and "model name" in cpuinfo.read_text(errors="replace"):
        assert env["processor"] == machine.cpu_model(cpuinfo) != ""
    if hasattr(os, "sched_getaffinity"):
        assert env["usable_cpus"] == len(os.sched_getaffinity(0))
    assert env["cpus"] == os.cpu_count()
    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    env = machine.environment()
    assert env["JAX_PLATFORMS"] == "cpu" and "XLA_FLAGS" not in env


def test_physical_memory_respects_a_container_limit(tmp_path, monkeypatch):
    from gslam_jax.driver import machine

    limit, unlimited = tmp_path / "memory.max", tmp_path / "unlimited"
    limit.write_text("1073741824\n")
    unlimited.write_text("max\n")
    monkeypatch.setattr(machine, "CGROUP_LIMITS", (str(unlimited), str(tmp_path / "absent")))
    free = machine.physical_memory()
    assert free > 1 << 30  # no limit set: the machine's memory (this test needs more than 1 GiB)
    monkeypatch.setattr(machine, "CGROUP_LIMITS", (str(unlimited), str(limit)))
    assert machine.physical_memory() == 1 << 30
