"""Dataset adapters reject inconsistent input by name: frame numbering, times/poses/IMU/ground-truth
files that do not line up with the frames, unparsable rows, bad calibration; gyro bias removal.
Partial EuRoC logs that real downloads have (ground truth starting late, an IMU log ending a few ms
early, one extra trailing frame in one camera) load, with NaN ground-truth rows and warnings."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

import gslam_jax.datasets.euroc as euroc
import gslam_jax.datasets.kitti as kitti
from gslam_jax.datasets.euroc import EurocParams, euroc_frontend, euroc_rig, read_sensor_yaml
from gslam_jax.datasets.kitti import KittiParams, kitti_frontend, read_kitti_poses
from gslam_jax.vo.calib import CalibrationError, ImageError, RectifiedRig
from gslam_jax.vo.frontend import FrontEndParams

EUROC = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc-v1_01-static-20"


@pytest.fixture()
def captured(monkeypatch) -> dict:
    """Replace the front-end loop of both adapters: record what they would hand it."""
    out: dict = {}

    def fake(load, n, rig, t_robot_cam, times, params, **kw):
        out.update(n=n, rig=rig, times=np.asarray(times), **kw)
        return out

    monkeypatch.setattr(kitti, "run_frontend", fake)
    monkeypatch.setattr(euroc, "run_frontend", fake)
    return out


# --- KITTI -------------------------------------------------------------------------------------

N_KITTI = 6
TIMES = 5.0 + 0.1 * np.arange(N_KITTI) + 0.01 * np.arange(N_KITTI) ** 2


@pytest.fixture()
def kitti_seq(tmp_path: Path) -> Path:
    """Synthetic 6-frame KITTI layout; frame k is at z = k^2 m (so a shift of rows shows)."""
    seq = tmp_path / "sequences" / "00"
    img = np.full((48, 64), 128, np.uint8)
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True)
        for k in range(N_KITTI):
            cv2.imwrite(str(seq / cam / f"{k:06d}.png"), img)
    (seq / "calib.txt").write_text("P0: 100 0 32 0 0 100 24 0 0 0 1 0\n"
                                   "P1: 100 0 32 -50 0 100 24 0 0 0 1 0\n")
    (seq / "times.txt").write_text("".join(f"{t:.6e}\n" for t in TIMES))
    (tmp_path / "poses").mkdir()
    (tmp_path / "poses" / "00.txt").write_text(
        "".join(f"1 0 0 0 0 1 0 0 0 0 1 {k * k}\n" for k in range(N_KITTI)))
    return tmp_path


def _seq(root: Path) -> Path:
    return root / "sequences" / "00"


def test_kitti_valid_sequence_is_unchanged(kitti_seq: Path, captured: dict):
    kitti_frontend(kitti_seq)
    assert captured["n"] == N_KITTI
    np.testing.assert_allclose(captured["times"], TIMES)
    np.testing.assert_allclose(captured["ground_truth"][:, 0], np.arange(N_KITTI) ** 2, atol=1e-9)
    assert captured["rig"].baseline == pytest.approx(0.5)


def test_kitti_gap_in_frame_numbers_is_named(kitti_seq: Path, captured: dict):
    (_seq(kitti_seq) / "image_0" / "000003.png").unlink()
    with pytest.raises(ImageError, match=r"image_0/000003.png: missing \(frames must be consec"):
        kitti_frontend(kitti_seq)
    # A gap after the frames in use does not matter.
    kitti_frontend(kitti_seq, KittiParams(max_frames=3))
    assert captured["n"] == 3


def test_kitti_missing_last_left_image_is_named(kitti_seq: Path, captured: dict):
    (_seq(kitti_seq) / "image_0" / "000005.png").unlink()
    with pytest.raises(ImageError, match=r"image_0/000005.png: missing \(image_1 has it"):
        kitti_frontend(kitti_seq)


def test_kitti_image_name_must_be_a_frame_number(kitti_seq: Path, captured: dict):
    cv2.imwrite(str(_seq(kitti_seq) / "image_0" / "preview.png"), np.zeros((48, 64), np.uint8))
    with pytest.raises(ImageError, match=r"preview.png: file name is not a frame number"):
        kitti_frontend(kitti_seq)


def test_kitti_frames_take_their_own_times_and_poses(kitti_seq: Path, captured: dict):
    for cam in ("image_0", "image_1"):
        for k in (0, 1):
            (_seq(kitti_seq) / cam / f"{k:06d}.png").unlink()
    kitti_frontend(kitti_seq)
    np.testing.assert_allclose(captured["times"], TIMES[2:])
    np.testing.assert_allclose(captured["ground_truth"][:, 0], np.arange(2, N_KITTI) ** 2 - 4,
                               atol=1e-9)


def test_kitti_short_times_file_is_named(kitti_seq: Path, captured: dict):
    times = _seq(kitti_seq) / "times.txt"
    times.write_text("".join(times.read_text().splitlines(True)[:4]))
    with pytest.raises(ValueError, match=r"times.txt: 4 times for frames up to 000005.png"):
        kitti_frontend(kitti_seq)


def test_kitti_times_must_increase(kitti_seq: Path, captured: dict):
    times = _seq(kitti_seq) / "times.txt"
    lines = times.read_text().splitlines(True)
    lines[3] = lines[2]
    times.write_text("".join(lines))
    with pytest.raises(ValueError, match=r"times.txt:4: time .* of frame 000003.png is not after"):
        kitti_frontend(kitti_seq)


def test_kitti_short_poses_file_is_named(kitti_seq: Path, captured: dict):
    poses = kitti_seq / "poses" / "00.txt"
    poses.write_text("".join(poses.read_text().splitlines(True)[:4]))
    with pytest.raises(ValueError, match=r"poses/00.txt: 4 poses for frames up to 000005.png"):
        kitti_frontend(kitti_seq)


@pytest.mark.parametrize("file, line, text, message", [
    ("poses", 3, "1 0 0 0 0 1 0 0 0 0 1 abc", r"00.txt:3: 'abc' is not a number"),
    ("poses", 2, "1 0 0 0 0 1 0 0 0 0 1", r"00.txt:2: 11 numbers, but 12 on line 1"),
    ("poses", 1, "1 0 0 0 0 1 0 0 0 0 1", r"00.txt:1: expected 12 numbers, got 11"),
    ("times", 2, "0.1x", r"times.txt:2: '0.1x' is not a number"),
    ("times", 5, "nan", r"times.txt:5: non-finite number"),
])
def test_kitti_parse_errors_name_file_and_line(kitti_seq: Path, captured: dict, file: str,
                                               line: int, text: str, message: str):
    path = kitti_seq / "poses" / "00.txt" if file == "poses" else _seq(kitti_seq) / "times.txt"
    lines = path.read_text().splitlines()
    lines[line - 1] = text
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=message):
        kitti_frontend(kitti_seq)
    if file == "poses":
        with pytest.raises(ValueError, match=message):
            read_kitti_poses(path)


# --- EuRoC -------------------------------------------------------------------------------------

N_EUROC = 6
T0 = 1_403_715_273_262_142_976
FRAME_NS = 50_000_000  # 20 Hz
IMU_NS = 5_000_000  # 200 Hz
GYRO_BIAS = np.array([0.01, -0.02, 0.03])  # rad/s; about "up" (body -y) it is 0.02 rad/s

SENSOR_YAML = """%YAML:1.0
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [{t_bs}]
rate_hz: 20
resolution: [{res}]
camera_model: pinhole
intrinsics: [{intr}] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [0.0, 0.0, 0.0, 0.0]
"""


def _sensor_yaml(x: float, intr: str = "60.0, 60.0, 40.0, 30.0", res: str = "80, 60",
                 bottom: str = "0.0, 0.0, 0.0, 1.0", r00: float = 1.0) -> str:
    """Camera axes = body axes (camera y down, so body "up" is -y), origin at body x = ``x``."""
    t_bs = f"{r00}, 0.0, 0.0, {x}, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, {bottom}"
    return SENSOR_YAML.format(t_bs=t_bs, res=res, intr=intr)


def _write_csv(path: Path, header: str, rows) -> None:
    path.write_text(header + "\n" + "".join(",".join(str(v) for v in r) + "\n" for r in rows))


@pytest.fixture()
def mav(tmp_path: Path) -> Path:
    """Synthetic EuRoC ASL folder: 6 frames, a static IMU (gravity + constant gyro bias) and
    ground truth one row per frame. No images (the front-end loop is replaced)."""
    mav = tmp_path / "mav0"
    frames = [T0 + k * FRAME_NS for k in range(N_EUROC)]
    for cam, x in (("cam0", 0.0), ("cam1", 0.11)):
        (mav / cam / "data").mkdir(parents=True)
        (mav / cam / "sensor.yaml").write_text(_sensor_yaml(x))
        _write_csv(mav / cam / "data.csv", "#timestamp [ns],filename",
                   [(t, f"{t}.png") for t in frames])
    (mav / "imu0").mkdir()
    imu_t = np.arange(T0, frames[-1] + 1, IMU_NS)
    _write_csv(mav / "imu0" / "data.csv", "#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z",
               [(t, *GYRO_BIAS, 0.0, -9.81, 0.0) for t in imu_t])
    (mav / "state_groundtruth_estimate0").mkdir()
    _write_csv(mav / "state_groundtruth_estimate0" / "data.csv", "#time(ns),px,py,pz,qw,qx,qy,qz",
               [(t, 1.0, 2.0, 0.9, 1.0, 0.0, 0.0, 0.0) for t in frames])
    return mav


def _edit_csv(path: Path, edit) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n")


def test_euroc_valid_folder(mav: Path, captured: dict):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complete folder loads without warnings
        euroc_frontend(mav.parent)
    assert captured["n"] == N_EUROC
    np.testing.assert_allclose(captured["times"], np.arange(N_EUROC) * 0.05)
    assert captured["rig"].baseline == pytest.approx(0.11)
    np.testing.assert_allclose(captured["aids"].accel, np.tile([0.0, 0.0, 9.81], (N_EUROC, 1)),
                               atol=1e-9)
    assert captured["ground_truth"].shape == (N_EUROC, 3)


def test_euroc_gyro_bias_is_removed_from_the_yaw(mav: Path, captured: dict):
    euroc_frontend(mav.parent)
    yaw = captured["aids"].imu_yaw
    assert len(yaw) == N_EUROC
    np.testing.assert_allclose(yaw, 0.0, atol=1e-12)  # raw integration: 0.02 * 0.05 = 1e-3/frame


def test_euroc_real_static_sample_yaw_is_small(captured: dict):
    if not (EUROC / "mav0").is_dir():
        pytest.skip(f"real EuRoC frames not found at {EUROC} (see shared/data/README.md)")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # complete logs, a still gyro: no warnings
        euroc_frontend(EUROC)
    total = float(np.sum(captured["aids"].imu_yaw))
    print(f"\nEuRoC 20 static frames: summed IMU yaw {total:.5f} rad (raw gyro gave about -0.029)")
    assert abs(total) < 0.005


def test_euroc_ground_truth_off_the_frames_is_named(mav: Path, captured: dict):
    def shift(lines):
        t, rest = lines[4].split(",", 1)  # frame 3
        lines[4] = f"{int(t) + 30_000_000},{rest}"
        return lines
    _edit_csv(mav / "state_groundtruth_estimate0" / "data.csv", shift)
    with pytest.raises(ValueError, match=r"state_groundtruth_estimate0/data.csv: no ground-truth "
                                         r"row within 5 ms of frame 3 .* 30.0 ms away"):
        euroc_frontend(mav.parent)


def test_euroc_ground_truth_gap_is_named(mav: Path, captured: dict):
    _edit_csv(mav / "state_groundtruth_estimate0" / "data.csv",
              lambda lines: lines[:4] + lines[5:])  # no row for frame 3, inside the log's span
    with pytest.raises(ValueError, match=r"state_groundtruth_estimate0/data.csv: no ground-truth "
                                         r"row within 5 ms of frame 3 .* 50.0 ms away \(a gap"):
        euroc_frontend(mav.parent)


def test_euroc_ground_truth_starting_late_and_ending_early(mav: Path, captured: dict):
    # Rows for frames 2-4 only (frame 2 at z = 0.7 m), as in EuRoC downloads whose ground truth
    # starts after cam0 and ends before the last image; frame 1 is 50 ms before the first row.
    def edit(lines):
        t = lines[3].split(",", 1)[0]
        return [lines[0], f"{t},1.0,2.0,0.7,1.0,0.0,0.0,0.0", *lines[4:6]]
    _edit_csv(mav / "state_groundtruth_estimate0" / "data.csv", edit)
    with pytest.warns(UserWarning, match=r"state_groundtruth_estimate0/data.csv: the ground truth "
                                         r"covers frames 2 to 4 of 6 only; the others get NaN"):
        euroc_frontend(mav.parent)
    gt = captured["ground_truth"]
    assert gt.shape == (N_EUROC, 3)
    assert np.isnan(gt[[0, 1, 5]]).all()
    # Height (body to ground) from frame 2: robot origin 0.7 m below the body, i.e. body y + 0.7.
    np.testing.assert_allclose(gt[2:5], np.tile([1.0, 2.7, 0.0], (3, 1)), atol=1e-9)
    np.testing.assert_allclose(captured["initial_pose"], [1.0, 2.7, 0.0], atol=1e-9)
    # A row 3 ms after a frame still counts for it (within 5 ms).
    _edit_csv(mav / "state_groundtruth_estimate0" / "data.csv",
              lambda lines: [lines[0], f"{T0 + FRAME_NS + 3_000_000},1,2,0.7,1,0,0,0", *lines[1:]])
    with pytest.warns(UserWarning, match=r"covers frames 1 to 4 of 6 only"):
        euroc_frontend(mav.parent)


def test_euroc_ground_truth_covering_no_frame(mav: Path, captured: dict):
    _write_csv(mav / "state_groundtruth_estimate0" / "data.csv", "#time(ns),px,py,pz,qw,qx,qy,qz",
               [(T0 + 10**9 + k * FRAME_NS, 1.0, 2.0, 0.9, 1.0, 0.0, 0.0, 0.0) for k in range(4)])
    with pytest.warns(UserWarning, match=r"state_groundtruth_estimate0/data.csv: the ground truth "
                                         r"covers none of the 6 frames .*no ground truth"):
        euroc_frontend(mav.parent)
    assert captured["ground_truth"] is None and captured["initial_pose"] is None
    assert captured["n"] == N_EUROC


def _rewrite_imu(mav: Path, gyro) -> None:
    """Replace the gyro columns of imu0/data.csv by ``gyro(t_ns)`` (the accelerometer stays)."""
    imu_t = np.arange(T0, T0 + (N_EUROC - 1) * FRAME_NS + 1, IMU_NS)
    _write_csv(mav / "imu0" / "data.csv", "#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z",
               [(t, *gyro(t), 0.0, -9.81, 0.0) for t in imu_t])


@pytest.mark.parametrize("drop", [5, 10])  # the log ends 25 ms / 50 ms (one frame) early
def test_euroc_imu_log_ending_within_a_frame_period_is_used(mav: Path, captured: dict, drop: int):
    # Still for the gravity window (0.1 s = frame 2), then turning at w rad/s about "up" (-y).
    w = 0.2
    _rewrite_imu(mav, lambda t: GYRO_BIAS + (t > T0 + 2 * FRAME_NS) * np.array([0.0, -w, 0.0]))
    _edit_csv(mav / "imu0" / "data.csv", lambda lines: lines[:-drop])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        euroc_frontend(mav.parent)
    assert captured["n"] == N_EUROC
    aids = captured["aids"]
    np.testing.assert_allclose(aids.accel, np.tile([0.0, 0.0, 9.81], (N_EUROC, 1)), atol=1e-9)
    covered = (FRAME_NS - drop * IMU_NS) * 1e-9  # of the last frame interval
    np.testing.assert_allclose(aids.imu_yaw, [0.0, 0.0, 0.0, w * 0.05, w * 0.05, w * covered],
                               atol=1e-12)


def test_euroc_imu_log_ending_early_is_named(mav: Path, captured: dict):
    _edit_csv(mav / "imu0" / "data.csv", lambda lines: lines[:-11])  # 55 ms before frame 5
    with pytest.raises(ValueError, match=r"imu0/data.csv: IMU log ends at \d+ ns, before frame 5 "
                                         r"\(\d+ ns\) by 55.0 ms, more than one frame period "
                                         r"\(50.0 ms\)"):
        euroc_frontend(mav.parent)
    euroc_frontend(mav.parent, EurocParams(max_frames=5))  # the frames in use are covered
    assert captured["n"] == 5


@pytest.mark.parametrize("drop", [5, 10])  # the log starts 25 ms / 50 ms (one frame) late
def test_euroc_imu_log_starting_within_a_frame_period_is_used(mav: Path, captured: dict,
                                                              drop: int):
    _edit_csv(mav / "imu0" / "data.csv", lambda lines: lines[:1] + lines[1 + drop:])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        euroc_frontend(mav.parent)
    assert captured["n"] == N_EUROC
    np.testing.assert_allclose(captured["aids"].accel, np.tile([0.0, 0.0, 9.81], (N_EUROC, 1)),
                               atol=1e-9)
    np.testing.assert_allclose(captured["aids"].imu_yaw, 0.0, atol=1e-12)


def test_euroc_imu_log_starting_late_is_named(mav: Path, captured: dict):
    _edit_csv(mav / "imu0" / "data.csv", lambda lines: lines[:1] + lines[12:])  # 55 ms late
    with pytest.raises(ValueError, match=r"imu0/data.csv: IMU log starts at \d+ ns, after frame 0 "
                                         r"\(\d+ ns\) by 55.0 ms, more than one frame period"):
        euroc_frontend(mav.parent)


@pytest.mark.parametrize("gyro", [
    lambda t: GYRO_BIAS + [0.0, -0.2, 0.0],  # a steady 0.2 rad/s turn about "up" from the start
    lambda t: GYRO_BIAS + [0.05 * (-1) ** ((t - T0) // IMU_NS), 0.0, 0.0],  # shaking
], ids=["steady-turn", "shaking"])
def test_euroc_gyro_not_still_keeps_the_raw_gyro(mav: Path, captured: dict, gyro):
    _rewrite_imu(mav, gyro)
    with pytest.warns(UserWarning, match=r"imu0/data.csv: the gyro is not still within 0.1 s of "
                                         r"frame 0 .*no gyro bias removed"):
        euroc_frontend(mav.parent)
    # The raw rate about "up" (body -y) is integrated: nothing subtracted as a bias.
    imu_t = np.arange(T0, T0 + (N_EUROC - 1) * FRAME_NS + 1, IMU_NS)
    w_up = np.array([-gyro(t)[1] for t in imu_t])
    expected = [0.0] + [w_up[10 * k + 1:10 * k + 11].sum() * IMU_NS * 1e-9
                        for k in range(N_EUROC - 1)]
    np.testing.assert_allclose(captured["aids"].imu_yaw, expected, atol=1e-12)
    assert abs(captured["aids"].imu_yaw[1]) > 5e-4  # 0.22 or 0.02 rad/s over 50 ms


def test_euroc_imu_gap_is_named(mav: Path, captured: dict):
    # Samples are 5 ms apart: frame 3 is sample 30 (line 32); drop (frame 2, frame 3].
    _edit_csv(mav / "imu0" / "data.csv", lambda lines: lines[:22] + lines[32:])
    with pytest.raises(ValueError, match=r"imu0/data.csv: no IMU samples between frame 2 .* and "
                                         r"frame 3"):
        euroc_frontend(mav.parent)


@pytest.mark.parametrize("cam, edit, n0, n1", [
    ("cam1", lambda lines: lines + [f"{T0 + N_EUROC * FRAME_NS},extra.png"], 6, 7),
    ("cam0", lambda lines: lines + [f"{T0 + N_EUROC * FRAME_NS},extra.png"], 7, 6),
    ("cam1", lambda lines: lines[:-1], 6, 5),
])
def test_euroc_trailing_frames_of_one_camera_are_dropped(mav: Path, captured: dict, cam: str,
                                                         edit, n0: int, n1: int):
    _edit_csv(mav / cam / "data.csv", edit)
    n = min(n0, n1)
    with pytest.warns(UserWarning, match=rf"cam0/data.csv lists {n0} frames but cam1/data.csv "
                                         rf"{n1}; using the first {n} stereo pairs \(1 trailing "
                                         rf"frame\(s\) of cam{int(n1 > n0)} dropped\)"):
        euroc_frontend(mav.parent)
    assert captured["n"] == n
    np.testing.assert_allclose(captured["times"], np.arange(n) * 0.05)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no frame in use is dropped
        euroc_frontend(mav.parent, EurocParams(max_frames=4))
    assert captured["n"] == 4


def test_euroc_frame_timestamps_must_agree(mav: Path, captured: dict):
    _edit_csv(mav / "cam1" / "data.csv",
              lambda lines: lines[:3] + [f"{T0 + 2 * FRAME_NS + 1},x.png"] + lines[4:])
    with pytest.raises(ValueError, match=r"timestamps differ at frame 2 \(\d+ vs \d+ ns"):
        euroc_frontend(mav.parent)


@pytest.mark.parametrize("file, line, text, message", [
    ("cam0/data.csv", 3, f"{T0 + FRAME_NS}", r"cam0/data.csv:3: expected 'timestamp,filename'"),
    ("cam0/data.csv", 3, f"{T0 + FRAME_NS},", r"cam0/data.csv:3: expected 'timestamp,filename'"),
    ("cam1/data.csv", 2, "12ab,x.png", r"cam1/data.csv:2: timestamp '12ab' is not an integer"),
    ("cam0/data.csv", 4, f"{T0},x.png", r"cam0/data.csv:4: timestamp \d+ is not after"),
    ("imu0/data.csv", 4, f"{T0 + 2 * IMU_NS},0,0,abc,0,-9.81,0", r"imu0/data.csv:4: 'abc' is not"),
    ("imu0/data.csv", 5, f"{T0 + 3 * IMU_NS},0,0,0,0,-9.81", r"imu0/data.csv:5: 6 numbers, but 7"),
    ("imu0/data.csv", 2, f"{T0}.5,0,0,0,0,-9.81,0", r"imu0/data.csv:2: .* not an integer timest"),
    ("state_groundtruth_estimate0/data.csv", 3, f"{T0 + FRAME_NS},1,2,x,1,0,0,0",
     r"state_groundtruth_estimate0/data.csv:3: 'x' is not a number"),
])
def test_euroc_parse_errors_name_file_and_line(mav: Path, captured: dict, file: str, line: int,
                                               text: str, message: str):
    def edit(lines):
        lines[line - 1] = text
        return lines
    _edit_csv(mav / file, edit)
    with pytest.raises(ValueError, match=message):
        euroc_frontend(mav.parent)


# --- calibration -------------------------------------------------------------------------------


def test_euroc_swapped_cameras_are_rejected(mav: Path, captured: dict):
    cam0, cam1 = (read_sensor_yaml(mav / c / "sensor.yaml") for c in ("cam0", "cam1"))
    assert euroc_rig(cam0, cam1).baseline == pytest.approx(0.11)
    with pytest.raises(CalibrationError, match=r"cam1/sensor.yaml.*cam1 must be to the right"):
        euroc_rig(cam1, cam0)
    if (EUROC / "mav0").is_dir():  # the real calibration, swapped: baseline -0.110
        real = [read_sensor_yaml(EUROC / "mav0" / c / "sensor.yaml") for c in ("cam1", "cam0")]
        with pytest.raises(CalibrationError, match=r"baseline must be positive, got -0.11"):
            euroc_rig(*real)


@pytest.mark.parametrize("kw, message", [
    (dict(intr="60.0, fv_missing, 40.0, 30.0"),
     r"sensor.yaml: field 'intrinsics' entry 1: 'fv_missing' is not a number"),
    (dict(intr="-60.0, 60.0, 40.0, 30.0"), r"sensor.yaml: field 'intrinsics': fu and fv must be"),
    (dict(intr="60.0, 0.0, 40.0, 30.0"), r"sensor.yaml: field 'intrinsics': fu and fv must be"),
    (dict(intr="60.0, .nan, 40.0, 30.0"), r"sensor.yaml: field 'intrinsics' has a non-finite"),
    (dict(res="80, 0"), r"sensor.yaml: field 'resolution': width and height must be positive"),
    (dict(bottom="0.0, 0.0, 0.1, 1.0"), r"sensor.yaml: field 'T_BS': bottom row must be"),
    (dict(r00=1.1), r"sensor.yaml: field 'T_BS': the rotation part is not orthonormal"),
    (dict(intr="60.0, [1], 40.0, 30.0"), r"sensor.yaml: field 'intrinsics' entry 1: is not a"),
])
def test_sensor_yaml_bad_values_are_named(tmp_path: Path, kw: dict, message: str):
    path = tmp_path / "sensor.yaml"
    path.write_text(_sensor_yaml(0.0, **kw))
    with pytest.raises(CalibrationError, match=message):
        read_sensor_yaml(path)


def test_from_raw_rejects_unusable_rigs():
    k = np.array([[60.0, 0.0, 40.0], [0.0, 60.0, 30.0], [0.0, 0.0, 1.0]])
    d, r = np.zeros(4), np.eye(3)
    rig = RectifiedRig.from_raw(k, d, k, d, r, [-0.11, 0.0, 0.0], (80, 60), "rig.yaml")
    assert rig.baseline == pytest.approx(0.11) and rig.fx > 0
    with pytest.raises(CalibrationError, match=r"rig.yaml: baseline must be positive.*cam1 must "
                                               r"be to the right of cam0"):
        RectifiedRig.from_raw(k, d, k, d, r, [0.11, 0.0, 0.0], (80, 60), "rig.yaml")
    bad = k.copy()
    bad[1, 1] = np.nan
    with pytest.raises(CalibrationError, match=r"rig.yaml: k1 has a non-finite entry"):
        RectifiedRig.from_raw(k, d, bad, d, r, [-0.11, 0.0, 0.0], (80, 60), "rig.yaml")
    bad[1, 1] = -60.0
    with pytest.raises(CalibrationError, match=r"rig.yaml: k1: focal lengths must be positive"):
        RectifiedRig.from_raw(k, d, bad, d, r, [-0.11, 0.0, 0.0], (80, 60), "rig.yaml")


def test_euroc_sensor_yaml_that_is_not_yaml_is_named(mav: Path, captured: dict):
    (mav / "cam1" / "sensor.yaml").write_text("intrinsics: [60, 60\n  {{ not: yaml\n")
    with pytest.raises(CalibrationError, match=r"cam1/sensor.yaml: not a readable YAML file"):
        euroc_frontend(mav.parent)
    assert not captured


def test_euroc_cameras_at_one_place_are_named(mav: Path, captured: dict):
    (mav / "cam1" / "sensor.yaml").write_text(_sensor_yaml(0.0))  # cam1's T_BS = cam0's
    with pytest.raises(CalibrationError, match=r"sensor.yaml: the two cameras are at the same "
                       r"place \(zero baseline"):
        euroc_frontend(mav.parent)


def test_euroc_run_keeps_the_nanosecond_clock(mav: Path, captured: dict):
    euroc_frontend(mav.parent)
    assert captured["time_origin_ns"] == T0  # the TUM outputs add it back to the 0-based times
    np.testing.assert_allclose(captured["times"], np.arange(N_EUROC) * 0.05)


def test_frontend_reports_progress(kitti_seq: Path):
    calls = []
    res = kitti_frontend(kitti_seq, KittiParams(frontend=FrontEndParams(dense=False)),
                         progress=lambda done, total: calls.append((done, total)))
    assert res.run.num_frames == N_KITTI
    assert calls[-1] == (N_KITTI, N_KITTI) and len(calls) >= 2
    assert all(a[0] < b[0] for a, b in zip(calls, calls[1:]))


# --- a --path or --sequence that misses the dataset --------------------------------------------

def test_kitti_missing_sequence_lists_those_found(kitti_seq: Path, captured: dict):
    (kitti_seq / "sequences" / "07").mkdir()
    with pytest.raises(FileNotFoundError, match=r"sequences/01: no such sequence; .*sequences "
                       r"holds 00, 07$"):
        kitti_frontend(kitti_seq, KittiParams(sequence="01"))


def test_gslam_run_with_a_missing_sequence_lists_them_and_writes_nothing(kitti_seq: Path,
                                                                         tmp_path: Path, capsys):
    from gslam_jax.app.cli import main

    out = tmp_path / "out"
    assert main(["run", "--source", "kitti", "--path", str(kitti_seq), "--sequence", "1",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gslam: error: ") and err.rstrip().endswith("sequences holds 00")
    assert not out.exists()


@pytest.mark.parametrize("inside, sequence", [("sequences", ""), ("sequences/00", " --sequence 00"),
                                              ("sequences/00/image_0", " --sequence 00"),
                                              ("poses", "")])
def test_kitti_path_inside_the_dataset_suggests_its_root(kitti_seq: Path, captured: dict,
                                                         inside: str, sequence: str):
    with pytest.raises(FileNotFoundError) as err:
        kitti_frontend(kitti_seq / inside)
    assert str(err.value).endswith(f"it lies inside the KITTI odometry folder {kitti_seq}: "
                                   f"give --path {kitti_seq}{sequence}")
    kitti_frontend(kitti_seq, KittiParams(sequence=sequence.split()[-1] if sequence else None))
    assert captured["n"] == N_KITTI  # the suggestion works


def test_kitti_path_elsewhere_says_what_layout_it_expected(tmp_path: Path, mav: Path):
    with pytest.raises(FileNotFoundError, match=r"no 'sequences' folder \(expected the KITTI "
                       r"odometry layout, DIR/sequences/NN/image_0/\.\.\.\)$"):
        kitti_frontend(tmp_path / "mav0" / "imu0")
    with pytest.raises(FileNotFoundError, match=r"looks like an EuRoC folder \(mav0\): "
                       r"--source euroc$"):
        kitti_frontend(mav.parent)
    with pytest.raises(FileNotFoundError, match=r"nowhere: no such folder$"):
        kitti_frontend(tmp_path / "nowhere")


@pytest.mark.parametrize("inside", ["mav0/cam0", "mav0/cam0/data", "mav0/imu0"])
def test_euroc_path_inside_the_dataset_suggests_its_root(mav: Path, captured: dict,
                                                         inside: str):
    root = mav.parent
    with pytest.raises(FileNotFoundError, match=rf"{inside}: lies inside the EuRoC folder "
                       rf"{root}: give --path {root} \(the folder holding mav0/\)$"):
        euroc_frontend(root / inside)
    euroc_frontend(mav)  # mav0 itself is accepted as before
    assert captured["n"] == N_EUROC


def test_euroc_path_elsewhere_says_what_layout_it_expected(kitti_seq: Path):
    with pytest.raises(FileNotFoundError, match=r"no 'mav0' folder \(expected the EuRoC ASL "
                       r"layout, DIR/mav0/cam0/\.\.\.\); it looks like a KITTI odometry folder "
                       r"\(sequences/\): --source kitti$"):
        euroc_frontend(kitti_seq)
