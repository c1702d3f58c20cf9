"""Config values that used to slip through: inf/NaN floats, a zero variance floor, wild seeds."""

import pytest

from gslam_jax.config import Config, ConfigError, apply_overrides, load_config


@pytest.mark.parametrize("item,named", [
    ("map.resolution=inf", r"\[map\] resolution must be finite"),
    ("localmap.max_range=inf", r"\[localmap\] max_range must be finite"),
    ("map.margin=inf", r"\[map\] margin must be finite"),
    ("motion.alpha_d=inf", r"\[motion\] alpha_d must be finite"),
    ("filter.beta_new=inf", r"\[filter\] beta_new must be finite"),
    ("localmap.min_height=-inf", r"\[localmap\] min_height must be finite"),
    ("localmap.travel=nan", r"\[localmap\] travel must be finite"),
    ("map.min_variance=inf", r"\[map\] min_variance must be finite"),
])
def test_non_finite_floats_are_rejected(item, named):
    with pytest.raises(ConfigError, match=r"--set: " + named):
        apply_overrides(Config(), [item])


def test_zero_min_variance_is_rejected(tmp_path):
    """S = 0 with k > 0 gives NaN log weights, so the floor must be positive."""
    with pytest.raises(ConfigError, match=r"\[map\] min_variance must be positive"):
        apply_overrides(Config(), ["map.min_variance=0"])
    p = tmp_path / "zero.toml"
    p.write_text("[map]\nmin_variance = 0.0\n")
    with pytest.raises(ConfigError, match=r"zero\.toml: \[map\] min_variance must be positive"):
        load_config(p)
    assert apply_overrides(Config(), ["map.min_variance=1e-8"]).map.min_variance == 1e-8


@pytest.mark.parametrize("seed", [-1, 2 ** 32, 2 ** 63 - 1])
def test_seed_outside_uint32_is_rejected(seed):
    with pytest.raises(ConfigError, match=r"\[filter\] seed must be in \[0, 2\*\*32\)"):
        apply_overrides(Config(), [f"filter.seed={seed}"])


def test_seed_range_ends_are_accepted():
    assert apply_overrides(Config(), ["filter.seed=0"]).filter.seed == 0
    assert apply_overrides(Config(), [f"filter.seed={2 ** 32 - 1}"]).filter.seed == 2 ** 32 - 1


def test_finite_values_still_pass():
    c = apply_overrides(Config(), ["map.resolution=0.2", "map.margin=0", "motion.alpha_d=0",
                                   "localmap.max_range=5"])
    assert (c.map.resolution, c.map.margin, c.motion.alpha_d) == (0.2, 0.0, 0.0)


def test_integer_too_large_for_a_float_is_a_config_error():
    """Before: float(10**400) raised OverflowError, a traceback instead of a message."""
    with pytest.raises(ConfigError, match=r"--set: \[map\] margin: 1000+ is too large for a float"):
        apply_overrides(Config(), ["map.margin=1" + "0" * 400])
