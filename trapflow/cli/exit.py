"""How every command ends on an error: one line on stderr and the policy's exit status.

The policy (see errors.py and docs/cli.md, "Exit status"): 0 ok, 1 runtime failure,
2 usage or configuration error. click's own usage errors already exit 2.
"""

from __future__ import annotations

from typing import IO, Any

import click

from trapflow.errors import EXIT_FAILURE, EXIT_USAGE, TrapflowError, exit_code


class CommandFailed(click.ClickException):
    """Ends a command with `trapflow: error: MESSAGE` and the given exit status."""

    def __init__(self, message: str, code: int = EXIT_FAILURE) -> None:
        super().__init__(message)
        # click declares exit_code a class variable (8.5); an instance value still wins.
        setattr(self, "exit_code", code)  # noqa: B010

    def show(self, file: IO[Any] | None = None) -> None:
        click.echo(f"trapflow: error: {self.format_message()}", file=file, err=file is None)


def failed(exc: TrapflowError | str) -> CommandFailed:
    """A runtime failure (1), or for an error, the status its class calls for."""
    if isinstance(exc, str):
        return CommandFailed(exc, EXIT_FAILURE)
    return CommandFailed(str(exc), exit_code(exc))


def bad_input(exc: TrapflowError | OSError | str) -> CommandFailed:
    """A usage or configuration error (2): an input the command line names cannot be used."""
    if isinstance(exc, OSError):
        return CommandFailed(f"{exc.filename}: {exc.strerror}", EXIT_USAGE)
    return CommandFailed(str(exc), EXIT_USAGE)
