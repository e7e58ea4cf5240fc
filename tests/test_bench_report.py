"""bench.report: docs/results.md from the result files, their commands, tables and notes."""

import re
import shutil
from pathlib import Path

import pytest

from bench.report import MAX_CELL, main, page, parse

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


def tables(text: str) -> list[list[list[str]]]:
    """Every Markdown table of ``text`` as rows of cells, the header first."""
    lines, found, i = text.splitlines(), [], 0
    while i < len(lines):
        if lines[i].startswith("|") and i + 1 < len(lines) and lines[i + 1].startswith("|---"):
            end = i + 2
            while end < len(lines) and lines[end].startswith("|"):
                end += 1
            rows = [lines[i], *lines[i + 2 : end]]
            found.append([r.replace("\\|", "").strip().strip("|").split("|") for r in rows])
            i = end
        else:
            i += 1
    return found


def test_the_page_shows_every_result_with_its_command_and_rows(tmp_path):
    out = tmp_path / "docs" / "results.md"
    assert main(["--out", str(out)]) == 0
    text = out.read_text()
    files = [p for p in RESULTS.rglob("*.md") if "notes" not in p.relative_to(RESULTS).parts]
    for path in files:
        name = path.relative_to(RESULTS).with_suffix("").as_posix()
        assert f"[{name}.md](" in text, name
    assert "not stated in the result file" not in text
    assert len(re.findall(r"; reproduce: `python3? -m bench [a-z_]+", text)) == len(files)
    # every row of every result table is on the page, in as many columns as its header
    shown = {tuple(c.strip() for c in row) for t in tables(text) for row in t}
    for path in files:
        for t in tables(path.read_text()):
            width = len(t[0])
            for row in t[1:]:
                assert len(row) == width, f"{path}: {row[:2]}"
                cells = [c.strip() for c in row]
                if all(len(c) <= MAX_CELL for c in cells):
                    assert tuple(cells) in shown, f"{path}: {row[:2]}"
    for t in tables(text):
        assert all(len(row) == len(t[0]) for row in t)
        assert all(len(c.strip()) <= MAX_CELL for row in t for c in row)
    held = text.index("## Held-out buildings")
    assert text.index("(held-out/merge)") > held > text.index("### Merge benchmark (merge)")


def test_notes_are_shown_verbatim_beside_the_result_a_run_rewrites(tmp_path):
    results = tmp_path / "results"
    shutil.copytree(RESULTS, results, ignore=shutil.ignore_patterns("*.png", "*.json"))
    note = (results / "notes" / "fleet.md").read_text()
    # a fresh run writes fleet.md whole; the notes stay where the run does not write
    fleet = results / "fleet.md"
    fleet.write_text(fleet.read_text().replace("| 16 | yes |", "| 16 | no |"))
    text = page(results, tmp_path / "docs" / "results.md")
    section = text[text.index("### Fleet benchmark (fleet)") :]
    section = section[: section.index("\n### ")]
    assert "| 16 | no |" in section
    assert note.rstrip("\n") in section
    assert "## Notes on this run" not in fleet.read_text()


def test_a_dict_of_numbers_is_a_column_per_key(tmp_path):
    path = tmp_path / "soak.md"
    path.write_text(
        "# Soak\n\n`python3 -m bench soak --minutes 1`\n\n"
        "- lag (s): {'median': 1.5, 'p90': 4.0}; polls in agreement: 12\n"
        "- propagation lag (s): {'median': 0.8, 'p90': 1.3}\n"
        "- RSS growth (%): {'r1': 2.0, 'r2': -1.0} (max 2.0 %, target < 10)\n"
        "- agents that died: none\n\n"
        "## Notes\n\n- Measured on: one machine\n"
    )
    result = parse(path)
    assert result.command == "python3 -m bench soak --minutes 1"
    assert result.blocks[0] == [
        "| quantity | median | p90 |",
        "|---|---|---|",
        "| lag (s) | 1.5 | 4.0 |",
    ]
    assert result.blocks[1][2:] == ["| polls in agreement | 12 |"]
    assert result.blocks[2][2:] == ["| propagation lag (s) | 0.8 | 1.3 |"]
    assert result.blocks[3][0] == "| quantity | r1 | r2 |"
    assert result.blocks[3][2] == "| RSS growth (%) (max 2.0 %, target < 10) | 2.0 | -1.0 |"
    assert result.blocks[4][2:] == ["| agents that died | none |"]
    assert result.blocks[-2:] == [["#### Notes"], ["- Measured on: one machine"]]


def test_a_long_cell_is_cut_and_a_short_row_padded(tmp_path):
    path = tmp_path / "recall.md"
    misses = ", ".join(f"pair-{i:02d}: {i}.5" for i in range(40))
    path.write_text(f"# Recall\n\n| group | misses | more |\n|---|---|---|\n| all | {misses} |\n")
    (row,) = tables("\n".join(parse(path).blocks[0]))[0][1:]
    assert len(row) == 3
    assert len(row[1].strip()) <= MAX_CELL and row[1].strip().endswith("(cut; see the result file)")
    assert row[1].strip().startswith("pair-00: 0.5, pair-01: 1.5")


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda r: (r / "notes").mkdir() or (r / "notes" / "gone.md").write_text("x"), "gone.md"),
        (lambda r: (r / "x.md").write_bytes(b"\xff\xfe"), "x.md"),
    ],
)
def test_bad_results_are_one_line_and_exit_2(tmp_path, capsys, make, message):
    results = tmp_path / "results"
    results.mkdir()
    make(results)
    assert main(["--results", str(results), "--out", str(tmp_path / "r.md")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench report: ") and message in err[0]
    assert main(["--results", str(tmp_path / "none"), "--out", str(tmp_path / "r.md")]) == 2


def test_docs_results_md_is_the_page_of_the_results_in_the_tree(tmp_path):
    out = ROOT / "docs" / "results.md"
    assert out.read_text() == page(RESULTS, out), "run python3 -m bench report"
