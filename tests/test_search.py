"""Batched parameter search: spaces, designs, ranking, objectives, sharding on 2 CPU devices."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import make_run

from gslam_jax.config import Config, FilterSection, MapSection
from gslam_jax.evaluation import metrics
from gslam_jax.tuning import designs as D, evaluation as E, search as S, space as SP
from gslam_jax.vo.localmap import LocalMapParams

LM = LocalMapParams(resolution=0.16, max_range=2.5, travel=1.0)
CONFIG = Config(filter=FilterSection(particles=8, unknown_cells="ignore"), map=MapSection(margin=1.0))


@pytest.fixture(scope="module")
def small_run():
    run, _ = make_run(seed=1, steps=24, drift=0.01, params=LM)
    return run


@pytest.mark.parametrize("table, match", [
    ({"alpha_d": [0.1, 0.01]}, "alpha_d: inverted range"),
    ({"alpha_d": [0.05, 0.05]}, "alpha_d: empty range"),
    ({"alpha_x": [0.0, 1.0]}, "unknown parameter 'alpha_x'"),
    ({"beta_new": [0.0, 1.0]}, "beta_new: .*positive"),
    ({"alpha_theta": {"range": [0.0, 1.0], "log": True}}, "alpha_theta: a log-scale range"),
    ({"alpha_d": [0.1]}, r"alpha_d: expected a range"),
    ({}, "non-empty"),
])
def test_bad_spaces_name_the_field(table, match):
    with pytest.raises(SP.SearchError, match=match):
        SP.parse_space(table)


def test_load_space_file(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[space]\nalpha_d = [0.01, 0.1]\nbeta_prev = { range = [0.01, 1.0], log = true }\n'
                 '[search]\ndesign = "sobol"\nn = 16\n')
    space, opts = SP.load_space(p)
    assert space.names == ("alpha_d", "beta_prev") and space.log == (False, True)
    assert opts == {"design": "sobol", "n": 16}
    p.write_text('[space]\nalpha_d = [0.01, 0.1]\n[search]\nbogus = 1\n')
    with pytest.raises(SP.SearchError, match="unknown key 'bogus'"):
        SP.load_space(p)
    space, _ = SP.load_space(Path(__file__).parents[1] / "configs" / "search_example.toml")
    assert space.dim >= 2


def test_designs_cover_the_ranges():
    space = SP.parse_space({"alpha_d": [0.01, 0.1], "alpha_theta": {"range": [1e-3, 1e-1], "log": True}})
    for design in D.DESIGNS:
        v = D.design_points(space, design, 16, seed=1)
        assert v.shape == (16, 2)
        assert np.all(v[:, 0] >= 0.01) and np.all(v[:, 0] <= 0.1)
        assert np.all(v[:, 1] >= 1e-3 - 1e-12) and np.all(v[:, 1] <= 1e-1 + 1e-12)
    grid = D.design_points(space, "grid", 16)
    assert len(np.unique(grid[:, 1].round(9))) == 4 and np.isclose(grid[:, 1].min(), 1e-3)
    with pytest.raises(SP.SearchError, match="design 'lhs' unknown"):
        D.design_points(space, "lhs", 4)


def test_sobol_points_are_stratified_and_seeded():
    """A scrambled Sobol net of 2^m points puts exactly one point in each of the 2^m equal
    intervals of every coordinate (a (0, m, 1)-net per axis), here in 8 dimensions; the seed
    picks the scrambling."""
    u = D.unit_points("sobol", 64, 8, seed=3)
    assert u.shape == (64, 8) and np.all((u >= 0) & (u < 1))
    for d in range(8):
        assert sorted(np.floor(u[:, d] * 64).astype(int)) == list(range(64))
    np.testing.assert_array_equal(u, D.unit_points("sobol", 64, 8, seed=3))
    assert not np.allclose(u, D.unit_points("sobol", 64, 8, seed=4))
    assert D.unit_points("sobol", 48, 8, seed=3).shape == (48, 8)  # a prefix of 64
    h = D.unit_points("halton", 30, 8, seed=1)
    assert h.shape == (30, 8) and len(np.unique(h[:, 0])) == 30


def test_nan_is_never_ranked_best():
    v = np.arange(5.0)[:, None]
    f = np.array([np.nan, 3.0, -np.inf, 1.0, np.nan])
    vals, obj = S.rank(v, f, maximize=False)
    assert list(vals[:, 0][:2]) == [3.0, 1.0] and np.all(~np.isfinite(obj[2:]))
    vals, obj = S.rank(v, f, maximize=True)
    assert list(vals[:, 0][:2]) == [1.0, 3.0]
    res = S.SearchResult(("alpha_d",), vals, obj, "loglik", True, 0.0, 0.0)
    assert res.best() == {"alpha_d": 1.0} and res.num_nan == 3
    allnan = S.SearchResult(("alpha_d",), v, np.full(5, np.nan), "rms", False, 0.0, 0.0)
    with pytest.raises(SP.SearchError, match="NaN"):
        allnan.best()


def test_rigid_rms_matches_metrics():
    rng = np.random.default_rng(0)
    ref = np.cumsum(rng.normal(size=(50, 3)), 0)
    a = 0.3
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    est = ref.copy()
    est[:, :2] = ref[:, :2] @ R.T + [5.0, -2.0] + rng.normal(0, 0.1, (50, 2))
    mask = np.ones(50, bool)
    mask[::7] = False
    got = float(E.rigid_rms(jnp.asarray(est, jnp.float32), jnp.asarray(ref, jnp.float32), jnp.asarray(mask)))
    want = metrics.rms_after_fit(est, ref, frames=np.flatnonzero(mask))
    assert abs(got - want) < 1e-4


@pytest.mark.parametrize("sets, max_batch, devices", [(64, 47, 1), (64, 47, 2), (100, 30, 2),
                                                      (5, 3, 1), (7, 64, 2), (3, 1, 2)])
def test_chunks_are_balanced(sets, max_batch, devices):
    """Against brute force over every chunk size: the fewest chunks of at most max_batch sets
    (at least one per device, a multiple of the device count), then the least padding."""
    cap = devices * -(-min(max_batch, sets) // devices)

    def cost(b: int) -> tuple[int, int]:
        chunks = -(-sets // b)
        return chunks, chunks * b - sets

    best = min(cost(b) for b in range(devices, cap + 1, devices))
    b = E.chunk_size(sets, max_batch, devices)
    assert b % devices == 0 and b <= cap
    assert cost(b) == best


@pytest.mark.slow
def test_search_ranks_and_writes(small_run, tmp_path):
    space = SP.parse_space({"alpha_d": [0.01, 0.1], "alpha_theta_d": [0.002, 0.05]})
    res = S.search(small_run, CONFIG, space, "halton", 5, "rms", batch=3)
    assert res.values.shape == (5, 2) and np.all(np.diff(res.objective) >= 0)
    # Every set is the filter's own output under the same key (common random numbers).
    import dataclasses

    from gslam_jax.driver import slam
    best = res.best()
    cfg = dataclasses.replace(CONFIG, motion=dataclasses.replace(CONFIG.motion, **best))
    out = slam.run_slam(small_run, cfg)
    assert abs(metrics.rms_after_fit(out.mean_pose, small_run.ground_truth) - res.objective[0]) < 1e-3
    res.to_csv(tmp_path / "r.csv")
    res.to_json(tmp_path / "r.json")
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["results"][0]["rank"] == 1 and doc["objective"] == "rms"
    assert (tmp_path / "r.csv").read_text().splitlines()[0] == "rank,alpha_d,alpha_theta_d,rms,status"


@pytest.mark.slow
def test_search_nan_objective_errors_and_warnings(small_run):
    space = SP.parse_space({"beta_prev": [0.01, 0.1]})
    with pytest.raises(SP.SearchError, match="objective 'loglik'"):
        # beta = NaN makes every objective NaN: a clear error, not a silent "best".
        S.search(small_run, CONFIG, space, objective="loglik", values=np.full((2, 1), np.nan))
    with pytest.warns(RuntimeWarning, match="NaN for 1 of 2"):
        res = S.search(small_run, CONFIG, space, objective="loglik",
                       values=np.array([[np.nan], [0.05]]))
    assert res.values[0, 0] == 0.05 and np.isnan(res.objective[1])
    with pytest.raises(SP.SearchError, match="ground_truth"):
        S.search(small_run._replace(ground_truth=None), CONFIG, space, n=2, objective="rms")


@pytest.mark.slow
def test_rms_needs_a_frame_with_ground_truth(small_run):
    """Ground truth with no finite frame would score every set 0 m: an error instead."""
    space = SP.parse_space({"alpha_d": [0.01, 0.1]})
    blind = small_run._replace(ground_truth=np.full_like(small_run.ground_truth, np.nan))
    with pytest.raises(SP.SearchError, match=r"no frame with a finite position \(x, y\)"):
        S.search(blind, CONFIG, space, n=2, objective="rms")
    import jax

    from gslam_jax.driver import device_arrays, sizing
    inputs, cfg = device_arrays.run_arrays(blind, CONFIG)
    with pytest.raises(SP.SearchError, match=r"no frame with a finite position \(x, y\)"):
        E.evaluate(np.array([[0.05]]), jax.random.key(0), inputs, sizing.filter_params(CONFIG),
                   space.names, cfg, "rms")
    # One frame with ground truth is enough; loglik needs none.
    some = blind.ground_truth.copy()
    some[3] = small_run.ground_truth[3]
    res = S.search(blind._replace(ground_truth=some), CONFIG, space, n=1, objective="rms")
    assert np.isfinite(res.objective[0])
    S.search(blind, CONFIG, space, n=1, objective="loglik")


@pytest.mark.slow
def test_rms_scores_position_only_ground_truth(small_run):
    """Ground truth with NaN headings (positions only): the RMS uses x, y alone, as
    metrics.errors_over_known_frames does. Before, every frame was dropped and the search
    refused ("no frame with finite values")."""
    from gslam_jax.driver import device_arrays
    space = SP.parse_space({"alpha_d": [0.01, 0.1]})
    gt = small_run.ground_truth.copy()
    gt[:, 2] = np.nan
    gt[5, 0] = np.nan  # a frame without a position is still skipped
    partial = small_run._replace(ground_truth=gt)
    full = small_run.ground_truth.copy()
    full[5] = np.nan
    values = np.array([[0.03], [0.07]])
    got = S.search(partial, CONFIG, space, values=values, objective="rms")
    want = S.search(small_run._replace(ground_truth=full), CONFIG, space, values=values,
                    objective="rms")
    np.testing.assert_array_equal(got.objective, want.objective)  # headings play no part
    assert np.all(np.isfinite(got.objective))
    np.testing.assert_array_equal(device_arrays.ground_truth_mask(partial),
                                  np.arange(small_run.num_frames) != 5)


@pytest.mark.slow
def test_result_times_are_named_for_what_they_hold(small_run, tmp_path):
    """total_seconds includes compilation; first_chunk_seconds is a part of it."""
    space = SP.parse_space({"alpha_d": [0.01, 0.1]})
    # batch=1: four chunks, compiled as test_rms_needs_a_frame_with_ground_truth's loglik
    res = S.search(small_run, CONFIG, space, n=4, objective="loglik", batch=1)
    assert 0 < res.first_chunk_seconds <= res.total_seconds
    res.to_json(tmp_path / "r.json")
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["total_seconds"] == res.total_seconds
    assert doc["first_chunk_seconds"] == res.first_chunk_seconds
    assert "seconds" not in doc and "compile_seconds" not in doc
    with pytest.raises(SP.SearchError, match="crn=False is not supported"):
        S.search(small_run, CONFIG, space, n=2, objective="loglik", crn=False)


@pytest.mark.slow
def test_sharded_on_two_cpu_devices(tmp_path):
    """Sharded over a 2-device mesh gives the same objectives as one device (subprocess: the
    device count must be set before JAX is imported). The test process's other XLA flags
    (conftest.py's classic CPU emitters: half the compilation time) go with it."""
    flags = " ".join([f for f in os.environ.get("XLA_FLAGS", "").split()
                      if not f.startswith("--xla_force_host_platform_device_count")]
                     + ["--xla_force_host_platform_device_count=2"])
    code = textwrap.dedent(f"""
        import os, sys
        os.environ["XLA_FLAGS"] = {flags!r}
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        import jax, numpy as np
        assert len(jax.devices()) == 2, jax.devices()
        from synthetic import make_run
        from gslam_jax.tuning import designs as D, search as S, space as SP
        from gslam_jax.config import Config, FilterSection, MapSection
        from gslam_jax.vo.localmap import LocalMapParams
        run, _ = make_run(seed=1, steps=16, drift=0.01,
                          params=LocalMapParams(resolution=0.16, max_range=2.5, travel=1.0))
        cfg = Config(filter=FilterSection(particles=8, unknown_cells="ignore"),
                     map=MapSection(margin=1.0))
        space = SP.parse_space({{"alpha_d": [0.01, 0.1]}})
        vals = D.design_points(space, "halton", 6)
        two = S.search(run, cfg, space, values=vals, objective="loglik", batch=4)
        one = S.search(run, cfg, space, values=vals, objective="loglik", batch=4,
                       devices=jax.devices()[:1])
        np.testing.assert_allclose(two.objective, one.objective, rtol=1e-5)
        print("OK", two.objective[:2])
    """)
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=300, cwd=Path(__file__).parents[1])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "OK" in proc.stdout


