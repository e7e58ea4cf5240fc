"""``pgvd demo --out DIR`` deletes only the files an earlier demo wrote in DIR, never a user's."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from agent.cli.common import CliError
from agent.cli.outdir import MARKER, claim, record
from agent.launcher import ROOT


def tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` with its bytes (symlinks as their target's path)."""
    out = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if path.is_symlink():
            out[rel] = os.readlink(path).encode()
        elif path.is_file():
            out[rel] = path.read_bytes()
    return out


def a_demo_run(out: Path) -> None:
    """What a demo leaves behind: files at the top and in per-robot directories."""
    claim(out)
    (out / "r1" / "state").mkdir(parents=True)
    (out / "r1" / "state" / "maps.npz").write_bytes(b"\0" * 64)
    (out / "r1" / "agent.log").write_text("started\n")
    (out / "report.json").write_text("{}")
    record(out)


def test_demo_refuses_the_current_directory_and_deletes_nothing(tmp_path: Path) -> None:
    """Defect: ``--out .`` ran ``shutil.rmtree`` on the current directory."""
    (tmp_path / "thesis.tex").write_text("three years of work")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "run1.csv").write_text("1,2,3\n")
    before = tree(tmp_path)
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "demo",
            "--robots",
            "2",
            "--timeout",
            "1",
            "--out",
            ".",
        ],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert tree(tmp_path) == before
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.count("\n") == 1 and "did not write" in res.stderr


def test_a_new_or_empty_directory_is_claimed(tmp_path: Path) -> None:
    claim(tmp_path / "new" / "out")
    assert (tmp_path / "new" / "out" / MARKER).is_file()
    (tmp_path / "empty").mkdir()
    claim(tmp_path / "empty")
    assert [p.name for p in (tmp_path / "empty").iterdir()] == [MARKER]


def test_an_earlier_demo_directory_is_emptied(tmp_path: Path) -> None:
    a_demo_run(tmp_path)
    claim(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == [MARKER]


@pytest.mark.parametrize(
    "user_edit",
    [
        lambda out: (out / "notes.txt").write_text("mine"),
        lambda out: (out / "r1" / "state" / "mine.npz").write_bytes(b"1"),
        lambda out: (out / "report.json").write_text('{"edited": true}'),
        lambda out: (out / MARKER).write_text("not json"),
        lambda out: (out / MARKER).unlink(),
    ],
    ids=["file at top", "file in a robot dir", "edited report", "bad marker", "no marker"],
)
def test_any_file_the_demo_did_not_write_stops_it_before_deleting(
    tmp_path: Path, user_edit
) -> None:
    a_demo_run(tmp_path)
    user_edit(tmp_path)
    before = tree(tmp_path)
    with pytest.raises(CliError, match="did not write"):
        claim(tmp_path)
    assert tree(tmp_path) == before


def test_a_symlink_is_removed_not_followed(tmp_path: Path) -> None:
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "keep.txt").write_text("keep")
    out = tmp_path / "out"
    claim(out)
    (out / "link").symlink_to(target, target_is_directory=True)
    record(out)
    claim(out)
    assert not (out / "link").is_symlink() and (target / "keep.txt").read_text() == "keep"


def test_a_file_is_not_a_directory(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(CliError, match="not a directory"):
        claim(tmp_path / "f")
    assert (tmp_path / "f").read_text() == "x"
