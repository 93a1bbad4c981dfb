"""The exception hierarchy: every error trapflow raises on purpose derives from TrapflowError.

Also the exit-code policy every command follows (README, "Exit status"): 0 when it did
what was asked, 1 when it ran and failed, 2 when it could not start as asked (a bad
option, config or input named on the command line).

And `unreachable`, the last branch of every exhaustive dispatch over a union.
"""

from typing import NoReturn

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


def unreachable(value: NoReturn) -> NoReturn:
    """The `else` of a dispatch over a closed union (typing.assert_never, which Python 3.10
    lacks): mypy rejects a call it can still reach, so a member added to the union without
    a branch fails the type check; at run time it names the type that had no branch."""
    raise TypeError(f"no branch for {type(value).__name__}: {value!r}")
