"""The Rerun viewer (optional extra ``viewer``): a run's values as Rerun log calls.

One concern: the project's values (particle clouds, poses, paths, the variance map, the ESS)
translated into Rerun entities on two timelines, ``frame`` (the frame index) and ``time``
(seconds on the run's clock, ``Run.timestamps``). Who calls it: ``gslam run --viewer`` /
``--viewer-save`` through ``slam.run_slam``'s ``on_chunk`` (:meth:`RunViewer.chunk`), ``gslam
view`` (``app.view``) for a finished run, and a live robot's loop (:meth:`RunViewer.online`).

Entities (one 3-D scene, z up, x/y the map frame's metres, everything at z = 0):

=========================  ====================================================================
``world/particles``        Points3D per frame: the particle cloud (at most ``max_particles``)
``world/pose/best|mean``   Points3D per frame: the highest-weight particle, the weighted mean
``world/path/best|mean``   LineStrips3D: the per-frame best and mean poses up to the chunk's end
``world/path/vo``          LineStrips3D: the VO-only path, as far as the filter has run
``world/path/ground_truth`` LineStrips3D: the truth where known (split at unknown frames)
``world/path/reported``    LineStrips3D: the results' path ([filter] estimate), once finished
``world/map``              GridMap: the best particle's map coloured by expected std (the map
                           figures' scale, 0.01 to 1 m, inferno), unobserved cells transparent
``stats/ess``              Scalars per frame: effective sample size (paper Fig. 4)
=========================  ====================================================================

Rerun is imported lazily (:func:`require_rerun`): the rest of gslam never needs it, and a
missing extra is a :class:`ViewerError` naming it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gslam_jax.errors import InputError
from gslam_jax.gridmap.grid import apply_pose, turn_poses

if TYPE_CHECKING:
    from gslam_jax.driver.online import Online, OnlineFrame
    from gslam_jax.driver.results import ChunkReport

__all__ = ["ViewerError", "RunViewer", "require_rerun", "has_display", "check_viewer",
           "open_viewer", "map_rgba", "finite_strips", "STD_RANGE", "INSTALL_HINT"]

INSTALL_HINT = "pip install 'gslam-jax[viewer]' (rerun-sdk >= 0.41)"
STD_RANGE = (0.01, 1.0)  # metres: the map figures' colour scale (app.plots), log scale
MAP_Z = -0.02            # the map lies just below the paths and particles
_COLOURS = {"best": (230, 60, 60), "mean": (255, 165, 0), "vo": (150, 150, 150),
            "ground_truth": (0, 200, 220), "reported": (255, 255, 255),
            "particles": (90, 140, 255)}


class ViewerError(InputError):
    """The viewer cannot be used as asked: the extra is missing, no display to spawn it on."""


def require_rerun(option: str = "--viewer") -> Any:
    """The ``rerun`` module, or a ViewerError naming ``option`` and the extra to install."""
    try:
        import rerun
    except ImportError as err:
        raise ViewerError(f"{option} needs the optional extra 'viewer': {INSTALL_HINT} "
                          f"({err})") from None
    if not hasattr(rerun, "GridMap"):  # the map's archetype; the rest is older
        raise ViewerError(f"{option}: rerun-sdk {getattr(rerun, '__version__', '?')} is too "
                          f"old: {INSTALL_HINT}")
    return rerun


def has_display() -> bool:
    """Whether a spawned viewer window can open: macOS and Windows always; elsewhere an X11
    ``DISPLAY`` or a ``WAYLAND_DISPLAY``."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def check_viewer(spawn: bool, save: Path | None, spawn_option: str = "--viewer",
                 save_option: str = "--viewer-save", overwrite: bool = False) -> None:
    """Before any work: ViewerError when Rerun is missing or ``spawn`` has no display;
    OutputFileError when ``save`` cannot be written, or exists and not ``overwrite``."""
    from gslam_jax.app.outfile import check_output_file

    if not spawn and save is None:
        return
    require_rerun(spawn_option if spawn else save_option)
    if spawn and not has_display():
        raise ViewerError(f"{spawn_option}: no display to open the viewer on (DISPLAY and "
                          f"WAYLAND_DISPLAY are unset); write a recording with {save_option} "
                          "FILE.rrd instead and open it with `rerun FILE.rrd` elsewhere")
    if save is not None:
        check_output_file(Path(save), save_option, overwrite)


def _blueprint(rr) -> Any:
    import rerun.blueprint as rrb

    return rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(origin="world", name="map"),
                                        rrb.TimeSeriesView(origin="stats", name="ESS"),
                                        column_shares=[3, 1]), collapse_panels=True)


