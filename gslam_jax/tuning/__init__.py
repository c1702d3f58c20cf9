"""Parameter search and tuning.

* ``space``: the table of searchable settings (section, bounds, integer or not) and the search
  space over them;
* ``designs``: grid, random, Halton and Sobol designs;
* ``evaluation``: the objectives (RMS after the rigid fit, log-likelihood) and the batched,
  sharded evaluation of many parameter sets;
* ``search``: ``search()``, its result and ranking; ``strategies``: successive halving and
  Optuna's TPE on top of it; ``distributed``: the same over a Dask cluster;
* ``gradient``: optax tuning with the Scibior-Wood estimator;
* ``motion_fit``: the maximum-likelihood motion noise of a log with ground truth.
"""
