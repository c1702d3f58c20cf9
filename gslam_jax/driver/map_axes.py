"""The axes of the map's lattice for a Run: their angle in the run's frame (a prior map's, or
by ``[map] axes``), the run expressed on them, and the check that its local maps were binned on
the same axes (``run_slam`` filters on them and turns its results back)."""

from __future__ import annotations

import math
import warnings

import numpy as np

from gslam_jax.config import Config
from gslam_jax.driver.map_reuse import PriorMap, rebase
from gslam_jax.gridmap import turn_poses
from gslam_jax.run import Run
from gslam_jax.vo.localmap import map_axes_heading

__all__ = ["map_heading", "on_map_axes", "filtered_run", "LatticeWarning", "local_lattice_axes",
           "check_local_lattices"]


def map_heading(run: Run, config: Config, prior: PriorMap | None = None) -> float:
    """The angle (radians) of the map lattice's axes in the run's frame: a prior map's
    (``GridMap.heading``), else by ``[map] axes``: 0 ("frame"), or the run's start heading
    ("start"), so that turning the frame the run is given in turns the result with it and
    changes nothing else."""
    if prior is not None:
        return float(prior.grid.heading)
    return map_axes_heading(config.map.axes, run.start_pose())


def on_map_axes(run: Run, heading: float) -> Run:
    """``run`` in its frame turned by ``heading`` about the origin (the lattice's axes): its
    start pose and ground truth expressed there; controls and local maps (robot frame) as
    they are. ``turn_poses(x, heading)`` carries the filter's poses back."""
    if not heading:
        return run
    truth = run.ground_truth
    if truth is not None:
        truth = turn_poses(truth, -heading)
    return run._replace(initial_pose=turn_poses(run.start_pose(), -heading),
                        ground_truth=truth)



def filtered_run(run: Run, config: Config, prior: PriorMap | None = None
                 ) -> tuple[Run, float, Run]:
    """``run`` as given (rebased on a ``prior``'s start), the angle of the map lattice's axes
    in its frame (``map_heading``) and the run on those axes (``on_map_axes``): what
    ``run_slam`` filters."""
    if prior is not None:
        run = rebase(run, prior.start)
    heading = map_heading(run, config, prior)
    return run, heading, on_map_axes(run, heading)

class LatticeWarning(UserWarning):
    """A run's local maps were binned on the map's axes ("map" lattice) at another angle than
    the map lattice the filter runs on: each local cell is then placed by its centre, two into
    some map cells and none into others (docs/notebook/results.md, "The map frame's
    orientation")."""


def local_lattice_axes(run: Run, tolerance: float = 1e-4) -> float | None:
    """The angle (radians) in the run's frame of the axes its local maps were binned on: the
    VO heading of each local map's frame plus its lattice heading (``Run.lattice_headings``),
    when that is one angle for every local map (a "map" lattice); None otherwise (the robot's
    axes, or no local map)."""
    if run.lattice_headings is None or not run.num_local_maps:
        return None
    t = np.flatnonzero(run.obs_index >= 0)
    turns = np.exp(1j * (run.vo_poses()[t, 2]
                         + np.asarray(run.lattice_headings, np.float64)[run.obs_index[t]]))
    mean = turns.mean()
    if np.max(np.abs(np.angle(turns / mean))) > tolerance:
        return None
    return float(np.angle(mean))


def check_local_lattices(run: Run, heading: float) -> None:
    """``LatticeWarning`` when the local maps lie on other axes than the map's at ``heading``."""
    axes = local_lattice_axes(run)
    if axes is not None and abs(math.remainder(axes - heading, 2 * math.pi)) > 1e-4:
        warnings.warn(LatticeWarning(
            f"the run's local maps were binned on the map's axes at {math.degrees(axes):.3f} "
            f"deg in its frame, but the map lattice lies at {math.degrees(heading):.3f} deg "
            "([map] axes, or a prior map's): each local cell is placed by its centre. Build the "
            "run with the [map] axes it is filtered with"), stacklevel=3)
