"""The product speaks in the user's terms, not in the project's own bookkeeping.

A reader of the docs, a ``--help`` text (docstrings become it), a report page, a schema or
a benchmark's output meets figures and goals, never "stop 34", "issue 19's goal" or
"before this stop": those name the team's work log and mean nothing outside it. This test
scans README.md, docs/*.md, pipeline/**/*.py, reports/*, schemas/**/*.json and
benchmarks/*.py and lists every file:line that still does.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: "stop 34", "Stops 26", "issue 19", "issues 18", "Issue #38"
NUMBERED = re.compile(r"\b(stop|issue)s? #?\d+", re.IGNORECASE)
#: phrases that date a text by the team's work log
PHRASES = ("this stop", "last stop", "before this stop")


def scanned_files(root: Path) -> list[Path]:
    """The files a user reads or runs (see the module doc), in a stable order."""
    files = [root / "README.md", *sorted((root / "docs").glob("*.md"))]
    files += sorted((root / "pipeline").rglob("*.py"))
    files += sorted(p for p in (root / "reports").glob("*") if p.is_file())
    files += sorted((root / "schemas").rglob("*.json"))
    files += sorted((root / "benchmarks").glob("*.py"))
    return [p for p in files if p.is_file()]


def hits_in_text(text: str) -> list[tuple[int, str]]:
    """``(line number, line)`` of each line of ``text`` that speaks in bookkeeping."""
    out = []
    for i, line in enumerate(text.splitlines(), 1):
        low = line.lower()
        if NUMBERED.search(line) or any(p in low for p in PHRASES):
            out.append((i, line.strip()))
    return out


def test_no_bookkeeping_in_what_users_read() -> None:
    found = []
    for path in scanned_files(ROOT):
        for i, line in hits_in_text(path.read_text(errors="replace")):
            found.append(f"{path.relative_to(ROOT)}:{i}: {line[:120]}")
    assert not found, f"{len(found)} references to the work log:\n" + "\n".join(found)


def test_the_scan_can_fail() -> None:
    """Negative controls: the forms it must catch, and ordinary uses of the words."""
    caught = [
        "at the end of stop 30",
        "Stop 29 (2026-11-26): the goal",
        "issue 19's ratio goal",
        "## Issue 37: what is left",
        "(issues 18, 38)",
        "see issue #38",
        "figures of stops 26 and 27",
        "measured before this stop",
        "0.0116 mm with last stop's code",
        "as this stop's fix",
    ]
    assert [n for n, _ in hits_in_text("\n".join(caught))] == list(range(1, len(caught) + 1))
    fine = [
        "--until stops after the named one",
        "a hand on the stop button",
        "the loop stops at 36 touch-ups",
        "a protective stop; 3 retries",
        "an issue with 2 cameras",
    ]
    assert hits_in_text("\n".join(fine)) == []
    assert ROOT / "README.md" in scanned_files(ROOT)
