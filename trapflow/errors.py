"""The exception hierarchy: every error trapflow raises on purpose derives from TrapflowError.

Also the exit-code policy every command follows (docs/cli.md, "Exit status"): 0 when it did
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


class NodeDiedError(TrapflowError):
    """A pipeline process died on its own account while the pipeline started (killed by a
    signal, or gone without a word): a runtime failure (1), not a usage error."""


def exit_code(exc: TrapflowError) -> int:
    """The exit status for an error that ends a command: 2 for usage or config, else 1."""
    return EXIT_USAGE if isinstance(exc, (ConfigError, StartupError)) else EXIT_FAILURE


def unreachable(value: NoReturn) -> NoReturn:
    """The `else` of a dispatch over a closed union (typing.assert_never, which Python 3.10
    lacks): mypy rejects a call it can still reach, so a member added to the union without
    a branch fails the type check; at run time it names the type that had no branch."""
    raise TypeError(f"no branch for {type(value).__name__}: {value!r}")


def yaml_problem(exc: Exception) -> str:
    """A YAML parser error in one line: what it expected and where (line and column,
    counted from 1), without the echoed source lines PyYAML adds (8 lines for one error)."""
    problem = getattr(exc, "problem", None)
    mark = getattr(exc, "problem_mark", None)
    if problem is None:
        return " ".join(str(exc).split())
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    context = getattr(exc, "context", None)
    if not context:
        return f"{where}{problem}"
    start = getattr(exc, "context_mark", None)
    since = f" at line {start.line + 1}, column {start.column + 1}" if start is not None else ""
    return f"{where}{problem} ({context}{since})"
