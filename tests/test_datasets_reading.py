"""The adapters' shared reading helpers (``datasets.reading``), against SciPy and by hand."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gslam_jax.datasets.reading import first_not_increasing, quat_to_matrix, read_table
from gslam_jax.errors import DatasetError


def test_quaternions_of_either_order_match_scipy():
    rng = np.random.default_rng(0)
    q_xyzw = rng.normal(size=(6, 4)) * 3.0  # not unit length: normalised first
    expected = Rotation.from_quat(q_xyzw).as_matrix()
    np.testing.assert_allclose(quat_to_matrix(q_xyzw, scalar_last=True), expected, atol=1e-12)
    q_wxyz = q_xyzw[:, [3, 0, 1, 2]]
    np.testing.assert_allclose(quat_to_matrix(q_wxyz), expected, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(q_wxyz[2]), expected[2], atol=1e-12)


def test_tables_and_time_stamps(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# comment\n1 2\n\n3 4  # trailing\n")
    table = read_table(p, 2)
    np.testing.assert_array_equal(table.data, [[1, 2], [3, 4]])
    np.testing.assert_array_equal(table.lines, [2, 4])
    p.write_text("1 2\n3 x\n")
    with pytest.raises(DatasetError, match=r"t\.txt:2: 'x' is not a number"):
        read_table(p, 2)
    assert first_not_increasing(np.array([1.0, 2.0, 3.0])) is None
    assert first_not_increasing(np.array([1.0, 2.0, 2.0, 3.0])) == 2
