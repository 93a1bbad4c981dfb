"""The exception hierarchy: every error trapflow raises on purpose derives from TrapflowError.

Also the exit-code policy every command follows (README, "Exit status"): 0 when it did
what was asked, 1 when it ran and failed, 2 when it could not start as asked (a bad
option, config or input named on the command line).
"""

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2


class TrapflowError(Exception):
    """Base of every error trapflow raises on purpose."""


class ConfigError(TrapflowError):
    """A configuration value, file or command-line option is invalid."""


class ProtocolError(TrapflowError):
    """A message on a socket does not match the wire format."""


class WorkerError(TrapflowError):
    """An algorithm plugin cannot be loaded, configured or run."""


class StartupError(TrapflowError):
    """A pipeline piece cannot start (socket in use, run directory locked...)."""


def exit_code(exc: TrapflowError) -> int:
    """The exit status for an error that ends a command: 2 for usage or config, else 1."""
    return EXIT_USAGE if isinstance(exc, (ConfigError, StartupError)) else EXIT_FAILURE
