"""Packages are found, never listed: trapflow's own, and workers/ under its install name.
The two folders of run-time files (the viewer's page, the demo models) are packages of data
too: setuptools warns about, and will stop installing, data folders that are not."""

from setuptools import find_packages, setup

WORKERS = "trapflow_workers"

setup(
    packages=find_packages(include=["trapflow", "trapflow.*"])
    + [WORKERS]
    + [f"{WORKERS}.{name}" for name in find_packages("workers")]
    + ["trapflow.viewer.static", f"{WORKERS}.models"],
)
