"""Results folders: complete or absent, never mixed; failures and interrupts leave nothing.

The filter is replaced by a stand-in that returns the VO path (``fake_slam``): these tests are
about the files around it, and run in a second or two. With ``fake_slam`` the figures are
built but not drawn (``quick_figures``: each ``savefig`` writes a 1 x 1 PNG where the figure
would go), as drawing them was most of these tests' time;
``test_results_appear_complete_with_a_marker`` draws them, and test_cli.py's runs check them.
"""

import base64
import errno
import json
import time

import numpy as np
import pytest
from cached_runs import shared_run

from gslam_jax.app.cli import main
from gslam_jax.driver import slam
from gslam_jax.driver.results import PathEstimates, SlamResult
from gslam_jax.gps import GpsLogError
from gslam_jax.io import read_tum, write_tum
from gslam_jax.run import load_run, save_run

MARKER = "COMPLETE"  # the documented name of the completeness marker


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    run = shared_run()  # the CLI tests' Run, built once per process
    path = tmp_path_factory.mktemp("run") / "r.npz"
    save_run(path, run)
    return run, path


# A 1 x 1 grey PNG: what ``quick_figures`` writes in place of a drawn figure.
TINY_PNG = base64.b64decode("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAAAAAA6fptVAAAACklEQVR4nGNoAAAAggCB"
                            "d81ytgAAAABJRU5ErkJggg==")


@pytest.fixture
def quick_figures(monkeypatch):
    """``Figure.savefig`` writes ``TINY_PNG`` to the file it is given instead of drawing the
    figure (the figures are still built, and every file is written where it would be)."""
    from matplotlib.figure import Figure

    def savefig(self, fname, *args, **kwargs):
        if hasattr(fname, "write"):
            fname.write(TINY_PNG)
            return
        with open(fname, "wb") as f:
            f.write(TINY_PNG)
    monkeypatch.setattr(Figure, "savefig", savefig)


@pytest.fixture
def fake_slam(drawn_fake_slam, quick_figures):
    """``drawn_fake_slam`` with ``quick_figures``."""
    return drawn_fake_slam


@pytest.fixture
def drawn_fake_slam(monkeypatch):
    """``slam.run_slam`` returning the VO path; ``calls`` lists the runs it was given."""
    calls = []

    def fake(run, config, progress=None, **kwargs):
        calls.append(run)
        T, vo = run.num_frames, run.vo_poses()
        return SlamResult(
            paths=PathEstimates.given(best=vo, map=vo, smoothed=vo), best_pose=vo,
            mean_pose=vo, vo_path=vo,
            ess=np.full(T, 8.0),
            resampled=np.zeros(T, bool), updated=np.asarray(run.obs_index) >= 0,
            log_lik=np.zeros(T), exponent=np.ones(T), kmap=np.ones((24, 24), np.float32),
            smap=np.ones((24, 24), np.float32), map_origin=(-2.0, -2.0), resolution=0.16,
            extent_violations=0, empty_observations=0, seconds=0.0, compile_seconds=0.0)
    monkeypatch.setattr(slam, "run_slam", fake)
    return calls


