"""One default per setting and one list of allowed values per enumerated setting: the config's
defaults (which the filter's static config and params take as theirs), the documented ones and
the command line's must not drift apart."""

import dataclasses
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax import choices, rbpf
from gslam_jax.app.cli import build_parser
from gslam_jax.config import Config, ConfigError, apply_overrides, load_config
from gslam_jax.driver import sizing
from gslam_jax.rbpf import resampling
from gslam_jax.rbpf.types import DRAWS
from gslam_jax.tiled import numerics
from gslam_jax.vo.localmap import LocalMapParams

ROOT = Path(__file__).resolve().parents[1]


def test_every_filter_setting_of_the_config_reaches_the_filter():
    """The filter's static config and params are built from a Config (``sizing.filter_config``,
    ``sizing.filter_params``): each setting they share, set away from its default, arrives."""
    run, _ = make_run(seed=1, steps=20)
    changed = {"filter": dict(particles=9, resampler="systematic", resample_ratio=0.3,
                              unknown_cells="sample", unknown_samples=77, particle_block=3,
                              tempering="fixed", ess_target=0.7, beta_prev=0.2, beta_new=0.3,
                              proposal_draws="antithetic"),
               "map": dict(store="shared", tile=16, pool_tiles=900),
               "motion": dict(alpha_d=0.11, alpha_theta_d=0.12, alpha_theta=0.13,
                              alpha_cross=0.14, fallback_scale=2.5, noise_spread=3.0)}
    config = dataclasses.replace(Config(), **{
        name: dataclasses.replace(getattr(Config(), name), **values)
        for name, values in changed.items()})
    cfg = sizing.filter_config(config, run)
    shared = [f for f in rbpf.FilterConfig._fields
              if f in changed["filter"] or f in changed["map"]]
    assert len(shared) == 11  # resampler .. ess_target, proposal_draws, store, tile, pool_tiles
    for name in shared:
        assert getattr(cfg, name) == {**changed["filter"], **changed["map"]}[name], name
    assert cfg.num_particles == 9 and cfg.noise_spread == 3.0
    params = sizing.filter_params(config)
    np.testing.assert_allclose([float(v) for v in params.motion],
                               [0.11, 0.12, 0.13, 0.14, 2.5], rtol=1e-6)
    np.testing.assert_allclose([float(params.beta_prev), float(params.beta_new)], [0.2, 0.3],
                               rtol=1e-6)


def test_local_map_defaults_are_the_config_defaults():
    """``LocalMapParams()`` is the default config's local maps for the simulator's point sensor
    (``lattice = "auto"`` resolved: the robot's axes); for stereo "auto" is the map's."""
    from gslam_jax.vo.localmap import localmap_params

    assert LocalMapParams() == localmap_params(Config())
    assert localmap_params(Config(), "stereo") == dataclasses.replace(LocalMapParams(),
                                                                      lattice="map")
    with pytest.raises(ConfigError, match="sensor must be one of points, stereo, got 'lidar'"):
        localmap_params(Config(), "lidar")


def test_paper_config_file_holds_every_default():
    """configs/paper.toml lists every field, each the built-in default but for the five it says
    differ: the paper's fixed tempering, best-particle path, independent draws, local maps
    on the robot's axes and map on the frame's."""
    path = ROOT / "configs" / "paper.toml"
    paper = load_config(path)
    default = Config()
    assert dataclasses.replace(paper, filter=dataclasses.replace(
        paper.filter, tempering=default.filter.tempering, estimate=default.filter.estimate,
        proposal_draws=default.filter.proposal_draws), localmap=default.localmap,
        map=default.map) == Config()
    assert dataclasses.replace(paper.localmap, lattice="auto") == default.localmap
    assert dataclasses.replace(paper.map, axes="start") == default.map
    assert (paper.filter.tempering, paper.filter.estimate, paper.filter.proposal_draws,
            paper.localmap.lattice, paper.map.axes) == ("fixed", "best", "independent", "robot",
                                                        "frame")
    data = tomllib.loads(path.read_text())
    for section in ("filter", "motion", "map", "localmap"):
        assert set(data[section]) == set(dataclasses.asdict(getattr(Config(), section)))


def test_configuration_reference_shows_the_defaults():
    reference = (ROOT / "docs" / "configuration.md").read_text()
    table = reference.split("| key | default | allowed | meaning |", 1)[1].split("\n\n", 1)[0]
    rows = re.findall(r"^\| ((?:`\w+\.\w+`(?:, )?)+) \| ([^|]+) \|", table, re.MULTILINE)
    seen = set()
    for keys, defaults in rows:
        keys = re.findall(r"`(\w+)\.(\w+)`", keys)
        values = [tomllib.loads(f"v = {v.strip().strip('`')}")["v"] for v in defaults.split(",")]
        assert len(values) == len(keys), keys
        for (section, key), value in zip(keys, values):
            assert getattr(getattr(Config(), section), key) == value, f"{section}.{key}"
            seen.add((section, key))
    every = {(s, k) for s in ("filter", "motion", "map", "localmap", "stereo")
             for k in dataclasses.asdict(getattr(Config(), s))}
    assert seen == every


def test_one_list_of_allowed_values_per_setting():
    assert tuple(resampling.RESAMPLERS) == choices.RESAMPLERS
    assert tuple(numerics.RESAMPLERS) == choices.RESAMPLERS
    for setting, allowed in (("resampler", choices.RESAMPLERS),
                             ("unknown_cells", choices.UNKNOWN_CELLS),
                             ("proposal_draws", DRAWS)):
        for value in allowed:
            apply_overrides(Config(), [f"filter.{setting}={value}"])
            rbpf.FilterConfig(1, (64, 64), (0.0, 0.0), 0.16, 8, **{setting: value}).validate()
        with pytest.raises(ConfigError, match=setting):
            apply_overrides(Config(), [f"filter.{setting}=other"])
        with pytest.raises(ValueError, match=setting):
            rbpf.FilterConfig(1, (64, 64), (0.0, 0.0), 0.16, 8, **{setting: "other"}).validate()


def test_command_line_choices_are_the_shared_lists():
    from gslam_jax.datasets.registry import source_names

    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.choices and "run" in a.choices).choices
    found = {}
    for name, sub in subparsers.items():
        for action in sub._actions:
            if action.choices is not None:
                found.setdefault(action.option_strings[0], set()).add(tuple(action.choices))
    expected = {"--source": source_names(), "--on-bad-frame": choices.BAD_FRAME_POLICIES,
                "--design": choices.SEARCH_DESIGNS, "--score-path": choices.SCORE_PATHS,
                "--mode": choices.UNKNOWN_CELLS, "--unknown-cells": choices.UNKNOWN_CELLS}
    for option, allowed in expected.items():
        assert found[option] == {tuple(allowed)}, option
    assert found["--objective"] == {choices.SEARCH_OBJECTIVES, choices.TUNE_OBJECTIVES}
