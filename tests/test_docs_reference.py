"""The measurement pages are references, and every link in the docs lands.

docs/results.md holds the current figures within 600 lines; the story of how they came about is
in docs/history/. A reference page (docs/*.md, not docs/history/) says when and on which machine a
figure was taken by its date, commit and machine description only: no "this host", no numbered
work periods, no issue numbers in headings. Every relative link in README.md and docs/ points to
a file that exists and, with a #anchor into a markdown file, to a heading there (GitHub's rule).
Standard library only, so it runs in a blink.
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
RESULTS_MAX_LINES = 600

ORDINALS = (
    "first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|thirteenth|"
    "fourteenth|fifteenth|sixteenth|seventeenth|eighteenth|nineteenth|twentieth|thirtieth|"
    r"twenty-\w+|thirty-\w+|\d+(?:st|nd|rd|th)"
)
# "the seventh session", "the twenty-fifth session", "the fourth GPU session", "the second visit"
WORK_PERIOD = re.compile(rf"\b(?:{ORDINALS})(?:\s+\w+)?\s+(?:session|visit)s?\b", re.IGNORECASE)
HOST = re.compile(r"\bthis (?:host|session)\b", re.IGNORECASE)
ISSUE_IN_HEADING = re.compile(r"\bissues?\s*#?\d+|#\d+\b", re.IGNORECASE)

HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")
LINK = re.compile(r"(?<!!)\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
IMAGE = re.compile(r"!\[[^\]]*\]\(\s*<?([^)\s>]+)>?\s*\)")


def reference_pages() -> list[Path]:
    return sorted(DOCS.glob("*.md"))


def linking_pages() -> list[Path]:
    return [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]


def prose_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) outside fenced code blocks."""
    lines, fenced = [], False
    for number, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, line))
    return lines


def headings(text: str) -> list[str]:
    return [m.group(2) for _, line in prose_lines(text) if (m := HEADING.match(line))]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: the text without markup, lowercased, every character that is
    not a letter, mark, number, connector, hyphen or space removed, and spaces turned into hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link counts by its text
    text = re.sub(r"<[^>]+>", "", text).lower()
    kept = "".join(
        c for c in text if c in "- " or unicodedata.category(c)[0] in "LMN" or unicodedata.category(c) == "Pc"
    )
    return kept.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Every heading's anchor, with GitHub's -1, -2, ... for repeats."""
    seen: dict[str, int] = {}
    result = set()
    for heading in headings(text):
        base = slug(heading)
        count = seen.get(base, 0)
        result.add(base if count == 0 else f"{base}-{count}")
        seen[base] = count + 1
    return result


def links(text: str) -> list[tuple[int, str]]:
    found = []
    for number, line in prose_lines(text):
        line = re.sub(r"`[^`]*`", "", line)
        found += [(number, m.group(1)) for m in LINK.finditer(line)]
        found += [(number, m.group(1)) for m in IMAGE.finditer(line)]
    return found


def broken_links(page: Path, text: str | None = None, read=lambda p: p.read_text()) -> list[str]:
    """Each relative link of `page` that misses its file or its heading, as 'page:line: target'."""
    text = page.read_text() if text is None else text
    problems = []
    for number, target in links(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        where = f"{page.relative_to(REPO)}:{number}: {target}"
        if not file.exists():
            problems.append(where + " (no such file)")
        elif anchor and file.suffix == ".md" and anchor.lower() not in anchors(read(file)):
            problems.append(where + " (no such heading)")
    return problems


def story_telling(text: str) -> list[str]:
    """Lines that tell when or where a figure was taken beyond its date, commit and machine."""
    problems = []
    for number, line in prose_lines(text):
        for pattern, what in ((HOST, "names the host or session"), (WORK_PERIOD, "numbers a work period")):
            if m := pattern.search(line):
                problems.append(f"{number}: {what}: {m.group(0)!r}")
        if (h := HEADING.match(line)) and ISSUE_IN_HEADING.search(h.group(2)):
            problems.append(f"{number}: an issue number in a heading: {h.group(2)!r}")
    return problems


def test_results_md_is_a_reference_of_at_most_600_lines():
    lines = len((DOCS / "results.md").read_text().splitlines())
    assert lines <= RESULTS_MAX_LINES, f"docs/results.md has {lines} lines; the story belongs in docs/history/"


@pytest.mark.parametrize("page", reference_pages(), ids=lambda p: p.name)
def test_a_reference_page_tells_no_story_of_hosts_sessions_or_issues(page):
    assert story_telling(page.read_text()) == []


@pytest.mark.parametrize("page", linking_pages(), ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_lands_on_a_file_and_heading(page):
    assert broken_links(page) == []


def test_history_has_an_index_of_its_files():
    index = (DOCS / "history" / "README.md").read_text()
    listed = {target.partition("#")[0] for _, target in links(index)}
    files = {p.name for p in (DOCS / "history").glob("*.md") if p.name != "README.md"}
    assert files <= listed, f"docs/history/README.md does not list {sorted(files - listed)}"


@pytest.mark.parametrize(
    ("heading", "anchor"),
    [
        ("The paper's Table I, under our protocol", "the-papers-table-i-under-our-protocol"),
        ("The `cunerf_iterations` trade", "the-cunerf_iterations-trade"),
        ("Starting from the volume (`--grid-init volume`)", "starting-from-the-volume---grid-init-volume"),
        (
            "Time, each stage (`cubecloud run --device cuda`, bundled CT)",
            "time-each-stage-cubecloud-run---device-cuda-bundled-ct",
        ),
        (
            "The paper's splat: 30 000 iterations at 512², no Gaussian budget",
            "the-papers-splat-30-000-iterations-at-512²-no-gaussian-budget",
        ),
        ("7. Where the code lives", "7-where-the-code-lives"),
    ],
)
def test_anchors_follow_githubs_rule(heading, anchor):
    assert slug(heading) == anchor


def test_the_checks_catch_the_faults_they_are_for():
    story = "## Binning (issue 21, twenty-third session)\nOn this host, the seventh GPU session measured it.\n"
    assert len(story_telling(story)) == 4  # the heading twice, then the host and the numbered session
    assert story_telling("## Binning stays serial\nOn the 2-core CPU VM, 2026-11-27, c6f70db.\n") == []
    page = DOCS / "results.md"
    assert len(broken_links(page, "[x](#no-such-heading) [y](no-such-file.md) [z](#presets)\n")) == 2
