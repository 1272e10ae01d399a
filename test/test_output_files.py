"""output_files.staged_output: outputs renamed into place on success, never half-written, never clobbered."""

from __future__ import annotations

import re

import pytest

from equidiff_core.runtime.output_files import (
    OutputExistsError,
    distinct_names,
    staged_dir,
    staged_output,
    unique_paths,
    write_output_text,
)


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def test_file_lands_on_success_and_only_then(tmp_path):
    target = tmp_path / "out.txt"
    with staged_output(target) as staged:
        staged.path.write_text("new")
        assert not target.exists()  # nothing at the target while it is written
        assert staged.path.parent.parent == tmp_path  # beside the target: one filesystem
    assert target.read_text() == "new"
    assert _listing(tmp_path) == ["out.txt"]


def test_directory_lands_whole(tmp_path):
    target = tmp_path / "a" / "b" / "dataset"
    with staged_output(target) as staged:
        (staged.path / "meta").mkdir(parents=True)
        (staged.path / "meta" / "info.json").write_text("{}")
    assert (target / "meta" / "info.json").read_text() == "{}"
    assert _listing(tmp_path) == ["a", "a/b", "a/b/dataset", "a/b/dataset/meta", "a/b/dataset/meta/info.json"]


@pytest.mark.parametrize("failure", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_failure_leaves_nothing_and_deletes_nothing(tmp_path, failure):
    kept = tmp_path / "kept.txt"
    kept.write_text("old")
    with pytest.raises(type(failure)), staged_output(tmp_path / "new" / "dir") as staged:
        staged.path.mkdir()
        (staged.path / "half").write_text("x")
        raise failure
    assert _listing(tmp_path) == ["kept.txt"]  # no temporary, not even the parent folder made for it

    with pytest.raises(type(failure)), staged_output(kept, force=True) as staged:
        staged.path.write_text("half")
        raise failure
    assert kept.read_text() == "old"
    assert _listing(tmp_path) == ["kept.txt"]


def test_existing_target_is_refused_before_any_work(tmp_path):
    for target in (tmp_path / "file.rrd", tmp_path / "folder"):
        if target.suffix:
            target.write_bytes(b"old bytes")
        else:
            target.mkdir()
            (target / "inside").write_bytes(b"old bytes")
        refused = pytest.raises(OutputExistsError, match=re.escape(f"{target} exists; not replacing it (pass --force"))
        with refused, staged_output(target):
            pytest.fail("the block must not run")
    assert (tmp_path / "file.rrd").read_bytes() == b"old bytes"
    assert (tmp_path / "folder" / "inside").read_bytes() == b"old bytes"
    assert _listing(tmp_path) == ["file.rrd", "folder", "folder/inside"]


def test_an_empty_folder_is_no_output_to_keep(tmp_path):
    target = tmp_path / "packed"
    target.mkdir()
    with staged_output(target) as staged:
        staged.path.mkdir()
        (staged.path / "x").write_text("x")
    assert (target / "x").read_text() == "x"


@pytest.mark.parametrize("kind", ["file", "dir"])
def test_force_replaces_only_once_complete(tmp_path, kind):
    target = tmp_path / "out"
    if kind == "file":
        target.write_text("old")
    else:
        target.mkdir()
        (target / "old_only").write_text("old")
    with staged_output(target, force=True) as staged:
        if kind == "file":
            staged.path.write_text("new")
            assert target.read_text() == "old"
        else:
            staged.path.mkdir()
            (staged.path / "new_only").write_text("new")
            assert (target / "old_only").read_text() == "old"
    if kind == "file":
        assert target.read_text() == "new"
    else:
        assert _listing(target) == ["new_only"]  # replaced, not merged
    assert _listing(tmp_path) == (["out"] if kind == "file" else ["out", "out/new_only"])  # no temporary left


def test_a_target_that_appears_meanwhile_is_not_clobbered(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(OutputExistsError), staged_output(target) as staged:
        staged.path.write_text("mine")
        target.write_text("someone else's")
    assert target.read_text() == "someone else's"
    assert _listing(tmp_path) == ["out.txt"]


def test_discard_keeps_the_target_as_it_was(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with staged_output(target, force=True) as staged:
        staged.path.write_text("nothing worth keeping")
        staged.discard()
    assert target.read_text() == "old"
    assert _listing(tmp_path) == ["out.txt"]


def test_write_output_text_refuses_a_named_file_and_rewrites_an_owned_one(tmp_path):
    target = tmp_path / "plots" / "result.json"
    assert write_output_text(target, "first") == target
    with pytest.raises(OutputExistsError):
        write_output_text(target, "second")  # a file the user named: refused without --force
    assert target.read_text() == "first"
    write_output_text(target, "second", force=True)  # a file the command owns: rewritten whole
    assert target.read_text() == "second"
    assert _listing(tmp_path) == ["plots", "plots/result.json"]


def test_staged_dir_lands_a_folder_or_fills_a_temporary_one(tmp_path):
    with staged_dir(tmp_path / "run") as staged:
        assert staged.path.is_dir() and not any(staged.path.iterdir())
        (staged.path / "log").write_text("x")
    assert _listing(tmp_path) == ["run", "run/log"]
    with pytest.raises(OutputExistsError), staged_dir(tmp_path / "run"):
        pytest.fail("the block must not run")
    with staged_dir(tmp_path / "run", force=True) as staged:  # a failure that returns: nothing lands
        (staged.path / "half").write_text("x")
        staged.discard()
    assert _listing(tmp_path) == ["run", "run/log"]
    with staged_dir(None, prefix="kept_nowhere_") as staged:  # no target: a temporary folder, then nothing
        assert staged.path == staged.target and staged.path.name.startswith("kept_nowhere_")
        (staged.path / "log").write_text("x")
    assert not staged.path.exists()


def test_distinct_names_from_the_common_folder(tmp_path):
    day1, day2 = tmp_path / "day1" / "pick_0000", tmp_path / "day2" / "pick_0000"
    assert distinct_names([day1, day2]) == ["day1__pick_0000", "day2__pick_0000"]
    assert distinct_names([day1, tmp_path / "day1" / "pick_0001"]) == ["pick_0000", "pick_0001"]
    assert distinct_names([day1]) == ["pick_0000"]
    day2_other = tmp_path / "day2" / "pick_0001"
    assert distinct_names([day1, day2, day2_other]) == ["day1__pick_0000", "day2__pick_0000", "pick_0001"]
    assert unique_paths([day1, tmp_path / "day1" / ".." / "day1" / "pick_0000", day2]) == [day1, day2]
