"""Write ``docs/results.md`` again from the result files of ``bench/results/``.

    python3 -m bench report [--results bench/results] [--out docs/results.md]

Every Markdown file a bench run writes becomes one section of the page: its title, the
command that reproduces it, every table in it (each row with its header's columns, a cell
cut to :data:`MAX_CELL` characters), its ``- quantity: value`` lines as a table of their own
(a dict of numbers with a column per key, a number to a cell) and its charts.  Then the
hand-written notes on that result, ``notes/NAME.md`` beside the results, verbatim: a run
rewrites its result file whole, so notes never live inside one.  Results on the held-out
buildings (``held-out/``) get a part of their own, after the development results.
Sections follow the listing of ``python3 -m bench --help``: benchmarks, then studies.
"""

from __future__ import annotations

import argparse
import ast
import itertools
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from bench.__main__ import SECTIONS, commands

ROOT = Path(__file__).resolve().parents[1]
#: The longest table cell the page shows; a longer one is cut, and says so.
MAX_CELL = 200
#: The folder of held-out results, and the one of the notes, under the results folder.
HELD_OUT = "held-out"
NOTES = "notes"

_COMMAND = re.compile(r"`(python3? -m bench [a-z_]+[^`]*)`")
_SEPARATOR = re.compile(r"^\|(\s*:?-+:?\s*\|)+\s*$")
_BULLET = re.compile(r"^- ([^:]+): (.+)$")
_CUT = " ... (cut; see the result file)"
_IMAGE = re.compile(r"!\[([^]]*)\]\(([^)]+)\)")


@dataclass
class Result:
    """One result file, as the page shows it."""

    path: Path
    title: str
    command: str | None
    blocks: list[list[str]] = field(default_factory=list)
    images: list[tuple[str, Path]] = field(default_factory=list)

    @property
    def module(self) -> str | None:
        """The bench module the command runs, or None when the file states no command."""
        return self.command.split()[3] if self.command else None


def cell(text: str) -> str:
    """One table cell: stripped, at most :data:`MAX_CELL` characters, cut at a separator."""
    text = text.strip()
    if len(text) <= MAX_CELL:
        return text
    head = text[: MAX_CELL - len(_CUT)]
    cut = max(head.rfind(", "), head.rfind("; "))
    return (head[:cut] if cut > 0 else head) + _CUT


def split_row(line: str) -> list[str]:
    """The cells of one Markdown table row (``\\|`` is a pipe inside a cell)."""
    inner = line.strip().removeprefix("|").removesuffix("|")
    return [c.replace("\0", "\\|") for c in inner.replace("\\|", "\0").split("|")]


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table, every row cut or padded to the header's columns."""
    width = len(header)
    lines = ["| " + " | ".join(map(cell, header)) + " |", "|" + "---|" * width]
    for row in rows:
        row = [*row[: width - 1], " ".join(row[width - 1 :])] if len(row) > width else row
        row = row + [""] * (width - len(row))
        lines.append("| " + " | ".join(map(cell, row)) + " |")
    return lines


def quantity(label: str, value: str) -> list[tuple[str, dict[str, str]]]:
    """A ``- label: value`` line as ``(label, columns)``: a dict of numbers, a column per key.

    A dict followed by ``; label: value`` is two quantities; followed by other words, those
    words join the label.  Any other value is one column, ``value``.
    """
    found = re.match(r"(\{[^{}]*\})(.*)$", value)
    try:
        parsed = ast.literal_eval(found[1]) if found else None
    except (ValueError, SyntaxError):
        parsed = None
    if not isinstance(parsed, dict) or not parsed:
        return [(label, {"value": value})]
    rest = found[2].strip()
    more = _BULLET.match(f"- {rest[2:]}") if rest.startswith("; ") else None
    if rest and not more:
        label = f"{label} {rest}"
    head = [(label, {str(k): str(v) for k, v in parsed.items()})]
    return head + (quantity(more[1], more[2]) if more else [])


def quantity_tables(items: list[tuple[str, dict[str, str]]]) -> list[list[str]]:
    """A table for each run of consecutive quantities with the same columns, in their order."""
    blocks = []
    for keys, group in itertools.groupby(items, key=lambda item: list(item[1])):
        rows = [[label, *(v.replace("|", "\\|") for v in cols.values())] for label, cols in group]
        blocks.append(table(["quantity", *keys], rows))
    return blocks


