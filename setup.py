"""Packages are found, never listed: trapflow's own, and workers/ under its install name."""

from setuptools import find_packages, setup

WORKERS = "trapflow_workers"

setup(
    packages=find_packages(include=["trapflow", "trapflow.*"])
    + [WORKERS]
    + [f"{WORKERS}.{name}" for name in find_packages("workers")],
)
