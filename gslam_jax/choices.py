"""The allowed values of every enumerated setting, each defined once (no JAX: the CLI's
argument parser imports this before JAX is loaded).

Config validation (``config``), argparse ``choices`` (``cli``), the filter
(``rbpf.FilterConfig.validate``, ``resampling.RESAMPLERS``), the search and the tuner all read
these tuples; a test checks that the implementations behind them match.
"""

from __future__ import annotations

__all__ = ["UNKNOWN_CELLS", "RESAMPLERS", "TEMPERING", "MAP_STORES", "TUNE_OBJECTIVES",
           "SEARCH_OBJECTIVES", "SEARCH_DESIGNS", "ESTIMATES", "SCORE_PATHS", "PROPOSALS",
           "PROPOSAL_EXPONENTS", "BAD_FRAME_POLICIES", "STEREO_ALGORITHMS", "SENSORS",
           "AUTO_ESS_TARGET", "RANGE_NOISE", "PROPOSAL_DRAWS",
           "AUTO_PROPOSAL_DRAWS", "LOCALMAP_LATTICES", "AUTO_LOCALMAP_LATTICE", "MAP_AXES"]

UNKNOWN_CELLS = ("ignore", "sample")  # eq. 30 / eq. 31 (``[filter] unknown_cells``)
RESAMPLERS = ("multinomial", "systematic", "stratified", "residual")  # ``[filter] resampler``
MAP_STORES = ("dense", "shared", "window", "auto")  # ``[map] store``; "auto": dense or shared
# ``[filter] proposal``: the motion model alone (eq. 24) or informed by the local map
# (``rbpf.proposal``)
PROPOSALS = ("motion", "informed")
# ``[filter] proposal_exponent``: how the informed proposal's adaptive tempering exponent is
# chosen: from the spread of the score over the motion prior (what the motion proposal's
# particles would leave in the weights) or from the spread of each particle's normaliser over
# its prior (what the informed proposal leaves; ``rbpf.tempering.normaliser_exponent``)
PROPOSAL_EXPONENTS = ("prior", "normaliser")
# ``[filter] proposal_draws``: the proposals' standard normals drawn independently per particle,
# or in antithetic pairs (particle j + ceil(J/2) gets the negated draw of particle j), so that
# the particles' unweighted mean draw is zero (``rbpf.draws.standard_normals``);
# "auto" resolves by the run's sensor (``AUTO_PROPOSAL_DRAWS``)
PROPOSAL_DRAWS = ("independent", "antithetic", "auto")
# ``[filter] range_noise``: none (eq. 26 as in the paper), or a measurement variance per range
# estimated from the run (``observations.range_noise_profile``) added to each weighed cell
RANGE_NOISE = ("none", "profile")
TEMPERING = ("fixed", "adaptive")  # ``[filter] tempering`` (paper's beta / ``tempering``)
TUNE_OBJECTIVES = ("loglik", "supervised")  # ``gslam tune --objective``
SEARCH_OBJECTIVES = ("rms", "loglik")  # ``gslam search --objective``
SEARCH_DESIGNS = ("grid", "random", "halton", "sobol")  # ``gslam search --design``
# ``[filter] estimate``: the trajectory a run reports, the final best particle's ancestral path
# (the paper), the per-frame weighted posterior mean, the smoother's mean over every final
# particle's ancestral path, the path of those paths' mean steps, the ancestral path of the
# final particle with the most weight within 1 m (``rbpf.paths.densest_particle``), the
# smoother's mean over the final particles within 1 m of that one (``rbpf.mode_mean_path``), or
# the path of mean steps each weighed by the factors that bear on it (``rbpf.local_step_path``)
ESTIMATES = ("best", "mean", "smoothed", "steps", "mode", "mode_mean", "local_steps")
SCORE_PATHS = ESTIMATES  # ``gslam search --score-path`` (default: ``[filter] estimate``)
# ``[localmap] lattice``: each local map binned on the robot's axes (the paper's) or on the
# map's at its VO pose (``vo.localmap.LocalMapParams``); "auto" resolves by the sensor that
# makes the local maps (``AUTO_LOCALMAP_LATTICE``)
LOCALMAP_LATTICES = ("robot", "map", "auto")
# ``[map] axes``: the global map's lattice on the axes of the frame the run is given in (its
# start pose's and ground truth's), or on the robot's at its start pose, so that the result does
# not depend on how that frame is turned (``slam.map_heading``)
MAP_AXES = ("frame", "start")
BAD_FRAME_POLICIES = ("error", "fallback")  # ``gslam run --on-bad-frame``
STEREO_ALGORITHMS = ("sgbm", "bm")  # ``[stereo] algorithm`` (vo.stereo.DenseStereoParams)
# ``Run.sensor``: how a run's local maps were made. "points": independent height samples (the
# simulator's point sensor); "stereo": dense stereo through the front-end, where neighbouring
# cells share disparity errors, so the gamma likelihood (eq. 26) is overconfident.
SENSORS = ("points", "stereo")
# ``[filter] ess_target = 0`` (automatic) by the run's sensor; a run that names none: "points".
# Stereo keeps 99 % of the particles' ESS per update: on real KITTI and on rendered stereo with
# the default motion noise it is what keeps Gamma-SLAM under VO-only (docs/real-data.md; 0.98
# until the antithetic draws below, with which 0.99 kept RMS and final drift under VO's on 78
# of 80 seeds over three stereo logs, against 67 of 80 at 0.98).
AUTO_ESS_TARGET = {"points": 0.5, "stereo": 0.99}
# ``[filter] proposal_draws = "auto"`` by the run's sensor; a run that names none: "points".
# Stereo's weights are tempered nearly flat (above), so the estimate is close to the
# particles' unweighted mean, whose Monte Carlo error antithetic pairs remove: on the KITTI clip
# RMS and final drift both fell under VO's on 30 of 32 seeds, against 18 (docs/real-data.md). On the
# point sensor's Table I they were no better (the maze +27 % on seeds 0-4, docs/results.md).
AUTO_PROPOSAL_DRAWS = {"points": "independent", "stereo": "antithetic"}
# ``[localmap] lattice = "auto"``: the map's lattice for stereo, whose results on the robot's
# depended on the map frame's orientation (KITTI drift 0.16-0.81 % by the frame alone, 0.29-0.42
# % on the map's); the robot's for the simulator's point sensor, where the map's broke one of
# ten Table I maze seeds (docs/results.md, "The map frame's orientation")
AUTO_LOCALMAP_LATTICE = {"points": "robot", "stereo": "map"}
