"""Outputs written beside their target and renamed into place: nothing is ever half-written or clobbered.

``staged_output(target)`` hands out a temporary path with the target's own name, inside a hidden
``.<name>.*.partial`` folder in the target's directory (one filesystem, so the final rename is
atomic). A file or a whole directory may be written there. When the ``with`` block ends normally
the result is renamed to ``target``; on any exception (KeyboardInterrupt included) the temporary
is removed and ``target`` is left as it was.

An existing target (anything but an empty directory) is refused with ``OutputExistsError``
unless ``force=True``; then the old one is replaced only once the new one is complete: a file
by one atomic rename over it, a directory by moving the old aside, renaming the new in, and
deleting the old (POSIX cannot rename a directory over a non-empty one).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path


class OutputExistsError(RuntimeError):
    """An output that exists already and was not to be replaced (``force=False``; ``--force`` on the CLI).

    Not an OSError on purpose: code that skips unreadable inputs on OSError must not swallow it."""

    def __init__(self, target: Path):
        super().__init__(f"{target} exists; not replacing it (pass --force to replace it, or choose another output)")
        self.target = target


@dataclass
class StagedOutput:
    path: Path  # write the file or directory here (it does not exist yet; its parent does)
    target: Path  # where it lands on success
    discarded: bool = False

    def discard(self) -> None:
        """Leave ``target`` as it was when the block ends, without raising (e.g. nothing worth keeping)."""
        self.discarded = True


def occupied(target: str | Path) -> bool:
    """Whether writing ``target`` would replace something: it exists and is not an empty directory."""
    target = Path(target)
    if not os.path.lexists(target):
        return False
    return target.is_symlink() or not target.is_dir() or any(target.iterdir())


def refuse_existing(target: str | Path, force: bool = False) -> None:
    """``OutputExistsError`` for an occupied ``target`` unless ``force``: checked before any work starts."""
    if not force and occupied(target):
        raise OutputExistsError(Path(target))


@contextmanager
def staged_output(target: str | Path, *, force: bool = False) -> Iterator[StagedOutput]:
    """A temporary path beside ``target`` (see the module docstring); renamed to ``target`` on success."""
    target = Path(target)
    refuse_existing(target, force)
    created = _make_parents(target.parent)
    workdir = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent))
    staged = StagedOutput(workdir / target.name, target)
    landed = False
    try:
        yield staged
        if not staged.discarded and os.path.lexists(staged.path):
            _move_in(staged.path, target, workdir, force)
            landed = True
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
        if not landed:
            for parent in reversed(created):  # folders made only for this output
                try:
                    parent.rmdir()
                except OSError:
                    break


def write_output_text(target: str | Path, text: str, *, force: bool = False) -> Path:
    """``text`` written to ``target`` through ``staged_output``: a reader sees the old file or the new, never half
    of one. ``force=True`` is for a file its command owns and rewrites on each call (a bench's result.json in
    its work folder); a file the user named is refused if it exists unless they passed ``--force``."""
    with staged_output(target, force=force) as staged:
        staged.path.write_text(text)
    return Path(target)


@contextmanager
def staged_dir(target: str | Path | None, *, force: bool = False, prefix: str = "equidiff_") -> Iterator[StagedOutput]:
    """A folder to fill: ``target``'s staged folder (``staged_output``, created empty; it lands as ``target`` when
    the block ends normally), or, without a ``target``, a temporary folder removed when the block ends (``path``
    and ``target`` the same). ``discard()`` on a failure that returns rather than raises leaves nothing."""
    if target is None:
        with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
            yield StagedOutput(Path(tmp), Path(tmp))
        return
    with staged_output(target, force=force) as staged:
        staged.path.mkdir()
        yield staged


def distinct_names(paths: list[Path], separator: str = "__") -> list[str]:
    """One output name per input path: its own name, or, where inputs share a name, the path relative to
    the common folder of those, its parts joined by ``separator`` (``day1/pick_0000``, ``day2/pick_0000``
    -> ``day1__pick_0000``, ``day2__pick_0000``). Give each path once: one path twice has one name."""
    resolved = [Path(os.path.abspath(p)) for p in paths]
    uses = Counter(p.name for p in resolved)
    shared = [p.parent for p in resolved if uses[p.name] > 1]
    root = Path(os.path.commonpath(shared)) if shared else None
    return [separator.join(p.relative_to(root).parts) if uses[p.name] > 1 else p.name for p in resolved]


def unique_paths(paths: list[Path]) -> list[Path]:
    """``paths`` without repeats of one file or folder (named twice, or once directly and once by its folder)."""
    first: dict[str, Path] = {}
    for path in paths:
        first.setdefault(os.path.abspath(path), path)
    return list(first.values())


def _make_parents(folder: Path) -> list[Path]:
    missing = [p for p in (folder, *folder.parents) if not p.exists()][::-1]
    folder.mkdir(parents=True, exist_ok=True)
    return missing


def _move_in(new: Path, target: Path, workdir: Path, force: bool) -> None:
    if not occupied(target):
        if target.is_dir() and not target.is_symlink():
            target.rmdir()  # an empty folder replaces nothing
        os.rename(new, target)
        return
    if not force:  # it appeared while this one was being written
        raise OutputExistsError(target)
    if not new.is_dir() and (target.is_symlink() or not target.is_dir()):
        os.replace(new, target)  # a file over a file: one atomic step
        return
    old = workdir / ".replaced"
    os.rename(target, old)
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(old, target)
        raise
    # ``old`` goes with ``workdir``


__all__ = [
    "OutputExistsError",
    "StagedOutput",
    "distinct_names",
    "occupied",
    "refuse_existing",
    "staged_dir",
    "staged_output",
    "unique_paths",
    "write_output_text",
]
