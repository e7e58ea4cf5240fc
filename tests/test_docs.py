"""The documentation checks itself: links resolve, tables are whole, the CLI reference is complete.

README.md and docs/*.md are read as GitHub renders them: a relative link or image must name a
file of the repository, every row of a table must have its header's column count (an escaped
``\\|`` is text, not a column), and docs/cli.md must name every option of every ``pgvd``
sub-command in that command's section (options hidden from ``--help`` excepted), so an option
added to a parser without its documentation fails here.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from agent.cli.dispatch import build_parser

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])
README_MAX_LINES = 170
#: A front-page table cell longer than this is a paragraph; it belongs in docs/.
README_MAX_CELL = 200

#: ``[text](target)`` and ``![alt](target)``, target up to a space (a title may follow).
_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_FENCE = re.compile(r"^\s*(```|~~~)")
_EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:", re.IGNORECASE)


def _prose(page: Path) -> list[tuple[int, str]]:
    """(line number, line) of ``page`` outside fenced code blocks."""
    lines, fenced = [], False
    for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), start=1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, line))
    return lines


def _without_code_spans(line: str) -> str:
    """``line`` with its inline code spans blanked: a link in code is text."""
    return re.sub(r"`[^`]*`", lambda m: "`" + "x" * (len(m.group(0)) - 2) + "`", line)


def _cells(row: str) -> int:
    """Columns of a Markdown table row: its unescaped pipes, outer ones not separating."""
    body = re.sub(r"\\\|", "", row.strip())
    return body.strip("|").count("|") + 1


def test_pages_exist():
    assert ROOT / "README.md" in PAGES
    assert len(PAGES) > 1, "docs/*.md holds no page"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(page: Path):
    broken = []
    for number, line in _prose(page):
        for target in _LINK.findall(_without_code_spans(line)):
            if _EXTERNAL.match(target) or target.startswith("#"):
                continue
            path = target.split("#", 1)[0]
            if not (page.parent / path).exists():
                broken.append(f"{page.name}:{number}: {target}")
    assert not broken, "links to no file: " + "; ".join(broken)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_table_rows_have_the_header_columns(page: Path):
    bad, header = [], None
    for number, line in _prose(page):
        if not line.lstrip().startswith("|"):
            header = None
            continue
        # a pipe inside a code span splits the cell too, as GitHub renders tables
        if header is None:
            header = _cells(line)
        elif _cells(line) != header:
            bad.append(f"{page.name}:{number}: {_cells(line)} columns, header {header}")
    assert not bad, "; ".join(bad)


def test_readme_fits_on_a_front_page():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines"


def test_readme_table_cells_are_short():
    long = [
        f"README.md:{number}: {len(cell.strip())} characters"
        for number, line in _prose(ROOT / "README.md")
        if line.lstrip().startswith("|")
        for cell in re.split(r"(?<!\\)\|", line.strip().strip("|"))
        if len(cell.strip()) > README_MAX_CELL
    ]
    assert not long, "; ".join(long)


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    """``{"pgvd": the top parser, name: parser}`` for every ``pgvd`` sub-command."""
    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {"pgvd": parser, **{f"pgvd {n}": p for n, p in subs.choices.items()}}


def _sections() -> dict[str, str]:
    """docs/cli.md's text under each ``## `pgvd ...` `` heading, by command."""
    text = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    parts = re.split(r"^## `(pgvd[a-z ]*)`\s*$", text, flags=re.MULTILINE)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def test_every_command_has_a_section():
    missing = sorted(set(_subcommands()) - set(_sections()))
    assert not missing, "no section in docs/cli.md: " + ", ".join(missing)


def test_every_option_is_in_its_command_section():
    sections = _sections()
    missing = [
        f"{command} {option}"
        for command, parser in _subcommands().items()
        for action in parser._actions
        if action.help != argparse.SUPPRESS  # hidden on purpose, as in --help
        for option in action.option_strings
        if option not in ("-h", "--help")
        and not re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", sections.get(command, ""))
    ]
    assert not missing, "not in its section of docs/cli.md: " + ", ".join(missing)
