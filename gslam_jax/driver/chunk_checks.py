"""The checks of what a chunk of filtered frames returns (``run_slam``, ``Online.push``):
non-finite weights, the map store's status, and the observed cells the filter skipped."""

from __future__ import annotations

import warnings

import numpy as np

from gslam_jax import rbpf
from gslam_jax.errors import InputError
from gslam_jax.rbpf import maps

__all__ = ["ExtentWarning", "WeightError", "check_weights", "pool_ran_out", "check_map_status",
           "check_observed_cells"]


class ExtentWarning(UserWarning):
    """Particles observed cells outside the map extent (those cells were skipped)."""


class WeightError(InputError):
    """The filter cannot weigh the data: an update left non-finite particle weights (ESS or
    log-likelihood not finite); names the frame and the local map."""


def check_weights(info: rbpf.StepInfo, start: int, frames: int, obs_index) -> None:
    """WeightError at the first of ``frames`` frames from ``start`` whose ESS or log_lik is
    not finite (NaN weights would otherwise be carried silently: no resampling, NaN poses).
    ``obs_index[t]``: frame t's local map (-1: none)."""
    ess = np.asarray(info.ess)[:frames]
    log_lik = np.asarray(info.log_lik)[:frames]
    bad = ~(np.isfinite(ess) & np.isfinite(log_lik))
    if bad.any():
        i = int(np.argmax(bad))
        t = start + i
        m = int(obs_index[t])
        what = (f"the filter cannot weigh local map {m}: the update with it left non-finite "
                f"particle weights" if m >= 0 else
                "non-finite particle weights at a frame without a local map")
        check = (f"check local map {m}'s statistics (n, sum z, sum z^2 per cell)" if m >= 0
                 else "check the run's controls and the local maps before this frame")
        raise WeightError(
            f"frame {t}: {what} (ESS {float(ess[i])}, evidence (log-likelihood) "
            f"{float(log_lik[i])}, not finite); {check}")


def pool_ran_out(info: rbpf.StepInfo) -> int:
    """1 + the chunk frame at which the shared pool first ran out of tiles; 0 if it did not."""
    return maps.pool_ran_out(np.asarray(info.map_status))


def check_map_status(info: rbpf.StepInfo, start: int, cfg: rbpf.FilterConfig,
                     automatic: bool = False) -> None:
    """The map store's error (``maps.check_status``) at the first frame it flagged;
    ``automatic``: the pool is grown by a ``maps.PoolGrowth``."""
    status = np.asarray(info.map_status)
    if status.any():
        i = int(np.argmax(status != 0))
        maps.check_status(status[i], cfg, where=f"frame {start + i}: ", automatic=automatic)


def check_observed_cells(infos: rbpf.StepInfo, cfg: rbpf.FilterConfig) -> int:
    """After a whole run: RuntimeError when observed local cells did not fit the filter's
    ``observed_cells`` (``sizing.observed_cells`` sizes it so that this cannot happen), an
    ``ExtentWarning`` when particle updates reached the map's edge; returns how many did."""
    dropped = int(np.sum(infos.dropped_cells))
    if dropped:
        raise RuntimeError(f"{dropped} observed local cells did not fit the filter's "
                           f"observed_cells = {cfg.max_observed}")
    violations = int(np.sum(infos.extent_violations))
    if violations:
        warnings.warn(f"{violations} particle updates reached the edge of the "
                      f"{cfg.map_shape} map; observed cells beyond the edge were skipped "
                      f"(neither weighed nor mapped). Increase [map] margin.", ExtentWarning,
                      stacklevel=2)
    return violations
