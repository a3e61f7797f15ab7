"""The code blocks of README.md and docs/guide/*.md, as the docs tests read them.

A block is a fenced code block (three backticks and a language). The line right above its fence may hold a
marker, an HTML comment that the rendered page does not show:

- ``<!-- docs-test: skip REASON -->``: the block is not run (it needs a person at the controls, a finished run
  folder, a GPU...); the reason is required, and the test lists the skipped blocks with their reasons;
- ``<!-- docs-test: continue -->``: a python block that carries on from the page's previous python block (its
  names); without it every python block starts from a fresh namespace, as a reader copying it would.

How each language runs is in ``tests/docs/test_doc_blocks.py`` and ``docs/index.md`` ("Examples that run").
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs" / "guide").glob("*.md"))]
FENCE = re.compile(r"^(?P<indent> *)```(?P<lang>[\w+-]*)\s*$")
MARKER = re.compile(r"^\s*<!--\s*docs-test:\s*(?P<kind>skip|continue)\b\s*(?P<reason>.*?)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    marker: str | None = None  # "skip" or "continue"
    reason: str = ""

    @property
    def id(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def read_blocks(page: Path) -> list[Block]:
    """Every fenced block of ``page``, in order, with the marker of the line above its fence."""
    lines, blocks, i = page.read_text().splitlines(), [], 0
    while i < len(lines):
        opening = FENCE.match(lines[i])
        if not opening or not opening["lang"]:
            i += 1
            continue
        indent, start = len(opening["indent"]), i
        i += 1
        body = []
        while i < len(lines) and not FENCE.match(lines[i]):
            body.append(lines[i][indent:])
            i += 1
        marker = MARKER.match(lines[start - 1]) if start > 0 else None
        blocks.append(Block(page, start + 1, opening["lang"], "\n".join(body) + "\n",
                            marker["kind"] if marker else None, marker["reason"] if marker else ""))
        i += 1
    return blocks


def all_blocks() -> list[Block]:
    return [block for page in PAGES for block in read_blocks(page)]
