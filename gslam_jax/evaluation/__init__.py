"""How good a run is: trajectory errors after the rigid fit, drift and ESS summaries
(``metrics``, paper 7.1), and loop closure as a measured verdict (``loops``)."""
