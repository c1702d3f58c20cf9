"""GPS (paper section 8 and appendix): weighted Procrustes alignment of a SLAM path to GPS
readings, batch and online (``core``), the georeferenced outputs of a run
(``georeference``) and a simulated WAAS-like receiver (``simulate``)."""

from gslam_jax.gps.core import *  # noqa: F401,F403
from gslam_jax.gps.core import __all__  # noqa: F401
