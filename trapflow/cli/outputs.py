"""One rule for what every command writes: an output that is already there is kept, unless
the command line says --force; an output that is also an input is refused, --force or not;
a folder that is not there is one line, not a traceback. Each refusal is one line naming
the flag, the path and what to do, and ends the command with status 2 before it writes
anything (docs/cli.md, "Outputs").

`refusal` decides from what the file system said of each path (`Seen`), purely;
`check_outputs` looks, asks it, and ends the command.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple, TypeVar

import click

from trapflow.cli.exit import CommandFailed
from trapflow.errors import EXIT_USAGE

FC = TypeVar("FC", bound=Callable[..., object])

FORCE_HELP = "Replace an output that is already there (never one of the inputs)."


def force_option(help_text: str = FORCE_HELP) -> Callable[[FC], FC]:
    """The --force flag of a command that writes outputs, as a click decorator."""
    return click.option("--force", is_flag=True, help=help_text)


class Out(NamedTuple):
    """One output of a command, as its command line names it."""

    path: Path
    flag: str  # "-o", "OUT", "--counts": how the command line names it
    folder: bool = False  # a folder written into: an empty one is in no one's way
    link: bool = False  # a symbolic link the command makes: an old link holds no data
    makes_folder: bool = False  # the command creates the folder it is in
    hint: str = ""  # what the kept file is, when that says what to do with it
    force_does: str = "replace it"  # what --force would do to what is there
    scratch: bool = False  # a working file the command replaces as it likes: only never an input
    appends: bool = False  # written at its end (a log, a state file): what is there stays


class In(NamedTuple):
    """One input of a command; an output must never be it."""

    path: Path
    flag: str


class Seen(NamedTuple):
    """What the file system says of one path (symbolic links followed, but `is_link`)."""

    exists: bool  # there, as anything (a dangling link too)
    is_dir: bool
    is_link: bool
    empty: bool  # a folder with no entry
    folder_ok: bool  # the folder it goes in is there (and is a folder)
    outer_ok: bool  # the folder that one goes in is there
    folder: Path  # the folder it goes in
    where: Path  # the path with every link resolved
    ident: tuple[int, int] | None  # (device, inode) when it exists


def _same(a: Seen, b: Seen) -> bool:
    if a.ident is not None and b.ident is not None:
        return a.ident == b.ident  # hard links and bind mounts too
    return a.where == b.where


def _inside(inner: Seen, outer: Seen) -> bool:
    return outer.where in inner.where.parents


def refusal(command: str, outputs: Sequence[tuple[Out, Seen]],
            inputs: Sequence[tuple[In, Seen]], force: bool) -> str | None:
    """The line that refuses these outputs, or None when the command may write them."""
    for i, (out, seen) in enumerate(outputs):
        for other, other_seen in outputs[:i]:
            if _same(seen, other_seen):
                return (f"{command}: {other.flag} and {out.flag} both name {out.path}; "
                        "name a different output for each")
        for inp, inp_seen in inputs:
            if inp_seen.exists and _same(seen, inp_seen):
                return (f"{command}: {out.flag} {out.path} is also an input ({inp.flag} "
                        f"{inp.path}); name another output (--force does not change this)")
            if out.folder and not out.appends and inp_seen.exists and _inside(inp_seen, seen):
                return (f"{command}: {out.flag} {out.path} holds an input ({inp.flag} "
                        f"{inp.path}); name another folder (--force does not change this)")
        if not out.scratch and (why := _kept(command, out, seen, force)):
            return why
    return None


def _kept(command: str, out: Out, seen: Seen, force: bool) -> str | None:
    """Why one output cannot be written (its folder, its kind, what is there), or None."""
    name = f"{command}: {out.flag} {out.path}"
    if not (seen.outer_ok if out.makes_folder and not seen.exists else seen.folder_ok):
        missing = seen.folder.parent if out.makes_folder else seen.folder
        return (f"{name}: the folder {missing} is not there (or is not a folder); "
                "create it first or name another output")
    if not seen.exists or (out.link and seen.is_link):
        return None
    if out.folder and not seen.is_dir:
        return f"{name} is a file; expected a folder (--force does not change this)"
    if not out.folder and seen.is_dir and not seen.is_link:
        return f"{name} is a folder; expected a file name (--force does not change this)"
    if force or out.appends or (out.folder and seen.empty):
        return None
    what = " and is not empty" if out.folder else ""
    hint = f" ({out.hint})" if out.hint else ""
    return f"{name} exists{what}{hint}; name another output, or pass --force to {out.force_does}"


def look(path: Path) -> Seen:
    """What the file system says of path now."""
    folder = path.parent
    exists = os.path.lexists(path)
    try:
        st = path.stat()
        ident: tuple[int, int] | None = (st.st_dev, st.st_ino)
    except OSError:
        ident = None
    is_dir = path.is_dir()
    try:
        empty = is_dir and not any(path.iterdir())
    except OSError:
        empty = False
    return Seen(exists=exists, is_dir=is_dir, is_link=path.is_symlink(), empty=empty,
                folder_ok=folder.is_dir(), outer_ok=folder.parent.is_dir(), folder=folder,
                where=path.resolve(), ident=ident)


def check_outputs(command: str, outputs: Iterable[Out], inputs: Iterable[In] = (),
                  force: bool = False) -> None:
    """End the command with status 2 and one line when its outputs break the rule."""
    outs = [(o, look(o.path)) for o in outputs]
    ins = [(i, look(i.path)) for i in inputs]
    if why := refusal(command, outs, ins, force):
        raise CommandFailed(why, EXIT_USAGE)


@contextlib.contextmanager
def replacing_folder(out: Path) -> Iterator[Path]:
    """Where to write a folder output: `out` itself when it is not there or empty; else (it
    was allowed with --force) a new folder beside it that takes its place only once the
    block ends without an error, so a failed run keeps the old one whole."""
    if not (out.is_dir() and any(out.iterdir())):
        yield out
        return
    new, old = (out.with_name(f".{out.name}.{what}-{os.getpid()}") for what in ("new", "old"))
    try:
        yield new
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)
        raise
    os.replace(out, old)
    os.replace(new, out)
    shutil.rmtree(old, ignore_errors=True)
