"""The one rule for what commands write (trapflow.cli.outputs): its pure verdict on what
the file system showed, and the shell's look at real paths."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from trapflow.cli.outputs import In, Out, Seen, look, refusal, replacing_folder


def _seen(path: str, *, exists: bool = False, is_dir: bool = False, empty: bool = False,
          is_link: bool = False, folder_ok: bool = True, ident: int | None = None) -> Seen:
    p = Path("/data") / path
    return Seen(exists=exists, is_dir=is_dir, is_link=is_link, empty=empty,
                folder_ok=folder_ok, outer_ok=True, folder=p.parent, where=p,
                ident=(1, ident) if ident is not None else None)


FILE = _seen("a.txt", exists=True, ident=7)
NEW = _seen("b.txt")


@pytest.mark.parametrize(("out", "seen", "force", "expected"), [
    (Out(Path("b.txt"), "-o"), NEW, False, None),
    (Out(Path("a.txt"), "-o"), FILE, False,
     "track: -o a.txt exists; name another output, or pass --force to replace it"),
    (Out(Path("a.txt"), "-o"), FILE, True, None),
    (Out(Path("a.txt"), "-o", appends=True), FILE, False, None),
    (Out(Path("a.txt"), "-o", scratch=True), FILE, False, None),
    (Out(Path("a.txt"), "-o", hint="cut short"), FILE, False,
     "track: -o a.txt exists (cut short); name another output, or pass --force to replace "
     "it"),
    (Out(Path("d"), "OUT", folder=True), _seen("d", exists=True, is_dir=True, empty=True),
     False, None),
    (Out(Path("d"), "OUT", folder=True), _seen("d", exists=True, is_dir=True), False,
     "track: OUT d exists and is not empty; name another output, or pass --force to "
     "replace it"),
    (Out(Path("d"), "OUT", folder=True), FILE, True,
     "track: OUT d is a file; expected a folder (--force does not change this)"),
    (Out(Path("d"), "-o"), _seen("d", exists=True, is_dir=True), True,
     "track: -o d is a folder; expected a file name (--force does not change this)"),
    (Out(Path("x/b.txt"), "-o"), _seen("x/b.txt", folder_ok=False), True,
     "track: -o x/b.txt: the folder /data/x is not there (or is not a folder); create it "
     "first or name another output"),
    (Out(Path("x/b.txt"), "-o", makes_folder=True), _seen("x/b.txt", folder_ok=False), False,
     None),
    (Out(Path("l"), "--link-a", link=True), _seen("l", exists=True, is_link=True), False,
     None),
    (Out(Path("l"), "--link-a", link=True), FILE, False,
     "track: --link-a l exists; name another output, or pass --force to replace it"),
])
def test_one_output(out: Out, seen: Seen, force: bool, expected: str | None) -> None:
    assert refusal("track", [(out, seen)], [], force) == expected


def test_an_input_is_never_an_output_even_with_force() -> None:
    same = _seen("other/name.txt", exists=True, ident=7)  # a hard link to a.txt
    for seen in (FILE, same):
        why = refusal("track", [(Out(Path("x"), "-o"), seen)], [(In(Path("a.txt"), "DET"),
                                                                 FILE)], True)
        assert why == ("track: -o x is also an input (DET a.txt); name another output "
                       "(--force does not change this)")


def test_a_folder_output_never_holds_an_input() -> None:
    inside = _seen("d/run/results.jsonl", exists=True, ident=3)
    why = refusal("export", [(Out(Path("d"), "OUT", folder=True),
                              _seen("d", exists=True, is_dir=True, ident=2))],
                  [(In(Path("d/run"), "RUN_DIR"), inside)], True)
    assert why is not None and "holds an input" in why


def test_two_outputs_never_name_one_file() -> None:
    why = refusal("track", [(Out(Path("b.txt"), "-o"), NEW),
                            (Out(Path("./b.txt"), "--counts"), NEW)], [], False)
    assert why == "track: -o and --counts both name b.txt; name a different output for each"


def test_look_follows_links_and_hard_links(tmp_path: Path) -> None:
    f = tmp_path / "f.txt"
    f.write_text("x")
    (tmp_path / "hard.txt").hardlink_to(f)
    (tmp_path / "soft.txt").symlink_to(f)
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    idents = {look(tmp_path / n).ident for n in ("f.txt", "hard.txt", "soft.txt")}
    assert len(idents) == 1 and None not in idents
    dangling = look(tmp_path / "dangling")
    assert dangling.exists and dangling.is_link and dangling.ident is None
    assert not look(tmp_path / "no" / "x").folder_ok


def test_a_replaced_folder_stays_whole_until_the_new_one_is(tmp_path: Path) -> None:
    out = tmp_path / "pkg"
    out.mkdir()
    (out / "old.csv").write_text("old")
    with pytest.raises(RuntimeError), replacing_folder(out) as into:
        into.mkdir()
        (into / "half.csv").write_text("half")
        raise RuntimeError("the export failed")
    assert sorted(os.listdir(out)) == ["old.csv"] and sorted(os.listdir(tmp_path)) == ["pkg"]
    with replacing_folder(out) as into:
        into.mkdir()
        (into / "new.csv").write_text("new")
    assert sorted(os.listdir(out)) == ["new.csv"] and sorted(os.listdir(tmp_path)) == ["pkg"]
