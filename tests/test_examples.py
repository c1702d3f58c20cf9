"""The scripts of examples/ run (on short runs, GSLAM_EXAMPLE_FRAMES) and print what they
promise: SLAM and VO errors, the live estimate and its latency, an alignment near the truth."""

from __future__ import annotations

import re
import runpy
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

pytestmark = pytest.mark.slow  # long-running: scheduled first (tests/conftest.py)


def _run(name: str, frames: int, monkeypatch, capsys) -> str:
    monkeypatch.setenv("GSLAM_EXAMPLE_FRAMES", str(frames))
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    return capsys.readouterr().out


# batch.py and merge.py both map mars-yard-a (seed 0) with 16 particles: on as many frames, the
# merge example's first run_slam reuses the filter the batch example compiled.
MERGE_FRAMES = 50
# The merge example itself maps 40 frames: its maps' known cells then fit one bucket of 128
# cells at the search's coarse level (8 x 8 cells), where 50 frames' took two, and each of its
# two coarse searches (B onto A, and the mutual check's A onto B) costs half as much.
MERGE_EXAMPLE_FRAMES = 40


def test_batch_example(monkeypatch, capsys):
    out = _run("batch.py", MERGE_FRAMES, monkeypatch, capsys)
    assert re.search(rf"loaded simulated course mars-yard-a \(seed 0\): {MERGE_FRAMES} frames",
                     out)
    slam, vo = map(float, re.search(r"SLAM ([\d.]+) m, VO only ([\d.]+) m", out).groups())
    assert slam < 1.0 and vo < 1.0
    assert int(re.search(r"cells of 0.16 m, (\d+) known", out).group(1)) > 1000


def test_live_example(monkeypatch, capsys):
    out = _run("live.py", 60, monkeypatch, capsys)
    errors = [float(e) for e in re.findall(r"error ([\d.]+) m", out)]
    assert re.search(r"frame   59:", out) and max(errors) < 1.0
    assert re.search(r"16 particles; map \d+ x \d+ cells", out)
    rtf = float(re.search(r"real-time factor ([\d.]+)", out).group(1))
    assert rtf > 0


def test_merge_example(monkeypatch, capsys):
    out = _run("merge.py", MERGE_EXAMPLE_FRAMES, monkeypatch, capsys)
    metres, degrees = map(float, re.search(r"alignment error: ([\d.]+) m, ([\d.]+) deg",
                                           out).groups())
    assert metres < 0.3 and degrees < 2.0
    merged, a, b = map(int, re.search(r"merged map: (\d+) known cells \(A (\d+), B (\d+)\)",
                                      out).groups())
    assert max(a, b) <= merged <= a + b