def open_viewer(name: str, spawn: bool = False, save: Path | None = None,
                max_particles: int = 1000) -> RunViewer:
    """A RunViewer on a new recording ``name``: streamed to a spawned viewer (``spawn``),
    written to the file ``save`` (.rrd), or both. Call :func:`check_viewer` first."""
    rr = require_rerun("--viewer" if spawn else "--viewer-save")
    rec = rr.RecordingStream("gslam")
    rec.send_recording_name(name)
    blueprint = _blueprint(rr)
    if spawn and save is not None:
        rr.spawn(connect=False, recording=rec)
        rec.set_sinks(rr.GrpcSink(), rr.FileSink(str(save)), default_blueprint=blueprint)
    elif spawn:
        rec.spawn(default_blueprint=blueprint)
    elif save is not None:
        rec.save(str(save), default_blueprint=blueprint)
    return RunViewer(rec, max_particles)


def map_rgba(std: np.ndarray) -> np.ndarray:
    """A map's expected std [nx, ny] (axis 0 = x, NaN = unobserved) as a north-up RGBA image
    [ny, nx, 4] uint8: row 0 is the largest y (Rerun's GridMap is top row first, placed by its
    lower-left corner), coloured on STD_RANGE (log, inferno), unobserved cells transparent."""
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm

    img = np.flipud(np.asarray(std, np.float64).T)
    known = np.isfinite(img)
    norm = LogNorm(*STD_RANGE, clip=True)
    rgba = colormaps["inferno"](norm(np.where(known, img, STD_RANGE[0])), bytes=True)
    rgba[..., 3] = np.where(known, 255, 0)
    return np.ascontiguousarray(rgba, np.uint8)


def finite_strips(xy: np.ndarray) -> list[np.ndarray]:
    """The runs of consecutive finite rows of ``xy`` [T, >=2] as 3-D strips [n, 3] (z = 0):
    a path with unknown frames (NaN ground truth) is drawn in pieces, not joined across."""
    xy = np.asarray(xy, np.float64)[:, :2]
    ok = np.isfinite(xy).all(axis=1)
    strips, start = [], None
    for t, good in enumerate(np.append(ok, False)):
        if good and start is None:
            start = t
        elif not good and start is not None:
            strips.append(np.column_stack([xy[start:t], np.zeros(t - start)]))
            start = None
    return strips


def _xyz(xy: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy, np.float64)
    return np.concatenate([xy[..., :2], np.zeros(xy.shape[:-1] + (1,))], axis=-1)


