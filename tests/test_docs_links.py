"""The README and docs/ as a new user reads them: every relative link lands, the README's
first screen says what to run.

A link ``[text](path#anchor)`` in README.md or docs/*.md must name a file or folder of
the repository, and its anchor a heading of that file (GitHub's rule: lower case, spaces
to hyphens, punctuation but hyphens and underscores dropped).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")


def anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading's text."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    out = set()
    in_fence = False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            in_fence = not in_fence
        elif not in_fence and (m := re.match(r"#{1,6} (.*)", line)):
            out.add(anchor(m.group(1)))
    return out


def links(path: Path) -> list[tuple[int, str]]:
    found = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        for m in LINK.finditer(line):
            target = m.group(1) or m.group(2)
            if not re.match(r"[a-z]+:", target):
                found.append((n, target))
    return found


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_relative_link_lands(doc: Path) -> None:
    broken = []
    for n, target in links(doc):
        file, _, frag = target.partition("#")
        dest = (doc.parent / file).resolve() if file else doc
        if not dest.exists():
            broken.append(f"{doc.name}:{n}: {target} (no such file)")
        elif frag and dest.suffix == ".md" and frag not in anchors(dest):
            broken.append(f"{doc.name}:{n}: {target} (no heading #{frag})")
    assert not broken, "\n".join(broken)


def test_anchor_follows_githubs_rule() -> None:
    assert anchor("Refusals and field variants") == "refusals-and-field-variants"
    assert anchor("The verdict against the truth (`--seed 11`)") == (
        "the-verdict-against-the-truth---seed-11"
    )
    assert anchor("What `vtcal run` writes") == "what-vtcal-run-writes"
    assert anchor("A renderer (`bench_render.py`)") == "a-renderer-bench_renderpy"


def test_the_readme_starts_with_what_to_run() -> None:
    """At most 150 lines; set-up line and the main command within the first 40; no table
    row a screen cannot hold."""
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 150, len(lines)
    first = "\n".join(lines[:40])
    assert '    pip install -e ".[dev]"' in first
    assert "    vtcal run datasets/samples/sample_lrmate.mcap --out runs/sample" in first
    wide = [n for n, ln in enumerate(lines, 1) if ln.startswith("|") and len(ln) > 300]
    assert not wide, f"table rows over 300 characters at lines {wide}"
