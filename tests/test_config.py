"""TOML configs: defaults, unknown keys, wrong types, malformed files, overrides."""

import re
from pathlib import Path

import pytest

from gslam_jax.config import Config, ConfigError, apply_overrides, config_to_toml, load_config
from gslam_jax.sim.courses import COURSES


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
            load_table_config(path, COURSES)
        else:
            load_config(path)


def test_table1_per_course_sections_override_only_their_course(tmp_path):
    from gslam_jax.config import load_table_config

    path = tmp_path / "t.toml"
    path.write_text("[filter]\nparticles = 50\n[motion]\nalpha_d = 0.04\n"
                    "[course.mars-yard-b.motion]\nalpha_theta_d = 0.03\n")
    shared, per_course = load_table_config(path, COURSES)
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
        load_table_config(path, COURSES)


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


ROOT = Path(__file__).resolve().parents[1]


def _section_changes(a: Config, b: Config) -> dict[str, tuple]:
    """``"section.key"`` -> (a's value, b's value) where the two configs differ."""
    import dataclasses

    return {f"{name}.{key}": (getattr(getattr(a, name), key), getattr(getattr(b, name), key))
            for name in dataclasses.asdict(a)
            for key in dataclasses.asdict(getattr(a, name))
            if getattr(getattr(a, name), key) != getattr(getattr(b, name), key)}


def test_gslam_config_comments_every_key_and_reads_back(capsys):
    """``gslam config`` prints every key with a one-line comment from its declaration, and the
    text parses back (TOML) to the same config, for the defaults and for a changed one."""
    import dataclasses
    import tomllib

    from gslam_jax.app.cli import main
    from gslam_jax.config import parse_config

    for sets in ([], ["filter.particles=50", "rig.matrix=[[1,0,0,0],[0,1,0,0],[0,0,1,0],"
                      "[0,0,0,1]]", "stereo.algorithm=bm", "filter.estimate=best"]):
        assert main(["config", *[a for s in sets for a in ("--set", s)]]) == 0
        text = capsys.readouterr().out
        expected = apply_overrides(Config(), sets)
        assert parse_config(tomllib.loads(text), "<gslam config>") == expected
        keys = {}
        section = None
        for line in text.splitlines():
            if not line or line.startswith("#"):
                continue
            if line.startswith("["):
                section = line.strip("[]")
                continue
            key, rest = line.split(" = ", 1)
            assert "  # " in rest, line
            keys[f"{section}.{key}"] = rest.split("  # ", 1)[1]
        every = {f"{s}.{k}" for s, sec in dataclasses.asdict(Config()).items() for k in sec}
        assert set(keys) == every
        assert all(len(comment) > 10 for comment in keys.values())
    # what 0 or "" means, for the keys where it means "automatic" or "the source's own"
    assert "0: automatic" in keys["filter.ess_target"]
    assert "0: the source's" in keys["stereo.num_disparities"]
    assert '"": the source\'s' in keys["stereo.algorithm"]
    assert "0: the source's own" in keys["rig.height"] and "metres" in keys["rig.height"]
    assert "the paper's: \"fixed\"" in keys["filter.tempering"]


def test_documented_differences_from_the_paper_are_the_actual_ones():
    """docs/configuration.md's table of the defaults that are not the paper's is the difference
    between the defaults and configs/paper.toml, the declarations' ``paper`` values and the
    list ``gslam run --help`` gives."""
    import tomllib

    from gslam_jax.app.cli import build_parser
    from gslam_jax.config import paper_differences

    actual = _section_changes(Config(), load_config(ROOT / "configs" / "paper.toml"))
    assert len(actual) == 5
    text = (ROOT / "docs" / "configuration.md").read_text()
    table = text.split("| key | default | the paper's |", 1)[1].split("\n\n", 1)[0]
    rows = re.findall(r"^\| `(\w+\.\w+)` \| `([^`]*)` \| `([^`]*)` \|$", table, re.MULTILINE)
    documented = {key: (tomllib.loads(f"v = {d}")["v"], tomllib.loads(f"v = {p}")["v"])
                  for key, d, p in rows}
    assert documented == actual
    assert paper_differences() == actual
    parser = build_parser()
    run = next(a for a in parser._actions if a.choices and "run" in a.choices).choices["run"]
    help_text = " ".join(run.format_help().split())
    listed = re.search(r"configs/paper\.toml, except ([\w., ]+)\)", help_text)[1]
    assert set(listed.replace(" ", "").split(",")) == set(actual)