class RunViewer:
    """Rerun logging for one run (see the module docstring for the entities)."""

    def __init__(self, rec, max_particles: int = 1000):
        import rerun as rr

        self.rr, self.rec, self.max_particles = rr, rec, int(max_particles)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for name in ("best", "mean"):
            rec.log(f"world/pose/{name}", rr.Points3D.from_fields(
                radii=0.12, colors=[_COLOURS[name]]), static=True)
        rec.log("world/particles", rr.Points3D.from_fields(
            radii=0.04, colors=[_COLOURS["particles"]]), static=True)

    def _at(self, frame: int, time_s: float | None) -> None:
        """The frame (and time, when known) the next logs are at."""
        self.rec.set_time("frame", sequence=int(frame))
        if time_s is not None:
            self.rec.set_time("time", duration=float(time_s))

    def _particles(self, poses: np.ndarray) -> np.ndarray:
        """[n, J, 3] -> [n, J', 3] with J' <= max_particles (evenly strided, deterministic)."""
        J = poses.shape[1]
        if J <= self.max_particles:
            return poses
        return poses[:, np.linspace(0, J - 1, self.max_particles).round().astype(int)]

    def frames(self, start: int, times: np.ndarray | None, best: np.ndarray, mean: np.ndarray,
               ess: np.ndarray | None = None, particles: np.ndarray | None = None) -> None:
        """Per-frame values of frames ``start`` .. ``start + n - 1`` in one call per entity:
        best and mean poses [n, 3], ESS [n], particle poses [n, J, 3]; ``times`` [n] seconds."""
        rr, n = self.rr, len(best)
        index = [rr.TimeColumn("frame", sequence=np.arange(start, start + n))]
        if times is not None:
            index.append(rr.TimeColumn("time", duration=np.asarray(times, np.float64)))
        for name, pose in (("best", best), ("mean", mean)):
            self.rec.send_columns(f"world/pose/{name}", indexes=index,
                                  columns=rr.Points3D.columns(positions=_xyz(pose)))
        if ess is not None:
            self.rec.send_columns("stats/ess", indexes=index,
                                  columns=rr.Scalars.columns(scalars=np.asarray(ess, float)))
        if particles is not None:
            cloud = self._particles(np.asarray(particles))
            columns = rr.Points3D.columns(positions=_xyz(cloud).reshape(-1, 3))
            self.rec.send_columns("world/particles", indexes=index,
                                  columns=columns.partition([cloud.shape[1]] * n))

    def paths(self, paths: dict[str, np.ndarray], frame: int | None = None,
              time_s: float | None = None) -> None:
        """Each path [T, >=2] as ``world/path/<name>`` at ``frame`` (None: static)."""
        rr = self.rr
        if frame is not None:
            self._at(frame, time_s)
        for name, xy in paths.items():
            width = 0.08 if name == "reported" else 0.05
            self.rec.log(f"world/path/{name}", rr.LineStrips3D(
                finite_strips(xy), radii=width, colors=[_COLOURS.get(name, (255, 255, 255))]),
                static=frame is None)

    def map(self, std: np.ndarray, origin: tuple[float, float], resolution: float,
            frame: int | None = None, time_s: float | None = None,
            heading: float = 0.0) -> None:
        """The map's expected std [nx, ny] (cell (i, j) at origin + (i, j) resolution on the
        lattice's axes, turned by ``heading`` in the frame: ``GridMap.heading``) as
        ``world/map`` at ``frame`` (None: static)."""
        rr = self.rr
        img = map_rgba(std)
        if frame is not None:
            self._at(frame, time_s)
        fmt = rr.components.ImageFormat(width=img.shape[1], height=img.shape[0],
                                        color_model="RGBA", channel_datatype="U8")
        corner = apply_pose(np.array([0.0, 0.0, heading]), np.asarray(origin)[None])[0]
        turn = {"rotation_axis_angle": rr.RotationAxisAngle(axis=[0.0, 0.0, 1.0],
                                                            radians=float(heading))} \
            if heading else {}
        self.rec.log("world/map", rr.GridMap(
            data=img.tobytes(), format=fmt, cell_size=float(resolution),
            translation=[*map(float, corner), MAP_Z], **turn), static=frame is None)

    def chunk(self, report: ChunkReport) -> None:
        """``slam.run_slam``'s ``on_chunk``: the chunk's frames (particles, poses, ESS), then
        at its last frame the paths so far (best and mean poses, VO, ground truth) and the best
        particle's map."""
        from gslam_jax import rbpf
        from gslam_jax.rbpf import cells

        run, start, n = report.run, report.start, len(report.best_pose)
        stop = start + n
        t = np.asarray(run.timestamps, np.float64)

        def framed(poses) -> np.ndarray:  # the run's frame (the filter's are on the map's axes)
            return turn_poses(poses, report.heading)

        best, mean = framed(report.best_pose), framed(report.mean_pose)
        self.frames(start, t[start:stop], best, mean, report.info.ess, framed(report.info.pose))
        if start == 0:
            self._best, self._mean = [], []
        self._best.append(best)
        self._mean.append(mean)
        paths = {"best": np.concatenate(self._best), "mean": np.concatenate(self._mean),
                 "vo": framed(run.vo_poses()[:stop])}
        if run.ground_truth is not None:
            paths["ground_truth"] = framed(np.asarray(run.ground_truth)[:stop])
        self.paths(paths, stop - 1, t[stop - 1])
        cfg, state = report.cfg, report.state
        k, S = rbpf.particle_map(state, int(state.best), cfg)
        self.map(np.asarray(cells.expected_std(k, S)), cfg.map_origin, cfg.resolution,
                 stop - 1, t[stop - 1], heading=report.heading)

    def online(self, online: Online, frame: OnlineFrame, time_s: float | None = None,
               map_every: int = 10) -> None:
        """One frame just pushed to ``online`` (``Online.push``): its particles, poses and ESS;
        every ``map_every`` frames also the best and mean paths so far and the best particle's
        map."""
        t = online.frames - 1
        parts = online.particles()
        times = None if time_s is None else np.array([time_s])
        self.frames(t, times, frame.pose[None], frame.mean[None], np.array([frame.ess]),
                    parts.pose[None])
        if map_every > 0 and t % map_every == 0:
            self.paths({"best": np.asarray(online.best), "mean": np.asarray(online.mean)},
                       t, time_s)
            grid = online.map()
            self.map(grid.expected_std(), grid.origin, grid.resolution, t, time_s)

    def flush(self) -> None:
        """Write out everything logged so far (the file or the viewer has it all)."""
        self.rec.flush()

    def close(self) -> None:
        """Flush and close the recording's sinks. A viewer that cannot be reached (closed,
        or never started) is a warning: the run and its results stand."""
        try:
            self.rec.flush()
        except RuntimeError as err:  # Rerun's sink errors, e.g. gRPC unable to connect
            print(f"WARNING: viewer: not everything reached the viewer ({err})", flush=True)
        self.rec.disconnect()
