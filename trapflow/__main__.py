"""`python -m trapflow` runs the command line."""

from trapflow.cli.main import main

main()
