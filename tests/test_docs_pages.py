"""The docs are what a user or contributor reads: pages of a readable size that speak of the product,
not a work log (no rounds of work, no issue numbers, no link to a log). The product's code and docs
name no test flight as a reason: a flight that taught something is a named regression test whose
docstring tells the story (tests/ may name flights)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]

#: Words of a work log: a round of work ("the ninth session"; a MAVSDK or HTTP session is a product
#: thing and says which), an issue number, a link to the old log.
LOG_WORDS = re.compile(r"(?<!MAVSDK )(?<!HTTP )\bsessions?\b|\bissue \d+|history\.md", re.IGNORECASE)

#: A named flight: a course kind and its seed ("office-6", "pitch-1003"). A course is named by its kind
#: and seed apart (``--course office --seed 6``).
NAMED_RUN = re.compile(r"\b(corridor|doorway|forest|pitch|side|deadend|office|detour)-\d+", re.IGNORECASE)
#: benchmarks.md is left out: its commands name the courses a tool flies (``--courses pitch-2,...``).
PRODUCT_FILES = (
    sorted((ROOT / "companion").rglob("*.py"))
    + sorted((ROOT / "config").glob("*.toml"))
    + [p for p in PAGES if p.name != "benchmarks.md"]
)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_a_page_is_at_most_25_kb(page: Path) -> None:
    assert page.stat().st_size <= 25 * 1024, f"{page.name}: {page.stat().st_size} bytes; split it by topic"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_a_page_speaks_of_the_product(page: Path) -> None:
    hits = [
        f"{page.name}:{n}: {line.strip()}"
        for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
        if LOG_WORDS.search(line)
    ]
    assert not hits, "\n".join(hits)


def test_benchmarks_hold_one_row_per_goal_with_machine_date_and_command() -> None:
    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    rows = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| goal")]
    rows = [r for r in rows if not set(r) <= set("|- ")]
    assert rows
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split(" | ")]
        assert len(cells) == 5, row
        assert re.fullmatch(r"\d{4}-\d{2}-\d{2}", cells[3]), row
        assert "`" in cells[4], row  # the command that reproduces it


def test_the_product_names_no_test_flight() -> None:
    hits = [
        f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
        for path in PRODUCT_FILES
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if NAMED_RUN.search(line)
    ]
    assert not hits, "\n".join(hits)