@pytest.mark.slow
def test_observation_settings_match_the_config_path(small_run):
    """Searching min_variance, obs_weight and min_points scores each set as a run whose [map]
    config holds those values (``config_with_values``: min_points rounded up)."""
    from gslam_jax.driver import slam

    space = SP.parse_space({"min_variance": {"range": [1e-6, 1e-2], "log": True},
                           "obs_weight": [0.2, 1.0], "min_points": [2.0, 6.0],
                           "alpha_d": [0.01, 0.1]})
    values = np.array([[1e-3, 0.5, 3.2, 0.05], [1e-5, 1.0, 2.0, 0.02]])
    res = S.search(small_run, CONFIG, space, values=values, objective="rms")
    for row, f in zip(res.values, res.objective):
        cfg = SP.config_with_values(CONFIG, dict(zip(space.names, row)))
        assert cfg.map.min_points == (4 if row[2] > 3 else 2)
        out = slam.run_slam(small_run, cfg)
        assert abs(metrics.rms_after_fit(out.mean_pose, small_run.ground_truth) - f) < 1e-3
    assert not np.isclose(res.objective[0], res.objective[1])


def test_config_with_values_sets_every_section():
    vals = {"alpha_d": 0.02, "beta_new": 0.3, "min_variance": 1e-4, "obs_weight": 0.5,
            "min_points": 2.5}
    cfg = SP.config_with_values(CONFIG, vals)
    assert (cfg.motion.alpha_d, cfg.filter.beta_new, cfg.map.min_variance, cfg.map.obs_weight,
            cfg.map.min_points) == (0.02, 0.3, 1e-4, 0.5, 3)
    assert SP.base_values(cfg)["obs_weight"] == 0.5
    with pytest.raises(SP.SearchError, match="obs_weight must be positive"):
        SP.config_with_values(CONFIG, {"obs_weight": 0.0})
    with pytest.raises(SP.SearchError, match="min_points: range"):
        SP.parse_space({"min_points": [1.0, 4.0]})


