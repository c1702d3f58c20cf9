"""Native .npz Run files: round trip and clear errors for bad input."""

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax.run import RunError, load_run, save_run


def test_round_trip(tmp_path):
    run, _ = make_run(steps=15)
    save_run(tmp_path / "r.npz", run)
    back = load_run(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.controls, run.controls)
    np.testing.assert_array_equal(back.local_maps, run.local_maps)
    np.testing.assert_array_equal(back.ground_truth, run.ground_truth)


def test_nan_control_names_the_frame(tmp_path):
    run, _ = make_run(steps=15)
    controls = run.controls.copy()
    controls[7, 1] = np.nan
    fields = {k: v for k, v in run._asdict().items() if v is not None}
    np.savez(tmp_path / "bad.npz", **{**fields, "controls": controls})
    with pytest.raises(RunError, match=r"bad\.npz: field 'controls': non-finite value .* at frame 7"):
        load_run(tmp_path / "bad.npz")


def test_missing_and_unknown_fields(tmp_path):
    run, _ = make_run(steps=15)
    d = {k: v for k, v in run._asdict().items() if v is not None}
    np.savez(tmp_path / "a.npz", **{k: v for k, v in d.items() if k != "obs_index"})
    with pytest.raises(RunError, match="missing field.*obs_index"):
        load_run(tmp_path / "a.npz")
    np.savez(tmp_path / "b.npz", **d, colour=np.zeros(2))
    with pytest.raises(RunError, match="unknown field.*colour"):
        load_run(tmp_path / "b.npz")


def test_out_of_range_obs_index_and_corrupt_file(tmp_path):
    run, _ = make_run(steps=15)
    idx = run.obs_index.copy()
    idx[3] = 99
    d = {k: v for k, v in run._asdict().items() if v is not None}
    np.savez(tmp_path / "c.npz", **{**d, "obs_index": idx})
    with pytest.raises(RunError, match="frame 3 refers to local map 99"):
        load_run(tmp_path / "c.npz")
    (tmp_path / "d.npz").write_bytes(b"not a zip")
    with pytest.raises(RunError, match=r"d\.npz: not a \.npz archive"):
        load_run(tmp_path / "d.npz")
    np.save(tmp_path / "e.npy", np.zeros(3))  # an .npy is no Run either (np.load would accept it)
    with pytest.raises(RunError, match=r"e\.npy: not a \.npz archive"):
        load_run(tmp_path / "e.npy")


def test_lattice_headings_round_trip_and_bad_values_are_named(tmp_path):
    """``lattice_headings`` ([localmap] lattice = "map") is kept by a Run file; a file without
    it loads as the robot's lattice (zeros to the filter); a wrong shape, a NaN or degrees in
    place of radians are errors naming the field and local map."""
    from gslam_jax.vo.localmap import LocalMapParams

    run, _ = make_run(steps=15, params=LocalMapParams(resolution=0.16, max_range=5.0,
                                                      travel=1.0, lattice="map"))
    assert run.lattice_headings is not None and np.any(run.lattice_headings != 0)
    save_run(tmp_path / "r.npz", run)
    back = load_run(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.lattice_headings, run.lattice_headings)
    plain, _ = make_run(steps=15)
    save_run(tmp_path / "p.npz", plain)
    old = load_run(tmp_path / "p.npz")
    assert old.lattice_headings is None
    np.testing.assert_array_equal(old.lattice_heading_array(), np.zeros(old.num_local_maps))
    d = {k: v for k, v in run._asdict().items() if v is not None}
    h = run.lattice_headings
    for bad, match in ((h[:-1], r"expected shape \[\d+\] \(one per local map\)"),
                       (np.where(np.arange(h.size) == 2, np.nan, h), "non-finite .* local map 2"),
                       (np.where(np.arange(h.size) == 1, 5000.0, h), "local map 1: 5000 rad")):
        np.savez(tmp_path / "bad.npz", **{**d, "lattice_headings": bad})
        with pytest.raises(RunError, match=r"bad\.npz: field 'lattice_headings': " + match):
            load_run(tmp_path / "bad.npz")
