"""The host side of a run: what drives the filter (``rbpf``) over a Run and gives back NumPy.

* ``slam``: ``run_slam``, the chunked scan over a whole Run; ``results``: what it returns
  (``SlamResult``, its trajectories built on first use) and reports per chunk;
  ``chunk_checks``: the checks of each chunk's outputs;
* ``online``: the same filter one frame at a time for a live robot (``Online``);
* ``sizing``: the static filter config and parameters for a Run (map extent, memory);
  ``machine``: the machine's memory and CPU;
* ``observations``: a Run's local maps as the filter's observations;
* ``map_axes``: the axes of the map's lattice; ``map_reuse``: prior maps (``PriorMap``);
* ``device_arrays``: a Run's device arrays as the search and the tuner feed them.
"""
