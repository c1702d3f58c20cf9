"""The source registry: discovery of SOURCE declarations, and the option checks it derives."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from gslam_jax.config import Config, apply_overrides
from gslam_jax.datasets import registry
from gslam_jax.datasets.registry import RUN_FILE, Source, check_source, get_source


def test_every_dataset_module_with_a_source_is_registered():
    names = set(registry.sources())
    assert names == {"sim", "sim-path", "sim-stereo", "kitti", "euroc", "stereo", "rosbag",
                     RUN_FILE}
    assert RUN_FILE not in registry.source_names()  # the positional argument, not --source
    flags = {n: (s.simulated, s.images) for n, s in registry.sources().items()}
    assert flags == {"sim": (True, False), "sim-path": (True, False), "sim-stereo": (True, True),
                     "kitti": (False, True), "euroc": (False, True), "stereo": (False, True),
                     "rosbag": (False, True), RUN_FILE: (False, False)}


def test_a_new_module_with_a_source_is_found_without_touching_another_file(tmp_path,
                                                                          monkeypatch):
    package = tmp_path / "fake_datasets"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "toy.py").write_text(textwrap.dedent("""
        from gslam_jax.datasets.registry import DataSource, LoadedSource
        SOURCE = DataSource(name="toy", help="a toy", load=lambda src, config, p=None: None,
                            path="a folder", sequence=True)
    """))
    (package / "helpers.py").write_text("X = 1\n")  # no SOURCE: not a source
    monkeypatch.syspath_prepend(str(tmp_path))
    import importlib

    found = registry.discover(importlib.import_module("fake_datasets"))
    assert list(found) == ["toy"] and found["toy"].sequence
    sys.modules.pop("fake_datasets", None)


def test_options_a_source_does_not_take_are_refused():
    with pytest.raises(registry.ConfigError, match="--path is for --source sim-path/euroc/kitti"):
        check_source(Source(source="sim", path=Path("x")))
    with pytest.raises(registry.ConfigError, match="--sequence is for --source kitti"):
        check_source(Source(source="euroc", path=Path("x"), sequence="00"))
    with pytest.raises(registry.ConfigError, match="needs --path"):
        check_source(Source(source="kitti"))
    with pytest.raises(registry.ConfigError, match="not simulated"):
        check_source(Source(source="kitti", path=Path("x"), seed=3))
    check_source(Source(source="kitti", path=Path("x"), seed=3), gps="sim")  # the GPS's seed
    stereo = apply_overrides(Config(), ["stereo.num_disparities=32"])
    with pytest.raises(registry.ConfigError, match=r"\[stereo\] num_disparities: settings apply"):
        check_source(Source(source="sim"), stereo)
    check_source(Source(source="sim-stereo"), stereo)
    with pytest.raises(registry.ConfigError, match="a Run file is used as it is; --max-frames"):
        check_source(Source(run_file=Path("r.npz"), max_frames=3))


def test_an_unknown_source_names_the_known_ones():
    with pytest.raises(registry.ConfigError, match="known sources: sim, sim-path, sim-stereo"):
        get_source("pcap")


def test_every_stereo_key_reaches_the_dense_stereo_params():
    """Each [stereo] key is the ``DenseStereoParams`` field of that name: set, it replaces the
    source's value; 0 or "" keeps it."""
    import dataclasses

    from gslam_jax.config import StereoSection
    from gslam_jax.datasets.registry import stereo_settings
    from gslam_jax.vo.stereo import DenseStereoParams

    given = {"num_disparities": 96, "block": 7, "stride": 3, "algorithm": "bm",
             "max_depth_error": 0.3, "disparity_std": 0.4, "edge_ratio": 0.25}
    assert set(given) == {f.name for f in dataclasses.fields(StereoSection)}
    config = dataclasses.replace(Config(), stereo=StereoSection(**given))
    got = stereo_settings(config, DenseStereoParams())
    assert {k: getattr(got, k) for k in given} == given
    assert stereo_settings(Config(), DenseStereoParams(stride=4)) == DenseStereoParams(stride=4)
