"""write_kitti: KITTI's file layout, this project's robot frame (x forward, y left, z up)."""

import numpy as np

from gslam_jax.io import write_kitti


def test_write_kitti_is_the_robot_frame(tmp_path):
    poses = np.array([[1.0, 2.0, 0.0], [3.0, -1.0, np.pi / 2]])
    write_kitti(tmp_path / "k.txt", poses)
    rows = np.loadtxt(tmp_path / "k.txt").reshape(-1, 3, 4)
    # translation (x, y, 0): the plane is x-y with z up, not KITTI's camera x-z plane
    np.testing.assert_allclose(rows[:, :, 3], [[1, 2, 0], [3, -1, 0]], atol=1e-12)
    # rotation about the third axis (z up), which stays fixed
    np.testing.assert_allclose(rows[1, :, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
