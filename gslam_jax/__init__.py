"""gslam-jax: Gamma-SLAM (Marks et al., Journal of Field Robotics 26(1), 2009) in JAX.

Modules: ``cells`` (cell statistics, eqs. 5-26), ``motion`` (eqs. 1-3), ``resampling``,
``unknown``, ``rbpf`` (the dense particle filter), ``localmap``, ``run`` (the Run container),
``slam`` (host driver), ``config`` and ``choices`` (settings), ``machine`` (memory, CPU),
``vo`` and ``datasets`` (front-ends), ``sim``, ``tiled`` (the reference), ``gps``, ``search``,
``tuning``, ``metrics``, ``plots``, ``cli``.
"""

__version__ = "0.1.0"
