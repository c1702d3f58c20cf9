"""experiments/online_latency --batch: the live API against the batch run on the same frames and
map extent, bit for bit equal with the defaults."""

from __future__ import annotations

from experiments.online_latency import main


def test_online_against_batch_on_the_same_frames(capsys):
    report = main(["--frames", "40", "--particles", "8", "--batch"])
    capsys.readouterr()
    assert report["settings"]["frames"] == 40 and report["per_local_map_update"]["count"] > 0
    assert report["best_pose_equal"] is True
    assert report["online_rms_m"] == report["batch_rms_m"] and 0 < report["online_rms_m"] < 1.0
