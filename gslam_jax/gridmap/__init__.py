"""Finished variance grid maps: loading, moving between frames, aligning and merging them
(the paper's open problem of map merging, section 9)."""

from gslam_jax.gridmap.grid import (GridMap, MapFileError, add, apply_pose, compose, invert_pose,
                                    known_cells, load_map, place, save_map, transform,
                                    turn_poses)

__all__ = ["GridMap", "MapFileError", "add", "apply_pose", "compose", "invert_pose",
           "known_cells", "load_map", "place", "save_map", "transform", "turn_poses"]
