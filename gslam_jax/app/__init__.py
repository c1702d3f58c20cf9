"""The application layer: the ``gslam`` command line (``cli``), ``gslam run`` as functions
(``pipeline``), the results folder (``results``), figures (``plots``), progress bars
(``progress``), and the commands table1, bench and compare."""
