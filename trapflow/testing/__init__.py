"""trapflow's test kit, installed with it: what a plugin author needs to test a plugin without
a pipeline (make_pair, make_context, run_plugin), the plugins trapflow's own tests and
benchmarks run (plugins.py), and the references they measure against (vo_metrics.py,
checkerboard.py). Nothing in the runtime imports it."""

from trapflow.testing.kit import make_context, make_pair, run_plugin

__all__ = ["make_context", "make_pair", "run_plugin"]
