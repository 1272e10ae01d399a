"""The code points to the docs for figures and reasons (``docs/model.md``, ``docs/results/model.md, "The over-fit
check"``): every such pointer in src/, launch/ and scripts/ names a page that exists and, where it names a
section, a section of that page, so that a page split or a renamed heading cannot leave the code pointing
nowhere."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
POINTING = ("src", "launch", "scripts")
PAGE = r"docs/((?:[\w-]+/)*[\w-]+\.md)"
# `docs/x.md, "Section"`, `docs/x.md "Section"`, `(docs/x.md, ("A", "B"))`; a quote right after `.md` (the end
# of a string that names the page) is no section
SECTIONED = re.compile(PAGE + r'(?:,\s*|\s+)\(?((?:"[^"]{1,100}"(?:,\s*)?)+)')
BOLD_BEFORE = re.compile(r"\*\*([^*]{1,100})\*\* \(" + PAGE + r"\)")
ANY_PAGE = re.compile(PAGE)


def _flat(text: str) -> str:
    """``text`` on one line: a comment or docstring that wraps a section's name reads it whole."""
    return re.sub(r"\s*\n\s*(?:#+\s*)?", " ", text)


def _plain(text: str) -> str:
    return " ".join(text.replace("`", "").replace("**", "").split())


def _sections(page: Path) -> list[str]:
    """The page's headings and the bold or plain openings of its paragraphs and list items, without markup."""
    return [_plain(line.lstrip("#-* ")) for line in page.read_text().splitlines() if line.strip()]


def pointers(text: str) -> list[tuple[str, str | None]]:
    """(page, section or None) for every pointer in ``text``."""
    flat = _flat(text)
    found: list[tuple[str, str | None]] = [(page, None) for page in ANY_PAGE.findall(flat)]
    for match in SECTIONED.finditer(flat):
        found += [(match.group(1), name) for name in re.findall(r'"([^"]+)"', match.group(2))]
    found += [(page, name) for name, page in BOLD_BEFORE.findall(flat)]
    return found


def broken(pointer: tuple[str, str | None], docs: Path) -> str | None:
    """Why ``pointer`` points nowhere in ``docs``, or None."""
    page, section = pointer
    path = docs / page
    if not path.is_file():
        return f"no page docs/{page}"
    if section is not None and not any(line.startswith(_plain(section)) for line in _sections(path)):
        return f'docs/{page} has no section "{section}"'
    return None


def _sources() -> list[Path]:
    return sorted(p for d in POINTING for p in (ROOT / d).rglob("*") if p.suffix in (".py", ".sh") and p.is_file())


def test_every_pointer_from_the_code_to_the_docs_names_a_page_and_section_that_exist():
    problems = [
        f"{path.relative_to(ROOT)}: {why}"
        for path in _sources()
        for pointer in sorted(set(pointers(path.read_text())), key=str)
        if (why := broken(pointer, ROOT / "docs"))
    ]
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ('# see docs/model.md, "The under-fit\n# check" for it', 'docs/model.md has no section "The under-fit check"'),
        ('"""(docs/model.md "GPU check")"""', 'docs/model.md has no section "GPU check"'),
        ("# measured in docs/nowhere.md", "no page docs/nowhere.md"),
        ("**Standstill at chunk boundaries** (docs/control.md): what", 'docs/control.md has no section "Standstill'),
        ('# docs/model.md, "The over-fit\n# check"; docs/results/model.md ("Training", "Training: CPU")', None),
        ('help="the figures: docs/model.md", default=None', None),  # a string ending at the page names no section
    ],
)
def test_a_broken_pointer_is_caught_and_a_good_one_is_not(text, why, tmp_path):
    docs = tmp_path / "docs"
    (docs / "results").mkdir(parents=True)
    (docs / "model.md").write_text("# The model\n\n## Training\n\n**The over-fit check, measured:** it fits\n")
    (docs / "control.md").write_text("# Control\n\n## Safety\n")
    (docs / "results" / "model.md").write_text("## Training: CPU threads\n")
    reasons = [r for p in pointers(text) if (r := broken(p, docs))]
    if why is None:
        assert reasons == []
    else:
        assert any(r.startswith(why) for r in reasons), reasons
