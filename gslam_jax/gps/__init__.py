"""GPS (paper section 8 and appendix): a SLAM run placed on the Earth.

Modules: ``align`` (weighted Procrustes alignment of SLAM paths to GPS readings, batch and
online, eqs. A.1-A.10), ``utm`` (WGS84 <-> UTM, Krueger-Karney series), ``log`` (GPS log files
read into a UTM site frame), ``raster`` (north-up PNG maps with world files), ``georeference``
(a run's GPS check and its UTM outputs) and ``simulate`` (a WAAS-like receiver). The names of
the first four are re-exported here; ``georeference`` and ``simulate`` are imported by name.
"""

from gslam_jax.gps.align import (
    Alignment, OnlineState, align, align_particles, align_to_gps, interpolate_path, online_init,
    online_solve, online_update, readings_in_span, transform_points, transform_poses,
)
from gslam_jax.gps.log import GpsLog, GpsLogError, read_gps_log, write_gps_log
from gslam_jax.gps.raster import (
    lattice_rotation, map_corners, world_file_params, write_georeferenced_png,
    write_world_file,
)
from gslam_jax.gps.utm import (
    WGS84, Ellipsoid, latlon_to_utm, transverse_mercator, utm_epsg, utm_to_latlon, utm_zone,
)

__all__ = [
    "Alignment", "OnlineState", "align", "align_particles", "online_init", "online_update",
    "online_solve", "transform_points", "transform_poses", "interpolate_path",
    "GpsLog", "GpsLogError", "read_gps_log", "write_gps_log", "latlon_to_utm", "utm_to_latlon",
    "utm_zone", "utm_epsg", "transverse_mercator", "Ellipsoid", "WGS84",
    "align_to_gps", "readings_in_span", "map_corners", "lattice_rotation", "world_file_params",
    "write_world_file",
    "write_georeferenced_png",
]