def parse(path: Path) -> Result:
    """The title, command, tables, ``- quantity: value`` lines and charts of a result file.

    Bullets under a ``## Notes`` heading are prose, kept as written.  The charts are the
    images the file shows and the one a run writes beside it (``NAME.png``).
    """
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from e
    title = next((x[2:].strip() for x in lines if x.startswith("# ")), path.stem)
    found = _COMMAND.search("\n".join(lines))
    result = Result(path, title, found[1] if found else None)
    pending: list[tuple[str, dict[str, str]]] = []
    notes = False
    i = 0
    while i < len(lines):
        line = lines[i]
        bullet = _BULLET.match(line)
        if pending and not (bullet and not notes):
            result.blocks += quantity_tables(pending)
            pending = []
        if line.startswith("|") and i + 1 < len(lines) and _SEPARATOR.match(lines[i + 1]):
            end = i + 2
            while end < len(lines) and lines[end].startswith("|"):
                end += 1
            rows = [split_row(x) for x in lines[i + 2 : end]]
            result.blocks.append(table(split_row(line), rows))
            i = end
            continue
        if line.startswith("## "):
            notes = line[3:].strip() == "Notes"
            result.blocks.append([f"#### {line[3:].strip()}"])
        elif bullet and notes:
            if i and _BULLET.match(lines[i - 1]):
                result.blocks[-1].append(line)
            else:
                result.blocks.append([line])
        elif bullet:
            pending += quantity(bullet[1], bullet[2])
        for alt, target in _IMAGE.findall(line):
            result.images.append((alt, path.parent / target))
        i += 1
    if pending:
        result.blocks += quantity_tables(pending)
    chart = path.with_suffix(".png")
    if chart.is_file() and chart not in [image for _, image in result.images]:
        result.images.append((path.stem, chart))
    return result


def order(results: list[Result]) -> list[Result]:
    """Results in the order of the listing (benchmarks, studies, data), then of their runs.

    A module's results come plain first (``merge.md``), then its variants
    (``merge-turned.md``), then the results of other folders (``exhaustive/merge.md``).
    """
    rank = {name: n for n, (_, package) in enumerate(SECTIONS) for name in commands(package)}
    names = list(rank)
    return sorted(
        results,
        key=lambda r: (
            rank.get(r.module, len(SECTIONS)),
            names.index(r.module) if r.module in rank else 0,
            len(r.path.parts),
            r.path.stem.count("-"),
            r.path.stem,
        ),
    )


def section(result: Result, results: Path, notes: Path, page: Path) -> list[str]:
    """One result's part of the page."""
    name = result.path.relative_to(results).with_suffix("")
    link = os.path.relpath(result.path, page.parent)
    command = f"`{result.command}`" if result.command else "not stated in the result file"
    lines = [f"### {result.title} ({name})", "", f"[{name}.md]({link}); reproduce: {command}", ""]
    for block in result.blocks:
        lines += [*block, ""]
    for alt, image in result.images:
        lines += [f"![{alt}]({os.path.relpath(image, page.parent)})", ""]
    note = notes / f"{name}.md"
    if note.is_file():
        lines += [f"Notes ([{NOTES}/{name}.md]({os.path.relpath(note, page.parent)})):", ""]
        lines += [note.read_text().rstrip("\n"), ""]
    return lines


def page(results: Path, out: Path) -> str:
    """The whole results page, from the result files under ``results``."""
    notes = results / NOTES
    files = sorted(p for p in results.rglob("*.md") if notes not in p.parents)
    orphans = sorted(
        n for n in notes.rglob("*.md") if not (results / n.relative_to(notes)).is_file()
    )
    if orphans:
        raise ValueError(f"{orphans[0]}: a note on no result file")
    held = [parse(p) for p in files if p.relative_to(results).parts[0] == HELD_OUT]
    development = [parse(p) for p in files if p.relative_to(results).parts[0] != HELD_OUT]
    source = os.path.relpath(results, out.parent)
    lines = [
        "# Bench results",
        "",
        f"Written by `python3 -m bench report` from the result files in [{source}]({source}).",
        "Do not edit this page: run a result's command again, or write notes on it in "
        f"`{NOTES}/NAME.md` beside the results.",
        "",
        "## Development buildings",
        "",
    ]
    for result in order(development):
        lines += section(result, results, notes, out)
    if held:
        lines += [
            "## Held-out buildings",
            "",
            "Buildings the merge was never tuned on: these results are read, never tuned on.",
            "",
        ]
        for result in order(held):
            lines += section(result, results, notes, out)
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--results", type=Path, default=ROOT / "bench" / "results", help="the result files"
    )
    parser.add_argument(
        "--out", type=Path, default=ROOT / "docs" / "results.md", help="the page to write"
    )
    args = parser.parse_args(argv)
    if not args.results.is_dir():
        print(f"bench report: {args.results}: no such folder of results", file=sys.stderr)
        return 2
    try:
        text = page(args.results.resolve(), args.out.resolve())
    except (OSError, ValueError) as e:
        print(f"bench report: {e}", file=sys.stderr)
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
