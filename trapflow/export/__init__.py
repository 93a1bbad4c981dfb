"""Exports of a finished run for the people who use its results: the run report."""
