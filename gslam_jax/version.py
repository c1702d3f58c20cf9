"""The package's version, in a module of its own so that every layer may read it (the package
root, which re-exports it as ``gslam_jax.__version__``, sits above them all)."""

__version__ = "0.1.0"
