"""`python -m trapflow` runs the command line."""

from trapflow.cli import main

main()
