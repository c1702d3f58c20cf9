"""experiments/headline.py, the script behind the headline results page: its arguments, the
commit it names, and its cheapest section (the default run, cut to a few frames and particles)
through to the files ``--out`` writes."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import pytest

from experiments import headline

ROOT = Path(__file__).resolve().parents[1]


def test_arguments_default_to_every_section_and_refuse_unknown_ones() -> None:
    args = headline.parse_args([])
    assert args.sections == list(headline.SECTIONS) == list(headline.RUNNERS)
    assert args.out is None and args.kitti_seeds == 16 and args.table1_particles == 200
    args = headline.parse_args(["--sections", "kitti", "table1", "--table1-seeds", "0", "4",
                                "--out", "figs"])
    assert args.sections == ["kitti", "table1"] and args.table1_seeds == [0, 4]
    assert args.out == Path("figs")
    with pytest.raises(SystemExit):
        headline.parse_args(["--sections", "everything"])


def test_commit_is_the_checkouts_head() -> None:
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True)
    if head.returncode != 0:
        pytest.skip("not a git checkout")
    commit = headline.git_commit()
    assert commit.removesuffix("+dirty") == head.stdout.strip()
    assert headline.git_commit(Path("/")) == "unknown"


def test_real_data_sections_skip_without_their_clip(tmp_path: Path) -> None:
    args = headline.parse_args(["--data", str(tmp_path / "nowhere")])
    for name in ("kitti", "euroc"):
        section = headline.RUNNERS[name](args, tmp_path)
        assert "not found" in section["skipped"]
        assert "Skipped:" in headline.markdown(section)


def test_page_is_written_between_its_markers_only() -> None:
    page = ("# Results\nprose before\n<!-- headline:kitti -->\nold table\n"
            "<!-- /headline:kitti -->\nprose after\n")
    new = headline.between_markers(page, "kitti", "| a | b |\n")
    assert new == ("# Results\nprose before\n<!-- headline:kitti -->\n| a | b |\n"
                   "<!-- /headline:kitti -->\nprose after\n")
    with pytest.raises(ValueError, match="headline:table1"):
        headline.between_markers(page, "table1", "x")


def test_the_results_page_has_every_sections_markers() -> None:
    page = (ROOT / "docs" / "results.md").read_text()
    for name in ("generated", *headline.SECTIONS):
        headline.between_markers(page, name, "")


def test_default_section_on_a_few_frames_writes_its_figures(tmp_path: Path, capsys) -> None:
    out = tmp_path / "figures"
    assert headline.main(["--sections", "default", "--max-frames", "20", "--particles", "4",
                          "--out", str(out)]) == 0
    report = json.loads((out / "headline.json").read_text())
    assert report["commit"] and report["environment"]["jax"]
    figures = report["sections"]["default"]["figures"]
    assert figures["frames"] == 20 and figures["particles"] == 4
    assert math.isfinite(figures["slam_rms_m"]) and figures["vo_rms_m"] > 0
    assert figures["ratio"] == pytest.approx(figures["slam_rms_m"] / figures["vo_rms_m"])
    page = (out / "headline.md").read_text()
    assert "gslam run --max-frames 20 --set filter.particles=4" in page
    assert f"{figures['slam_rms_m']:.3f} m" in page
    assert (out / "default_maps.png").stat().st_size > 0
    printed = capsys.readouterr().out
    assert printed.startswith("# ") and report["commit"] in printed.splitlines()[0]
    assert any(line.strip().startswith("Gamma-SLAM RMS:") for line in printed.splitlines())
