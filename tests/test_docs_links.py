"""Relative links in the README and docs/ point at files and headings that exist.

Anchors follow GitHub's heading slugs: lower case, punctuation other than ``-`` and ``_``
dropped, spaces turned into ``-``. External links (``http...``) are not checked.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*$", re.M)
_LINK = re.compile(r"\]\(([^)#\s]*)(?:#([^)\s]+))?\)")
_FENCE = re.compile(r"^```.*?^```", re.M | re.S)


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _text(path: Path) -> str:
    return _FENCE.sub("", path.read_text(encoding="utf-8"))  # no headings or links in code


@functools.cache  # read each linked document once
def _anchors(path: Path) -> set[str]:
    return {slug(h) for h in _HEADING.findall(_text(path))}


def test_slug_matches_githubs_rules():
    assert slug("Speed and memory") == "speed-and-memory"
    assert slug("Scale-drift indicator (paper Sec. V, Eq. 11-17)") == \
        "scale-drift-indicator-paper-sec-v-eq-11-17"
    assert slug("Crowded cells (`max_tracks_per_cell`, ours, off by default)") == \
        "crowded-cells-max_tracks_per_cell-ours-off-by-default"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(doc: Path):
    broken = []
    for target, anchor in _LINK.findall(_text(doc)):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path = (doc.parent / target).resolve() if target else doc
        if not path.exists():
            broken.append(f"{target}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
            broken.append(f"{target}#{anchor}: no such heading")
    assert not broken, f"{doc.relative_to(ROOT)}: " + "; ".join(broken)
