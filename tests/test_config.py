"""TOML configs: defaults, unknown keys, wrong types, malformed files, overrides."""

import re
from pathlib import Path

import pytest

from gslam_jax.config import Config, ConfigError, apply_overrides, config_to_toml, load_config


def test_defaults_are_the_papers():
    c = Config()
    assert c.map.resolution == 0.16 and c.filter.particles == 200
    assert c.localmap.max_range == 10.0 and c.filter.resample_ratio == 0.5


def test_round_trip_through_toml(tmp_path):
    c = apply_overrides(Config(), ["filter.particles=50", "filter.unknown_cells=ignore"])
    p = tmp_path / "c.toml"
    p.write_text(config_to_toml(c))
    assert load_config(p) == c


@pytest.mark.parametrize("text,match", [
    ("[filter]\nparticle = 3\n", r"bad\.toml: unknown key 'particle' in \[filter\]"),
    ("[filtr]\n", r"bad\.toml: unknown section \[filtr\]"),
    ("[filter]\nparticles = \"many\"\n", r"bad\.toml: \[filter\] particles: expected int, got str"),
    ("[map]\nresolution = -1.0\n", r"bad\.toml: \[map\] resolution must be positive"),
    ("[filter]\nresampler = \"best\"\n", r"bad\.toml: \[filter\] resampler must be one of"),
    ("[filter]\nparticle_block = -2\n", r"bad\.toml: \[filter\] particle_block must be >= 0"),
    ("[filter\nparticles = 3\n", r"bad\.toml: malformed TOML"),
    ("[map]\nstore = \"tiles\"\n", r"bad\.toml: \[map\] store must be one of dense, shared, window, auto"),
    ("[map]\ntile = 12\n", r"bad\.toml: \[map\] tile must be a positive multiple of 8"),
    ("[map]\npool_tiles = -1\n", r"bad\.toml: \[map\] pool_tiles must be >= 0"),
    ("[localmap]\nlattice = \"north\"\n",
     r"bad\.toml: \[localmap\] lattice must be one of robot, map"),
])
def test_bad_configs_name_file_section_and_key(tmp_path, text, match):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(p)


def test_missing_file_and_bad_override(tmp_path):
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="expected section.key=value"):
        apply_overrides(Config(), ["particles=3"])


def test_shipped_configs_load():
    """Every file in configs/ is a filter config, a Table I config (with [course.*] tables) or
    (with a [space] table) a search space."""
    import tomllib
    from pathlib import Path

    from gslam_jax.tuning.space import load_space
    from gslam_jax.config import load_table_config

    paths = sorted((Path(__file__).parents[1] / "configs").glob("*.toml"))
    assert paths
    for path in paths:
        data = tomllib.loads(path.read_text())
        if "space" in data:
            load_space(path)
        elif "course" in data:
            load_table_config(path)
        else:
            load_config(path)


def test_table1_per_course_sections_override_only_their_course(tmp_path):
    from gslam_jax.config import load_table_config

    path = tmp_path / "t.toml"
    path.write_text("[filter]\nparticles = 50\n[motion]\nalpha_d = 0.04\n"
                    "[course.mars-yard-b.motion]\nalpha_theta_d = 0.03\n")
    shared, per_course = load_table_config(path)
    assert shared.motion.alpha_d == 0.04 and shared.motion.alpha_theta_d == 0.01
    b = per_course["mars-yard-b"]
    assert (b.motion.alpha_d, b.motion.alpha_theta_d, b.filter.particles) == (0.04, 0.03, 50)
    assert set(per_course) == {"mars-yard-b"}


@pytest.mark.parametrize("text, named", [
    ("[course.mars-yard-z.motion]\nalpha_d = 0.1\n", "course.mars-yard-z"),
    ("[course.maze.motion]\nalpha_dd = 0.1\n", "alpha_dd"),
    ("[course.maze.motion]\nalpha_d = 'x'\n", "[course.maze]"),
])
def test_table1_bad_course_sections_are_named(tmp_path, text, named):
    from gslam_jax.config import load_table_config

    path = tmp_path / "t.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(named)):
        load_table_config(path)


PAPER = Path(__file__).resolve().parents[2] / "shared" / "paper" / "gamma-slam-jfr2009.txt"


def test_paper_table1_figures_match_the_papers_text():
    """The reference column printed beside the simulated Table I is the paper's own."""
    from gslam_jax.app.table1 import PAPER_TABLE1

    if not PAPER.is_file():
        pytest.skip(f"the paper's text is not at {PAPER}")
    text = PAPER.read_text(encoding="utf-8", errors="replace")
    rows = {"mars-yard-a": "Mars Yard A", "mars-yard-b": "Mars Yard B",
            "arroyo-a": "Arroyo Seco A", "arroyo-b": "Arroyo Seco B", "maze": "SwRI maze"}
    for course, label in rows.items():
        m = re.search(re.escape(label) + r"\s+(\d+)\s+(\d+\.\d+)\s+(\d+\.\d+)", text)
        assert m, label
        assert PAPER_TABLE1[course] == (int(m[1]), float(m[2]), float(m[3])), course


@pytest.mark.parametrize("sets, match", [
    (["map.resolution=1e6"], r"\[map\] resolution 1e\+06 m against \[localmap\] max_range 10 m "
                             r"spans 2e-05 cells per side, fewer than 8.*at most 2\.5 m"),
    (["map.resolution=50"], r"\[map\] resolution 50 m against \[localmap\] max_range 10 m spans "
                            r"0\.4 cells"),
    (["localmap.max_range=0.2"], r"\[localmap\] max_range 0\.2 m spans 2\.5 cells"),
    (["localmap.cells=4"], r"\[localmap\] cells = 4 gives local maps of fewer than 8 cells"),
])
def test_local_maps_of_a_few_cells_are_refused(sets, match):
    from gslam_jax.app.pipeline import check_local_map_size

    with pytest.raises(ConfigError, match=match):
        check_local_map_size(apply_overrides(Config(), sets))
    check_local_map_size(apply_overrides(Config(), ["map.resolution=2.5"]))  # 8 cells: enough


def test_a_coarse_resolution_is_refused_before_the_run(tmp_path, capsys, monkeypatch):
    from gslam_jax.app.cli import main

    monkeypatch.setattr("gslam_jax.datasets.sim.simulate_run", lambda *a, **k: 1 / 0)
    assert main(["run", "--set", "map.resolution=50", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "gslam: error: [map] resolution 50 m against [localmap] max_range 10 m" in err
    assert not (tmp_path / "o").exists()
