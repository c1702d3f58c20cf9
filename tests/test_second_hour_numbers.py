"""Issue 68's smaller input checks: a spike in a pose file is named, sim-path says it does not
use the file's clock, a NaN in calib.txt is named, and a stereo folder with both image layouts
is refused."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from gslam_jax.config import Config
from gslam_jax.datasets.kitti import read_kitti_calib
from gslam_jax.datasets.reading import pose_jump
from gslam_jax.datasets.registry import Source, get_source
from gslam_jax.datasets.sim_path import path_notes, read_path
from gslam_jax.datasets.stereo import find_pairs
from gslam_jax.errors import DatasetError
from gslam_jax.vo.calib import CalibrationError

KITTI = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-stereo-51"


def _kitti_lines(xz: np.ndarray, times: bool = False) -> str:
    """KITTI pose lines (identity rotation) at camera positions x, z (y = 0)."""
    rows = []
    for k, (x, z) in enumerate(xz):
        pose = [1, 0, 0, x, 0, 1, 0, 0.0, 0, 0, 1, z]
        rows.append(" ".join(str(v) for v in ([0.1 * k] if times else []) + pose))
    return "\n".join(rows) + "\n"


def test_a_spike_in_a_trajectory_file_is_named_by_line(tmp_path):
    xz = np.column_stack([np.zeros(40), np.arange(40.0)])
    xz[17, 0] = 1000.0  # one pose 1 km to the side
    path = tmp_path / "spike.txt"
    path.write_text("# a comment line\n" + _kitti_lines(xz))
    notes = path_notes(path, read_path(path))
    assert len(notes) == 1 and notes[0].startswith(f"{path}:19: pose 17 is 1000.0 m from the "
                                                   "one before, where the median step is 1 m")
    assert "(1 more such steps)" in notes[0]
    clean = tmp_path / "clean.txt"
    clean.write_text(_kitti_lines(np.column_stack([np.zeros(40), np.arange(40.0)])))
    assert path_notes(clean, read_path(clean)) == []
    # a vehicle that stands still for a while is no spike
    assert pose_jump(np.r_[np.zeros((30, 2)), np.column_stack([np.arange(9.0), np.zeros(9)])],
                     np.arange(39) + 1, "still") is None


def test_sim_path_says_it_does_not_use_the_files_clock(tmp_path):
    xz = np.column_stack([np.zeros(40), np.arange(40.0)])
    path = tmp_path / "timed.txt"
    path.write_text(_kitti_lines(xz, times=True))
    notes = path_notes(path, read_path(path))
    assert len(notes) == 1
    assert "the file's clock (3.9 s for 39 m, 10.00 m/s on average) is not used" in notes[0]
    assert "up to 0.8 m/s" in notes[0]


@pytest.mark.skipif(not (KITTI / "sequences").is_dir(), reason=f"no KITTI clip at {KITTI}")
def test_the_kitti_source_notes_a_spike_in_its_ground_truth(tmp_path, capsys):
    seq = tmp_path / "sequences" / "seq1"
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True)
        for t in range(6):
            shutil.copy(KITTI / "sequences" / "seq1" / cam / f"{t:06d}.png", seq / cam)
    shutil.copy(KITTI / "sequences" / "seq1" / "calib.txt", seq)
    poses = np.loadtxt(KITTI / "poses" / "seq1.txt")
    poses[30, 3] += 1000.0  # beyond the frames read: not this run's truth
    (tmp_path / "poses").mkdir()
    np.savetxt(tmp_path / "poses" / "seq1.txt", poses)
    source = Source(source="kitti", path=tmp_path, max_frames=6)
    get_source("kitti").load(source, Config(), None)
    assert "note:" not in capsys.readouterr().out
    poses[3, 3] += 1000.0
    np.savetxt(tmp_path / "poses" / "seq1.txt", poses)
    get_source("kitti").load(source, Config(), None)
    out = capsys.readouterr().out
    assert f"note: {tmp_path / 'poses' / 'seq1.txt'}:4: pose 3 is 1000.0 m from the one " in out
    assert "as the ground truth that scores this run" in out


def test_nan_in_calib_txt_is_named(tmp_path):
    good = ("P0: 700 0 600 0 0 700 180 0 0 0 1 0\n"
            "P1: 700 0 600 -380 0 700 180 0 0 0 1 0\n")
    path = tmp_path / "calib.txt"
    path.write_text(good.replace("-380", "nan"))
    with pytest.raises(CalibrationError, match=r"calib.txt: field 'P1' number 4 of 12 is nan"):
        read_kitti_calib(path, (1226, 370))
    path.write_text(good)
    assert read_kitti_calib(path, (1226, 370)).baseline == pytest.approx(380 / 700)


def test_a_stereo_folder_with_both_layouts_is_refused(tmp_path):
    for name in ("left", "right", "image_0", "image_1"):
        (tmp_path / name).mkdir()
    with pytest.raises(DatasetError, match=r"holds both left/ right/ and image_0/ image_1/"):
        find_pairs(tmp_path)
    (tmp_path / "image_1").rmdir()
    with pytest.raises(DatasetError, match=r"holds both"):
        find_pairs(tmp_path)