def test_run_and_search_share_the_observation_route(small_run):
    """A run, the search and the tuner refine the same raw observations on the device
    (``observations.refine_observations``); with the default settings that equals the float64 host
    conversion of ``cells.obs_from_stats`` bit for bit, and within float32 rounding with
    others."""
    from gslam_jax.driver import device_arrays, observations

    np.testing.assert_array_equal(np.asarray(observations.map_observations(small_run, CONFIG)),
                                  observations.local_observations(small_run, 1e-6))
    values = {"min_variance": 1e-3, "obs_weight": 0.4, "min_points": 3}
    cfg = SP.config_with_values(CONFIG, values)
    inputs, _ = device_arrays.run_arrays(small_run, CONFIG)
    row = jnp.asarray(list(values.values()), jnp.float32)
    searched = SP.observations_from_values(row, tuple(values), inputs.obs, inputs.local_obs)
    np.testing.assert_array_equal(np.asarray(searched),
                                  np.asarray(observations.map_observations(small_run, cfg)))
    np.testing.assert_allclose(np.asarray(searched),
                               observations.local_observations(small_run, 1e-3, 0.4, 3), rtol=1e-6)


def test_settings_table_names_config_fields_and_device_fields():
    """Every searchable setting is a field of its Config section; the observation settings
    are the fields of ``observations.ObsSettings``, the filter parameters those of FilterParams."""
    from gslam_jax import rbpf
    from gslam_jax.driver import observations

    for s in SP.SETTINGS.values():
        assert hasattr(getattr(CONFIG, s.section), s.name), s
    assert set(SP.OBS_PARAM_NAMES) == set(observations.ObsSettings._fields)
    params = rbpf.FilterParams()
    # range_noise is no setting: a per-cell profile estimated from the run ([filter] range_noise)
    assert set(SP.FILTER_PARAM_NAMES) == (set(params.motion._fields)
                                          | set(params._fields) - {"motion", "range_noise"})
    assert tuple(SP.base_values(CONFIG)) == SP.PARAM_NAMES