def _leftovers(folder):
    """Hidden staging / old folders left beside a results folder."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_results_appear_complete_with_a_marker(tmp_path, run_file, drawn_fake_slam, monkeypatch):
    run, path = run_file
    out = tmp_path / "out"
    seen = []
    real = slam.run_slam

    def spy(*args, **kwargs):
        seen.append(out.exists())  # during the run, --out does not exist yet
        return real(*args, **kwargs)
    monkeypatch.setattr(slam, "run_slam", spy)
    assert main(["run", str(path), "--out", str(out)]) == 0
    assert seen == [False]
    marker = json.loads((out / MARKER).read_text())
    files = {p.name: p.stat().st_size for p in out.iterdir() if p.name != MARKER}
    assert marker["files"] == files and "summary.json" in files and "map.png" in files
    assert _leftovers(tmp_path) == []


def test_existing_results_are_refused_without_overwrite(tmp_path, run_file, fake_slam, capsys):
    _, path = run_file
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert main(["run", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: is a finished results folder" in err and "--overwrite" in err
    assert len(fake_slam) == 1  # refused before the second run
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_overwrite_replaces_the_folder_as_a_whole(tmp_path, run_file, fake_slam):
    _, path = run_file
    out = tmp_path / "out"
    assert main(["run", str(path), "--gps", "sim", "--out", str(out)]) == 0
    assert (out / "trajectory_utm.txt").exists() and (out / "gps_alignment.npz").exists()
    assert main(["run", str(path), "--out", str(out), "--overwrite"]) == 0
    names = {p.name for p in out.iterdir()}
    assert not {"trajectory_utm.txt", "map_utm.png", "gps_alignment.npz"} & names
    assert json.loads((out / MARKER).read_text())["files"].keys() == names - {MARKER}
    assert "gps" not in json.loads((out / "summary.json").read_text())
    assert _leftovers(tmp_path) == []


def test_overwrite_never_replaces_a_folder_of_other_files(tmp_path, run_file, fake_slam, capsys):
    _, path = run_file
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    assert main(["run", str(path), "--out", str(mine), "--overwrite"]) == 2
    assert "holds files gslam does not write (notes.txt)" in capsys.readouterr().err
    assert (mine / "notes.txt").read_text() == "keep me" and not fake_slam


def test_a_failed_write_leaves_no_results(tmp_path, run_file, fake_slam, capsys, monkeypatch):
    from gslam_jax.app import plots

    _, path = run_file
    out = tmp_path / "deep" / "out"

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(plots, "save_ess_png", full)
    assert main(["run", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cannot write the results" in err and "No space left on device" in err
    assert not (tmp_path / "deep").exists()  # created for this run, removed again


def test_an_unwritable_place_is_found_before_the_run(tmp_path, run_file, fake_slam, capsys,
                                                      monkeypatch):
    import tempfile

    _, path = run_file
    real = tempfile.mkdtemp

    def read_only(*args, dir=None, **kwargs):
        if dir is not None and str(dir).startswith(str(tmp_path / "ro")):
            raise PermissionError(errno.EACCES, "Permission denied", str(dir))
        return real(*args, dir=dir, **kwargs)
    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    (tmp_path / "ro").mkdir()
    assert main(["run", str(path), "--out", str(tmp_path / "ro" / "out")]) == 2
    assert "cannot write there (Permission denied); nothing was run" in capsys.readouterr().err
    assert not fake_slam


def test_save_run_place_is_checked_before_the_run(tmp_path, run_file, fake_slam, capsys,
                                                   monkeypatch):
    _, path = run_file
    (tmp_path / "adir").mkdir()
    out = tmp_path / "out"
    assert main(["run", str(path), "--save-run", str(tmp_path / "adir"), "--out", str(out)]) == 2
    assert "--save-run" in capsys.readouterr().err and not fake_slam
    assert main(["run", str(path), "--save-run", str(tmp_path / "no" / "r.npz"),
                 "--out", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err and not fake_slam and not out.exists()

    import tempfile

    def read_only(*args, dir=None, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(dir))
    monkeypatch.setattr(tempfile, "mkstemp", read_only)  # root may write anywhere: simulated
    assert main(["run", str(path), "--save-run", str(tmp_path / "r2.npz"), "--out", str(out)]) == 2
    assert f"--save-run {tmp_path / 'r2.npz'}: cannot write in {tmp_path} (Permission denied)" \
        in capsys.readouterr().err and not fake_slam and not out.exists()


def test_ctrl_c_is_a_short_message_and_exit_130(tmp_path, run_file, monkeypatch, capsys):
    _, path = run_file

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(slam, "run_slam", interrupted)
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out)]) == 130
    assert capsys.readouterr().err.strip() == "gslam: interrupted; no results were written"
    assert not out.exists() and _leftovers(tmp_path) == []


def test_jax_out_of_memory_is_a_message(tmp_path, run_file, monkeypatch, capsys):
    import jax

    _, path = run_file

    def exhausted(*args, **kwargs):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to "
                                         "allocate 25769803776 bytes.")
    monkeypatch.setattr(slam, "run_slam", exhausted)
    assert main(["run", str(path), "--out", str(tmp_path / "out")]) == 3
    err = capsys.readouterr().err
    assert err.startswith("gslam: error: out of memory (RESOURCE_EXHAUSTED") and "ulimit" in err
    assert "Traceback" not in err


def test_ground_truth_is_written_beside_the_estimate(tmp_path, run_file, fake_slam):
    run, _ = run_file
    gt = np.array(run.ground_truth)
    gt[3:6] = np.nan
    save_run(tmp_path / "r.npz", run._replace(ground_truth=gt))
    out = tmp_path / "out"
    assert main(["run", str(tmp_path / "r.npz"), "--out", str(out)]) == 0
    t, poses = read_tum(out / "ground_truth_tum.txt")
    known = np.isfinite(gt).all(axis=1)
    np.testing.assert_allclose(t, np.asarray(run.timestamps)[known], atol=1e-9)
    np.testing.assert_allclose(poses[:, :2], gt[known, :2], atol=1e-8)
    np.testing.assert_allclose(np.angle(np.exp(1j * (poses[:, 2] - gt[known, 2]))), 0, atol=1e-8)
    t_est, _ = read_tum(out / "trajectory_tum.txt")
    assert set(t) <= set(t_est)  # the same clock: evo associates them


def test_tum_files_keep_the_dataset_clock(tmp_path, run_file):
    # EuRoC stamps in ns: float64 seconds since 1970 cannot hold all nine decimals.
    origin = 1403636579763555584
    write_tum(tmp_path / "t.txt", np.array([0.0, 0.05, 1.25]), np.zeros((3, 3)), origin_ns=origin)
    stamps = [line.split()[0] for line in (tmp_path / "t.txt").read_text().splitlines()[1:]]
    assert stamps == ["1403636579.763555584", "1403636579.813555584", "1403636581.013555584"]
    save_run(tmp_path / "r.npz", run_file[0]._replace(time_origin_ns=origin))
    assert load_run(tmp_path / "r.npz").time_origin_ns == origin


def test_a_second_command_on_the_same_out_never_mixes(tmp_path, run_file, fake_slam, monkeypatch,
                                                      capsys):
    _, path = run_file
    out = tmp_path / "out"
    real = slam.run_slam

    def other_finishes_first(*args, **kwargs):
        out.mkdir()  # another gslam command on the same --out finishes while this one runs
        (out / "summary.json").write_text("{}")
        (out / MARKER).write_text("{}")
        return real(*args, **kwargs)
    monkeypatch.setattr(slam, "run_slam", other_finishes_first)
    assert main(["run", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "another command wrote there while this one ran" in err
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "summary.json"]  # untouched
    kept = tmp_path / err.split("kept in ")[1].strip().split("/")[-1]
    assert (kept / MARKER).is_file() and (kept / "trajectory_tum.txt").is_file()


def test_a_failing_gps_output_leaves_no_folder_that_looks_complete(tmp_path, run_file, fake_slam,
                                                                   monkeypatch, capsys):
    from gslam_jax.gps import georeference

    _, path = run_file

    def crash(*args, **kwargs):
        raise GpsLogError("simulated GPS: the fit failed")
    monkeypatch.setattr(georeference, "write_gps_outputs", crash)
    out = tmp_path / "out"
    assert main(["run", str(path), "--gps", "sim", "--out", str(out)]) == 2
    assert "the fit failed" in capsys.readouterr().err
    assert not out.exists() and _leftovers(tmp_path) == []


def test_an_existing_read_only_out_is_refused_before_the_run(tmp_path, run_file, fake_slam,
                                                              monkeypatch, capsys):
    import os

    _, path = run_file
    out = tmp_path / "ro"
    out.mkdir()
    real = os.access
    # root may write anywhere, so the permission bits are simulated: --out is read-only
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if str(p) == str(out) and
                        mode == os.W_OK else real(p, mode, **kw))
    assert main(["run", str(path), "--out", str(out)]) == 2
    assert f"--out {out}: is read-only" in capsys.readouterr().err and not fake_slam


def test_overwrite_never_trusts_a_complete_file_gslam_did_not_write(tmp_path, run_file,
                                                                    fake_slam, capsys):
    _, path = run_file
    thesis = tmp_path / "thesis"
    thesis.mkdir()
    (thesis / "thesis.tex").write_text("\\chapter{}")
    (thesis / MARKER).write_text("done\n")
    before = {p.name: p.read_bytes() for p in thesis.iterdir()}
    assert main(["run", str(path), "--out", str(thesis), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert f"--out {thesis}: holds files gslam does not write" in err and "thesis.tex" in err
    assert {p.name: p.read_bytes() for p in thesis.iterdir()} == before and not fake_slam
    # without --overwrite it is not called a finished results folder either
    assert main(["run", str(path), "--out", str(thesis)]) == 2
    assert "not empty (2 entries)" in capsys.readouterr().err


def test_overwrite_keeps_files_the_marker_does_not_list(tmp_path, run_file, fake_slam, capsys):
    from gslam_jax.app.results import MARKER_FORMAT, is_complete

    _, path = run_file
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out)]) == 0
    marker = json.loads((out / MARKER).read_text())
    assert next(iter(marker)) == "format" and marker["format"] == MARKER_FORMAT
    assert is_complete(out)
    (out / "notes.txt").write_text("mine")  # the user's file added to a results folder
    assert main(["run", str(path), "--out", str(out), "--overwrite"]) == 2
    assert "holds files gslam does not write (notes.txt)" in capsys.readouterr().err
    (out / "notes.txt").unlink()
    (out / "map.png").unlink()  # a marker whose files are gone does not count
    assert not is_complete(out)
    assert main(["run", str(path), "--out", str(out), "--overwrite"]) == 2
    assert "holds files gslam does not write (COMPLETE)" in capsys.readouterr().err
    assert len(fake_slam) == 1


@pytest.mark.parametrize("kind", ["empty", "dangling", "loop"])
def test_out_as_a_symlink_writes_into_its_target(tmp_path, run_file, fake_slam, capsys, kind):
    _, path = run_file
    real = tmp_path / "disk" / "real"
    link = tmp_path / "link"
    if kind == "empty":
        real.mkdir(parents=True)
    if kind == "loop":
        link.symlink_to(tmp_path / "link2")
        (tmp_path / "link2").symlink_to(link)
        assert main(["run", str(path), "--out", str(link)]) == 2
        assert f"--out {link}: is a symbolic link that resolves to no folder" in \
            capsys.readouterr().err and not fake_slam
        return
    link.symlink_to(real, target_is_directory=True)
    assert main(["run", str(path), "--out", str(link)]) == 0
    assert link.is_symlink() and link.resolve() == real.resolve()
    assert json.loads((real / MARKER).read_text())["files"].keys() >= {"summary.json"}
    assert _leftovers(real.parent) == [] and _leftovers(tmp_path) == []
    # a second run into the link is refused as a finished folder, and --overwrite replaces it
    assert main(["run", str(path), "--out", str(link)]) == 2
    assert "is a finished results folder" in capsys.readouterr().err
    assert main(["run", str(path), "--out", str(link), "--overwrite"]) == 0
    assert link.is_symlink() and (link / MARKER).is_file() and _leftovers(real.parent) == []


def test_out_as_the_current_folder_is_refused_before_the_run(tmp_path, monkeypatch, capsys):
    """Renaming onto the working folder fails (EBUSY) after the whole run: refused first."""
    from gslam_jax.app.results import ResultsError, results_folder

    work = tmp_path / "empty"
    work.mkdir()
    monkeypatch.chdir(work)
    with pytest.raises(ResultsError, match=r"--out \.: is the current folder"):
        with results_folder(".", "run"):
            pytest.fail("work started before --out was checked")
    assert list(work.iterdir()) == []


def test_sigterm_removes_the_staging_folder_like_ctrl_c(tmp_path):
    """Before: SIGTERM ended ``gslam run`` at once (exit -15) and left .o.partial-* behind."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "gslam_jax.app.cli", "run", "--max-frames",
                             "400", "--out", str(out)], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob(".o.partial-*")):
            assert proc.poll() is None and time.monotonic() < deadline, "no staging folder"
            time.sleep(0.05)
        time.sleep(0.5)  # well inside the work (the simulator runs for seconds)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert "terminated (SIGTERM); no results were written" in err
    assert list(tmp_path.iterdir()) == []
