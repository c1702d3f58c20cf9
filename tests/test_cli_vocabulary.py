"""One command-line vocabulary (issue 68, "One interface"): every option explained, the shared
options spelled, stored and explained alike in every command, the old spellings still working
with a note; Python warnings printed as the CLI's notes; the persistent compilation cache."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

from gslam_jax.app import arguments, cli, compile_cache
from gslam_jax.app.cli import build_parser, main

# Options that several commands take with a meaning of their own (the help says which).
DIFFERENT_MEANINGS = {
    "--store",      # bench: the stores to time; compare: the JAX filter's store
    "--course",     # the simulated course to run; bench: a course to time as well
    "--objective",  # search and tune rank by different objectives
}


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    return next(a for a in parser._actions
                if isinstance(a, argparse._SubParsersAction)).choices


def _options(sub: argparse.ArgumentParser):
    for action in sub._actions:
        if action.option_strings and not isinstance(action, argparse._HelpAction) \
                and "--version" not in action.option_strings:
            yield action


def test_every_option_of_every_command_has_help():
    missing = [f"gslam {name} {action.option_strings[0]}"
               for name, sub in _commands().items() for action in _options(sub)
               if not (action.help and action.help.strip())]
    assert not missing, missing
    positionals = [f"gslam {name} {action.dest}" for name, sub in _commands().items()
                   for action in sub._actions
                   if not action.option_strings and not isinstance(
                       action, argparse._SubParsersAction) and not action.help]
    assert not positionals, positionals


def test_hidden_options_are_only_the_deprecated_spellings():
    hidden = [(name, a.option_strings[0]) for name, sub in _commands().items()
              for a in _options(sub) if a.help == argparse.SUPPRESS]
    assert hidden, "the old spellings are kept (hidden)"
    for name, option in hidden:
        action = next(a for a in _options(_commands()[name]) if option in a.option_strings)
        assert isinstance(action, arguments.Deprecated), (name, option)


def test_shared_options_have_one_name_dest_and_help():
    seen: dict[str, list[tuple[str, str, str]]] = {}
    for name, sub in _commands().items():
        for action in _options(sub):
            if isinstance(action, arguments.Deprecated):
                continue
            for option in action.option_strings:
                seen.setdefault(option, []).append((name, action.dest, action.help))
    for option, shared in arguments.SHARED.items():
        assert option in seen, f"{option} is shared but no command takes it"
        for name, dest, help_text in seen[option]:
            assert dest == option.lstrip("-").replace("-", "_"), (name, option, dest)
            assert help_text == shared["help"], (name, option)
    for option, uses in seen.items():
        if len(uses) > 1 and option not in DIFFERENT_MEANINGS:
            assert len({(d, h) for _, d, h in uses}) == 1, (option, uses)


@pytest.mark.parametrize("command", ["run", "bench", "table1", "compare"])
def test_particles_and_unknown_cells_are_taken_alike(command):
    names = {a.option_strings[0] for a in _options(_commands()[command])
             if not isinstance(a, arguments.Deprecated)}
    assert "--particles" in names
    if command in ("bench", "compare"):
        assert "--unknown-cells" in names


def test_out_is_a_results_folder_in_every_command_that_writes_one():
    for name, sub in _commands().items():
        outs = [a for a in _options(sub) if "--out" in a.option_strings]
        for action in outs:
            if isinstance(action, arguments.Deprecated):
                assert "--save-config" in action.advice, name  # the old file spelling
            else:
                assert action.help == arguments.SHARED["--out"]["help"], name
    for name in ("run", "search", "tune", "merge", "compare", "bench", "table1"):
        assert any(a.help == arguments.SHARED["--out"]["help"]
                   for a in _options(_commands()[name])), name


def test_run_particles_is_set_filter_particles():
    from gslam_jax.app.arguments import load_config

    parser = build_parser()
    given = load_config(parser.parse_args(["run", "--particles", "37"]))
    spelled = load_config(parser.parse_args(["run", "--set", "filter.particles=37"]))
    assert given.filter.particles == spelled.filter.particles == 37
    # --particles is applied after --set, as the later override
    both = load_config(parser.parse_args(["run", "--set", "filter.particles=5",
                                          "--particles", "9"]))
    assert both.filter.particles == 9


@pytest.mark.parametrize("argv, dest, value, old", [
    (["bench", "--mode", "sample"], "unknown_cells", ["sample"], "--mode"),
    (["view", "R", "--save", "x.rrd"], "viewer_save", Path("x.rrd"), "--save"),
    (["compare", "--tile-size", "1.6"], "tile_size", 1.6, "--tile-size"),
    (["compare", "--seed", "3"], "seed", 3, "--seed"),
    (["table1", "--json", "t.json"], "json", Path("t.json"), "--json"),
    (["bench", "--json", "b.json"], "json", Path("b.json"), "--json"),
    (["fit-motion", "--out", "f.toml"], "save_config", Path("f.toml"), "--out"),
])
def test_old_spellings_work_with_a_note(argv, dest, value, old, capsys):
    args = build_parser().parse_args(argv)
    assert getattr(args, dest) == value
    err = capsys.readouterr().err
    assert err.startswith(f"note: {old} is deprecated") and "use " in err


def test_old_spelling_is_checked_as_before(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["compare", "--tile-size", "-1"])
    assert "argument --tile-size: expected a finite positive number" in capsys.readouterr().err


def test_compare_tile_cells_are_cells(monkeypatch):
    seen = {}

    def fake_compare(run, config, **kw):
        seen.update(kw, particles_cfg=config.filter.particles, seed_cfg=config.filter.seed)
        return {"agreement": {"ok": True}}
    import gslam_jax.app.compare as compare_module
    monkeypatch.setattr(compare_module, "compare", fake_compare)
    assert main(["compare", "--tile-cells", "62", "--particles", "7",
                 "--set", "filter.seed=4"]) == 0
    assert seen["tile_size"] == pytest.approx(62 * compare_module.default_resolution())
    assert seen["particles"] == 7 and seen["seed"] == 4
    seen.clear()
    assert main(["compare", "--tile-cells", "5000"]) == 2 and not seen


def test_bench_out_is_a_results_folder(tmp_path):
    out = tmp_path / "b"
    assert main(["bench", "--particles", "4", "--local", "16", "--map", "64",
                 "--unknown-cells", "ignore", "--repeats", "1", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["COMPLETE", "bench.json", "bench.png"]
    assert main(["bench", "--particles", "4", "--local", "16", "--map", "64",
                 "--unknown-cells", "ignore", "--repeats", "1", "--out", str(out)]) == 2


def test_warnings_are_printed_as_notes(monkeypatch, capsys):
    def warns(args):
        warnings.warn("the disparity range is narrower than the nearest surfaces need",
                      UserWarning)
        warnings.warn("ran out of something", RuntimeWarning)
        return 0
    monkeypatch.setattr(cli, "cmd_run", warns)
    assert main(["run"]) == 0
    err = capsys.readouterr().err
    assert err.splitlines() == [
        "note: the disparity range is narrower than the nearest surfaces need",
        "note: RuntimeWarning: ran out of something"]
    assert ".py:" not in err
    assert warnings.showwarning is not cli._show_note  # restored after the command


# -- the persistent compilation cache ---------------------------------------------------------

def test_cache_folder_rules(tmp_path):
    home = {"HOME": str(tmp_path / "home")}
    assert compile_cache.cache_folder(home) == tmp_path / "home/.cache/gslam-jax/jax"
    xdg = {**home, "XDG_CACHE_HOME": str(tmp_path / "xdg")}
    assert compile_cache.cache_folder(xdg) == tmp_path / "xdg/gslam-jax/jax"
    assert compile_cache.cache_folder({**xdg, "GSLAM_JAX_CACHE": str(tmp_path / "c")}) == \
        tmp_path / "c"
    assert compile_cache.cache_folder({**xdg, "GSLAM_JAX_CACHE": ""}) is None


def test_enable_leaves_a_users_jax_cache_and_can_be_turned_off(tmp_path):
    env = {"HOME": str(tmp_path), "JAX_COMPILATION_CACHE_DIR": "/mine"}
    assert compile_cache.enable_compile_cache(env) is None
    assert env["JAX_COMPILATION_CACHE_DIR"] == "/mine"
    env = {"HOME": str(tmp_path), "GSLAM_JAX_CACHE": ""}
    assert compile_cache.enable_compile_cache(env) is None
    assert "JAX_COMPILATION_CACHE_DIR" not in env
    env = {"HOME": str(tmp_path), "GSLAM_JAX_CACHE_MAX_MB": "0"}
    assert compile_cache.enable_compile_cache(env) is None and len(env) == 2
    env = {"HOME": str(tmp_path), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "3"}
    compile_cache.enable_compile_cache(env)
    assert env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "3"  # the user's is kept
    env = {"HOME": str(tmp_path)}
    assert compile_cache.enable_compile_cache(env) == tmp_path / ".cache/gslam-jax/jax"
    assert env["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / ".cache/gslam-jax/jax")
    with pytest.raises(ValueError, match="GSLAM_JAX_CACHE_MAX_MB"):
        compile_cache.enable_compile_cache({"HOME": str(tmp_path),
                                            "GSLAM_JAX_CACHE_MAX_MB": "lots"})


def test_prune_removes_the_least_recently_used_beyond_the_bound(tmp_path):
    now = time.time()
    for i in range(5):  # 1000 bytes each, file 0 the oldest
        f = tmp_path / f"key{i}-cache"
        f.write_bytes(b"x" * 1000)
        os.utime(f, (now - 100 * (5 - i), now - 100 * (5 - i)))
    assert compile_cache.prune(tmp_path, 2500) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["key3-cache", "key4-cache"]
    assert compile_cache.prune(tmp_path, 2500) == 0


def test_gslam_caches_compiled_programs_in_the_users_cache(tmp_path):
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAX_COMPILATION_CACHE", "GSLAM_JAX_CACHE", "XDG_CACHE"))}
    env.update(HOME=str(tmp_path), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
               PYTHONPATH=os.pathsep.join([str(Path(cli.__file__).parents[2]),
                                           env.get("PYTHONPATH", "")]))
    code = ("import os, sys; from gslam_jax.app.cli import main; main(['config']); "
            "import jax, jax.numpy as jnp; jax.jit(lambda x: jnp.sin(x) * 3)(jnp.ones(3)); "
            "print(os.environ['JAX_COMPILATION_CACHE_DIR'])")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    folder = tmp_path / ".cache/gslam-jax/jax"
    assert done.stdout.strip().splitlines()[-1] == str(folder)
    assert any(folder.iterdir())
    env["GSLAM_JAX_CACHE"] = ""
    done = subprocess.run([sys.executable, "-c", code.replace(
        "print(os.environ['JAX_COMPILATION_CACHE_DIR'])",
        "print(os.environ.get('JAX_COMPILATION_CACHE_DIR'))")], env=env, capture_output=True,
        text=True, timeout=120)
    assert done.stdout.strip().splitlines()[-1] == "None"
