"""Experiments and benchmarks behind the figures in docs/: run one from the repository root as
``python -m experiments.<name>`` (e.g. ``python -m experiments.weights_scan --help``)."""
