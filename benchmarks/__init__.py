"""trapflow's benchmarks: one module per part of scripts/bench.sh, each run as
`python -m benchmarks.NAME` from the repository root, all on one harness (harness.py): the
common options, repeats with median and spread, CPU of a process tree, one result type and
its JSON and markdown. Speed is measured here, never asserted in tests."""
