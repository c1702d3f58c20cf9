"""examples/own_rig.py: a pitched simulated rig written as a stereo folder and run through
--source stereo; the folder is the documented layout, the RMS printed is that of the run, and
the [rig] pitch it writes puts the ground level in the local maps."""

from __future__ import annotations

import re
import runpy
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from gslam_jax.evaluation.metrics import rms_after_fit

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "own_rig.py"

pytestmark = pytest.mark.slow  # long-running: scheduled first (tests/conftest.py)


def test_own_rig_example(tmp_path, monkeypatch, capsys):
    folder = tmp_path / "rig"
    monkeypatch.setattr("sys.argv", [str(EXAMPLE), str(folder)])
    monkeypatch.delenv("GSLAM_EXAMPLE_FRAMES", raising=False)
    ns = runpy.run_path(str(EXAMPLE), run_name="__main__")
    out = capsys.readouterr().out
    n = len(list((folder / "left").glob("*.png")))
    assert n == len(list((folder / "right").glob("*.png"))) > 30
    assert re.search(rf"wrote {n} stereo pairs", out)
    for name in ("calib.yaml", "times.txt", "odometry.txt", "groundtruth.txt"):
        assert (folder / name).is_file(), name
    rig = tomllib.loads((folder / "rig.toml").read_text())["rig"]
    assert (rig["height"], rig["pitch"]) == (1.2, 20.0)

    run, result = ns["loaded"].run, ns["result"]
    assert run.num_frames == n
    vo, slam = map(float, re.search(r"VO only ([\d.]+) m, Gamma-SLAM ([\d.]+) m", out).groups())
    truth = np.loadtxt(folder / "groundtruth.txt")  # TUM: t x y z qx qy qz qw
    assert np.allclose(run.ground_truth[:, :2], truth[:, 1:3], atol=1e-6)
    assert slam == round(rms_after_fit(result.path, truth[:, 1:3]), 3)
    assert vo < 0.2 and slam < 0.3  # a 14 m drive

    # The local maps hold the world's heights: each cell's mean point height, placed at the
    # true pose of the frame its map is centred on, against the rendered world's surface
    # there, relative to the ground under the robot (a 20 degree pitch assumed level would be
    # metres off at the far cells, 5 degrees too little ~0.4 m at 5 m).
    world = ns["renderer"].world
    L, res = run.local_maps.shape[1], run.resolution
    centre = (np.arange(L) - L // 2 + 0.5) * res
    cx, cy = np.meshgrid(centre, centre, indexing="ij")
    errors = []
    for t in np.flatnonzero(run.obs_index >= 0):
        m = run.local_maps[run.obs_index[t]]
        known = m[..., 0] >= 2
        x, y, th = run.ground_truth[t]
        wx = x + np.cos(th) * cx[known] - np.sin(th) * cy[known]
        wy = y + np.sin(th) * cx[known] + np.cos(th) * cy[known]

        def at(raster, px, py):
            ij = [(np.atleast_1d(px) - world.origin[0]) / world.resolution - 0.5,
                  (np.atleast_1d(py) - world.origin[1]) / world.resolution - 0.5]
            return map_coordinates(raster, ij, order=1)

        true = at(world.height, wx, wy) - at(world.ground, x, y)
        errors.append(m[..., 1][known] / m[..., 0][known] - true)
    errors = np.concatenate(errors)
    assert errors.size > 5000 and np.median(np.abs(errors)) < 0.05, np.median(np.abs(errors))