@pytest.mark.slow
@pytest.mark.parametrize("command", ["search", "tune"])
def test_a_full_disk_is_a_named_error_and_publishes_nothing(small_run, tmp_path, monkeypatch,
                                                            capsys, command):
    """A write that fails (ENOSPC) while search or tune write their files: exit 2 naming
    --out, no traceback, nothing at --out."""
    import errno
    from pathlib import Path

    from gslam_jax.app.cli import main
    from gslam_jax.run import save_run

    save_run(tmp_path / "r.npz", small_run)
    space = tmp_path / "space.toml"
    space.write_text("[space]\nalpha_d = [0.01, 0.1]\n")

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    out = tmp_path / "out"
    sets = ["--set", "filter.particles=8", "--set", "localmap.max_range=2.5",
            "--set", "localmap.travel=1.0", "--set", "map.margin=1.0"]
    args = ([command, str(tmp_path / "r.npz"), "--space", str(space), "--n", "2", "--out",
             str(out)] if command == "search" else
            [command, str(tmp_path / "r.npz"), "--steps", "1", "--runs-per-step", "1", "--out",
             str(out)]) + sets
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: cannot write the results (No space left on device)" in err
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("path", ["steps", "local_steps"])
def test_the_search_scores_the_path_the_run_reports(small_run, path):
    """``--score-path``: the search's RMS at the config's own values is the RMS of the path
    ``run_slam`` reports under that estimate (local_steps needs the run's local map
    footprints, which the search's inputs carry)."""
    from gslam_jax.config import apply_overrides
    from gslam_jax.driver import slam

    space = SP.parse_space({"alpha_d": [0.01, 0.1]})
    values = np.array([[CONFIG.motion.alpha_d]])
    got = S.search(small_run, CONFIG, space, values=values, objective="rms", path=path)
    res = slam.run_slam(small_run, apply_overrides(CONFIG, [f"filter.estimate={path}"]))
    want = metrics.rms_after_fit(res.path, small_run.ground_truth)
    np.testing.assert_allclose(got.objective[0], want, rtol=1e-4)
