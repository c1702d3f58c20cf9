"""The allowed values of every enumerated setting, each defined once (no JAX: the CLI's
argument parser imports this before JAX is loaded).

The settings' declarations (``config.sections``, whose rules the config and
``rbpf.FilterConfig.validate`` share), argparse ``choices`` (``cli``), ``resampling.RESAMPLERS``,
the search and the tuner all read these tuples; a test checks that the implementations behind
them match. Why the automatic values are what they are: docs/appendix/settings-rationale.md.
"""

from __future__ import annotations

__all__ = ["UNKNOWN_CELLS", "RESAMPLERS", "TEMPERING", "MAP_STORES", "TUNE_OBJECTIVES",
           "SEARCH_OBJECTIVES", "SEARCH_DESIGNS", "ESTIMATES", "SCORE_PATHS", "PROPOSALS",
           "PROPOSAL_EXPONENTS", "BAD_FRAME_POLICIES", "STEREO_ALGORITHMS", "SENSORS",
           "AUTO_ESS_TARGET", "RANGE_NOISE", "PROPOSAL_DRAWS",
           "AUTO_PROPOSAL_DRAWS", "LOCALMAP_LATTICES", "AUTO_LOCALMAP_LATTICE", "MAP_AXES"]

# The values of each enumerated setting; what each means is the setting's declaration
# (``config.sections``, printed by ``gslam config``).
UNKNOWN_CELLS = ("ignore", "sample")  # ``[filter] unknown_cells``: eq. 30 / eq. 31
RESAMPLERS = ("multinomial", "systematic", "stratified", "residual")  # ``[filter] resampler``
MAP_STORES = ("dense", "shared", "window", "auto")  # ``[map] store``; "auto" resolves to one of the others
PROPOSALS = ("motion", "informed")  # ``[filter] proposal`` (``rbpf.proposal.RULES``)
PROPOSAL_EXPONENTS = ("prior", "normaliser")  # ``[filter] proposal_exponent``
# ``[filter] proposal_draws``; "auto" resolves by the run's sensor (``AUTO_PROPOSAL_DRAWS``)
PROPOSAL_DRAWS = ("independent", "antithetic", "auto")
RANGE_NOISE = ("none", "profile")  # ``[filter] range_noise``
TEMPERING = ("fixed", "adaptive")  # ``[filter] tempering`` (paper's beta / ``tempering``)
TUNE_OBJECTIVES = ("loglik", "supervised")  # ``gslam tune --objective``
SEARCH_OBJECTIVES = ("rms", "loglik")  # ``gslam search --objective``
SEARCH_DESIGNS = ("grid", "random", "halton", "sobol")  # ``gslam search --design``
# ``[filter] estimate``
ESTIMATES = ("best", "mean", "smoothed", "steps", "mode", "mode_mean", "local_steps")
SCORE_PATHS = ESTIMATES  # ``gslam search --score-path`` (default: ``[filter] estimate``)
# ``[localmap] lattice``; "auto" resolves by the sensor (``AUTO_LOCALMAP_LATTICE``)
LOCALMAP_LATTICES = ("robot", "map", "auto")
MAP_AXES = ("frame", "start")  # ``[map] axes``
BAD_FRAME_POLICIES = ("error", "fallback")  # ``gslam run --on-bad-frame``
STEREO_ALGORITHMS = ("sgbm", "bm")  # ``[stereo] algorithm`` (vo.stereo.DenseStereoParams)
# ``Run.sensor``: how a run's local maps were made. "points": independent height samples (the
# simulator's point sensor); "stereo": dense stereo through the front-end, where neighbouring
# cells share disparity errors, so the gamma likelihood (eq. 26) is overconfident.
SENSORS = ("points", "stereo")
# ``[filter] ess_target = 0`` (automatic) by the run's sensor; a run that names none: "points"
AUTO_ESS_TARGET = {"points": 0.5, "stereo": 0.99}
# ``[filter] proposal_draws = "auto"`` by the run's sensor; a run that names none: "points"
AUTO_PROPOSAL_DRAWS = {"points": "independent", "stereo": "antithetic"}
# ``[localmap] lattice = "auto"`` by the sensor that makes the local maps
AUTO_LOCALMAP_LATTICE = {"points": "robot", "stereo": "map"}
