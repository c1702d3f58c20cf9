"""Every file a ``gslam`` command writes: an existing one is refused before any work unless
``--overwrite``, a folder or a missing folder is refused, and nothing is left beside it.

The sweep lists each file-writing option of each command (results folders, ``--out`` of run,
merge, search, tune and compare, are swept in test_results.py). The work is replaced by a
function that fails the test: these checks come before it.
"""

from __future__ import annotations

import pytest
from cached_runs import run_file

from gslam_jax.app.cli import main

OLD = b"the user's file"


@pytest.fixture
def no_work(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("work started before the output file was checked")
    for name in ("gslam_jax.app.pipeline.prepare_source", "gslam_jax.driver.slam.run_slam",
                 "gslam_jax.app.bench.time_update", "gslam_jax.app.bench.time_course",
                 "gslam_jax.app.table1.run_course", "gslam_jax.app.arguments.config_and_run",
                 "gslam_jax.app.tuning_commands.config_and_run",
                 "gslam_jax.app.view.read_results"):
        monkeypatch.setattr(name, boom)


def _viewer_available() -> bool:
    try:
        from gslam_jax.app.viewer import require_rerun
        require_rerun()
    except Exception:  # noqa: BLE001 - the extra is optional
        return False
    return True


VIEWER = pytest.mark.skipif(not _viewer_available(), reason="the viewer extra is not installed")

# (command line with {run} for a Run file and {dir} for a folder, the option, the file's name)
WRITERS = [
    pytest.param(["run", "{run}", "--out", "{dir}/o", "--save-run"], "--save-run", "s.npz",
                 id="run --save-run"),
    pytest.param(["run", "{run}", "--out", "{dir}/o", "--viewer-save"], "--viewer-save",
                 "v.rrd", id="run --viewer-save", marks=VIEWER),
    pytest.param(["view", "{dir}", "--save"], "--save", "v.rrd", id="view --save", marks=VIEWER),
    pytest.param(["bench", "--particles", "8", "--json"], "--json", "b.json", id="bench --json"),
    pytest.param(["bench", "--particles", "8", "--plot"], "--plot", "b.png", id="bench --plot"),
    pytest.param(["table1", "--quick", "--json"], "--json", "t.json", id="table1 --json"),
    pytest.param(["config", "--out"], "--out", "c.toml", id="config --out"),
    pytest.param(["fit-motion", "{run}", "--out"], "--out", "m.toml", id="fit-motion --out"),
]


def _argv(argv: list[str], tmp_path, path) -> list[str]:
    run = run_file(tmp_path / "r.npz")[1]
    return [a.format(run=run, dir=tmp_path) for a in argv] + [str(path)]


@pytest.mark.parametrize("argv, option, name", WRITERS)
def test_an_existing_file_is_refused_before_any_work(argv, option, name, tmp_path, capsys,
                                                     no_work):
    """Before: --save-run, --viewer-save, view --save, bench/table1 --json and bench --plot
    replaced an existing file without asking (config and fit-motion --out refused it)."""
    path = tmp_path / name
    path.write_bytes(OLD)
    assert main(_argv(argv, tmp_path, path)) == 2
    assert f"gslam: error: {option} {path}: exists (--overwrite replaces it)" in \
        capsys.readouterr().err
    assert path.read_bytes() == OLD
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted({"r.npz", name})


@pytest.mark.parametrize("argv, option, name", WRITERS)
def test_a_folder_or_a_missing_folder_is_refused_before_any_work(argv, option, name, tmp_path,
                                                                 capsys, no_work):
    (tmp_path / name).mkdir()
    assert main(_argv(argv, tmp_path, tmp_path / name)) == 2
    assert f"{option} {tmp_path / name}: is a directory" in capsys.readouterr().err
    missing = tmp_path / "no" / name
    assert main(_argv(argv, tmp_path, missing)) == 2
    assert f"{option} {missing}: folder {missing.parent} does not exist" in \
        capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted({"r.npz", name})


def test_save_run_with_overwrite_replaces_the_file_when_complete(tmp_path, capsys):
    """--overwrite, as for --out, lets --save-run replace a file: atomically, when written."""
    from gslam_jax.run import load_run

    run, path = run_file(tmp_path / "r.npz")
    saved = tmp_path / "s.npz"
    saved.write_bytes(OLD)
    assert main(["run", str(path), "--set", "filter.particles=4", "--no-map-check",
                 "--out", str(tmp_path / "o"), "--save-run", str(saved), "--overwrite"]) == 0
    assert load_run(saved).num_frames == run.num_frames
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o", "r.npz", "s.npz"]
