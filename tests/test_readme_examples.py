"""The README's worked examples, one per input kind, run as written (on a few frames): the
simulator, the KITTI and EuRoC folders (where ../shared/data has them), the bag (its line is
the one tests/test_rosbag.py runs on a written bag), the own-rig script (run by
tests/test_example_own_rig.py) and the live API's Python block."""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
import shlex
from pathlib import Path

import pytest

from gslam_jax.app.cli import main

ROOT = Path(__file__).resolve().parents[1]
FEW = ["--set", "filter.particles=4"]


def _section() -> str:
    text = (ROOT / "README.md").read_text()
    start = text.index("## Worked examples, one per input kind")
    return text[start:text.index("\n## ", start + 1)]


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", _section(), flags=re.S)


def _commands() -> list[list[str]]:
    (bash,) = _blocks("bash")
    return [shlex.split(line, comments=True) for line in bash.splitlines() if line.strip()]


def _example(*words: str) -> list[str]:
    found = [c for c in _commands() if all(w in c for w in words)]
    assert len(found) == 1, f"one README example with {words}"
    return found[0]


def test_every_input_kind_has_one_example() -> None:
    commands = _commands()
    sources = [c[c.index("--source") + 1] if "--source" in c else c[1] for c in commands]
    assert sources == ["run", "kitti", "euroc", "rosbag", "examples/own_rig.py"]
    assert "gslam_jax.Online" in _blocks("python")[0]


def _run(args: list[str], out: Path, frames: int) -> dict:
    """``gslam ARGS`` with the example's paths from the repository root, --out in ``out``."""
    args = [str(ROOT / a) if a.startswith("../") else a for a in args[1:]]
    args[args.index("--out") + 1] = str(out)
    with contextlib.redirect_stdout(io.StringIO()):
        assert main([*args, "--max-frames", str(frames), *FEW]) == 0
    return json.loads((out / "summary.json").read_text())


def test_simulator_example(tmp_path: Path) -> None:
    summary = _run(_example("--course"), tmp_path / "sim", 40)
    assert summary["frames"] == 40
    assert math.isfinite(summary["slam_rms_m"]) and summary["gt_distance_m"] > 1.0


@pytest.mark.parametrize("source, frames", [("kitti", 6), ("euroc", 6)])
def test_dataset_folder_example(source: str, frames: int, tmp_path: Path) -> None:
    args = _example(source)
    data = ROOT / args[args.index("--path") + 1]
    if not data.is_dir():
        pytest.skip(f"real frames not found at {data} (see shared/data/README.md)")
    summary = _run(args, tmp_path / source, frames)
    assert summary["frames"] == frames and math.isfinite(summary["slam_rms_m"])


def test_bag_example_is_the_one_the_bag_tests_run() -> None:
    pytest.importorskip("rosbags")
    from test_rosbag import _readme_bag_example

    assert ["gslam", *_readme_bag_example()] == _example("rosbag")


def test_own_rig_example_is_run_by_its_test() -> None:
    (script,) = [a for a in _example("examples/own_rig.py") if a.endswith(".py")]
    assert (ROOT / script).is_file()
    assert "own_rig.py" in (ROOT / "tests" / "test_example_own_rig.py").read_text()


def test_live_example(capsys) -> None:
    (code,) = _blocks("python")
    assert "max_frames=100" in code
    scope: dict = {}
    exec(compile(code.replace("max_frames=100", "max_frames=30"), "README.md", "exec"), scope)
    estimate, run = scope["estimate"], scope["run"]
    assert run.num_frames == 30
    assert math.hypot(*(estimate.pose[:2] - run.ground_truth[-1, :2])) < 0.5
    assert capsys.readouterr().out.strip()