def test_the_filter_config_is_built_from_the_settings_by_their_keys():
    """Every field of ``rbpf.FilterConfig`` is a config setting's (``CONFIG_KEYS``, found by
    name) or sized from the run (``GIVEN_FIELDS``); ``from_config`` carries every setting, and
    the filter's defaults are the settings' (an automatic one resolved as for no sensor)."""
    import dataclasses

    from gslam_jax import choices
    from gslam_jax.config.sections import SECTION_TYPES
    from gslam_jax.config.setting import UNSET, setting_of
    from gslam_jax.rbpf.types import CONFIG_KEYS, GIVEN_FIELDS, FilterConfig

    assert set(CONFIG_KEYS).isdisjoint(GIVEN_FIELDS)
    assert set(CONFIG_KEYS) | set(GIVEN_FIELDS) == set(FilterConfig._fields)
    assert len(CONFIG_KEYS) == 20
    changed = {"particles": 9, "resampler": "systematic", "resample_ratio": 0.3,
               "unknown_cells": "sample", "unknown_samples": 77, "particle_block": 3,
               "tempering": "fixed", "ess_target": 0.7, "proposal": "informed",
               "proposal_points": 5, "proposal_span": 1.5, "proposal_stages": 3,
               "proposal_cell_stride": 4, "proposal_exponent": "normaliser",
               "proposal_draws": "antithetic", "resolution": 0.2, "store": "shared", "tile": 16,
               "pool_tiles": 900, "noise_spread": 3.0}
    config = Config()
    for field, (section, key) in CONFIG_KEYS.items():
        value = changed[key]
        assert value != getattr(getattr(config, section), key), key
        config = dataclasses.replace(config, **{section: dataclasses.replace(
            getattr(config, section), **{key: value})})
    cfg = FilterConfig.from_config(config.validate(), map_shape=(64, 64), map_origin=(0.0, 0.0),
                                   local_size=8).validate()
    for field, (section, key) in CONFIG_KEYS.items():
        assert getattr(cfg, field) == changed[key], field
    bare = FilterConfig(1, (64, 64), (0.0, 0.0), 0.16, 8)
    automatic = {"ess_target": choices.AUTO_ESS_TARGET["points"],
                 "proposal_draws": choices.AUTO_PROPOSAL_DRAWS["points"]}
    for field, (section, key) in CONFIG_KEYS.items():
        if field in ("num_particles", "resolution"):
            continue  # no default: given
        default = getattr(SECTION_TYPES[section](), key)
        if setting_of(SECTION_TYPES[section], key).resolved is not UNSET and \
                default == setting_of(SECTION_TYPES[section], key).resolved:
            default = automatic[field]
        assert getattr(bare, field) == default, field


_CANDIDATES = {int: [-1, 0, 1, 2, 3, 4, 7, 8, 12, 16, 32, 1000, 1001, 2 ** 32],
               float: [-1.0, 0.0, 0.25, 0.5, 1.0, 1.5, 4.5, 1000.0, 1001.0],
               str: ["other", "", "auto", "dense", "shared", "motion", "informed",
                     "independent", "antithetic", "fixed", "adaptive", "prior", "normaliser",
                     "multinomial", "systematic", "ignore", "sample"]}


def test_the_config_and_the_filter_refuse_the_same_values():
    """One rule per setting: for every setting the filter's static config takes, a value is
    refused by ``rbpf.FilterConfig.validate`` exactly when the config refuses it (or it is the
    automatic value the host resolves before), each naming the setting; and every rule refuses
    some value tried here."""
    import dataclasses

    from gslam_jax.config.sections import SECTION_TYPES
    from gslam_jax.config.setting import setting_of
    from gslam_jax.rbpf.types import CONFIG_KEYS, FilterConfig

    base = FilterConfig(4, (64, 64), (0.0, 0.0), 0.16, 8).validate()
    for field, (section, key) in CONFIG_KEYS.items():
        rule = setting_of(SECTION_TYPES[section], key)
        kind = type(getattr(Config(), section).__getattribute__(key))
        refused = 0
        for value in _CANDIDATES[kind]:
            try:
                dataclasses.replace(Config(), **{section: dataclasses.replace(
                    getattr(Config(), section), **{key: value})}).validate()
                config_ok = True
            except ConfigError as err:
                assert f"[{section}] {key} " in str(err)
                config_ok = False
            try:
                base._replace(**{field: value}).validate()
                filter_ok = True
            except ValueError as err:
                assert str(err).startswith(f"{field} "), (field, value, err)
                filter_ok = False
            assert filter_ok == (config_ok and value != rule.resolved), (field, value)
            refused += not config_ok
        assert refused, f"no value tried here breaks [{section}] {key}'s rule: add one"


def test_course_tables_need_the_course_names_given():
    """The config layer knows no course names: the caller passes them (``sim.courses``)."""
    from gslam_jax.config import load_table_config

    path = ROOT / "configs" / "table1.toml"
    with pytest.raises(ConfigError, match=r"unknown course \[course\.\S+\]; known courses: none"):
        load_table_config(path)
    assert set(load_table_config(path, COURSES)[1]) <= set(COURSES)


def test_every_proposal_has_one_rule():
    """``rbpf.proposal.select`` knows every ``[filter] proposal`` value, and only those."""
    from gslam_jax import choices
    from gslam_jax.rbpf import proposal

    assert tuple(proposal.RULES) == choices.PROPOSALS
