"""``gslam --version``, ``gslam config`` and the examples at the end of every ``--help``."""

import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

import gslam_jax
from gslam_jax.app.cli import build_parser, main
from gslam_jax.config import Config, load_config

ROOT = Path(__file__).resolve().parents[1]


def test_version_names_the_package_and_its_stack():
    out = subprocess.run([sys.executable, "-m", "gslam_jax.app.cli", "--version"],
                         capture_output=True, text=True, check=False)
    assert out.returncode == 0 and out.stderr == ""
    line = out.stdout.strip()
    assert line.startswith(f"gslam {gslam_jax.__version__} (")
    for dist in ("jax", "numpy"):
        assert f"{dist} {metadata.version(dist)}" in line
    assert "opencv " in line and "not installed" not in line


def test_version_is_the_one_the_package_is_installed_as():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert gslam_jax.__version__ == project["version"]


def test_config_prints_the_defaults_as_toml_that_load_back(tmp_path, capsys):
    assert main(["config"]) == 0
    text = capsys.readouterr().out
    assert "[filter]" in text and "[motion]" in text
    path = tmp_path / "printed.toml"
    path.write_text(text)
    assert load_config(path) == Config()


def test_config_out_writes_the_file_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "c.toml"
    assert main(["config", "--out", str(out), "--set", "filter.particles=37"]) == 0
    assert load_config(out).filter.particles == 37
    assert load_config(out).motion == Config().motion
    assert main(["config", "--out", str(out)]) == 2
    assert "exists (--overwrite replaces it)" in capsys.readouterr().err
    assert load_config(out).filter.particles == 37  # untouched
    assert main(["config", "--out", str(out), "--overwrite"]) == 0
    assert load_config(out) == Config()
    assert [p.name for p in tmp_path.iterdir()] == ["c.toml"]  # no temporary left behind
    assert main(["config", "--out", str(tmp_path)]) == 2  # a folder
    assert "is a directory" in capsys.readouterr().err


def _commands():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices


@pytest.mark.parametrize("name", sorted(_commands()))
def test_every_commands_help_ends_with_examples(name, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([name, "--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out.rstrip()
    tail = text[text.rindex("examples:"):].splitlines()[1:]
    assert 2 <= len(tail) <= 3, text
    assert all(line.strip().startswith(f"gslam {name}") for line in tail), tail


@pytest.mark.parametrize("name", sorted(_commands()))
def test_every_example_parses(name):
    """Each example is a valid command line (file arguments aside, which run time checks)."""
    from gslam_jax.app.info import EXAMPLES

    for line in EXAMPLES[name].splitlines():
        words = line.split("#")[0].split()
        assert words[:2] == ["gslam", name]
        build_parser().parse_args(words[1:])
