"""The documents stand on their own and say what is true now: no reference to a folder outside the
repository, no numbered work history (that goes to CHANGELOG.md and git) in docs/ or the code."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
CODE = sorted(p for top in ("training", "sim", "som_torch") for p in (REPO / top).rglob("*.py"))
#: "session 20", "seed 12 #508": references to the work's history, meaningless to a reader.
WORK_HISTORY = re.compile(r"\bsession \d+|\bseeds?[- ]\d+,? ?#\d+", re.IGNORECASE)


def _rel(path: Path) -> str:
    return str(path.relative_to(REPO))


@pytest.mark.parametrize("path", DOCS, ids=_rel)
def test_no_document_refers_outside_the_repository(path):
    assert "../shared" not in path.read_text(encoding="utf-8")


@pytest.mark.parametrize("path", [p for p in DOCS if p.name != "README.md"] + CODE, ids=_rel)
def test_no_numbered_work_history(path):
    text = path.read_text(encoding="utf-8")
    found = [f"line {text.count(chr(10), 0, m.start()) + 1}: {m.group(0)}" for m in WORK_HISTORY.finditer(text)]
    assert not found, found


def test_readme_has_no_numbered_work_history():
    assert not WORK_HISTORY.search((REPO / "README.md").read_text(encoding="utf-8"))


def test_changelog_holds_the_history():
    assert (REPO / "CHANGELOG.md").is_file()
