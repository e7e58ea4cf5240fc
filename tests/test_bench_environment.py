"""bench.environment: what a bench result was measured with, and the pair cache's key."""

from __future__ import annotations

import subprocess

import numpy as np

from bench import environment


def test_the_record_names_the_imported_libraries_and_the_checkout():
    env = environment.environment()
    assert env["libraries"]["numpy"] == np.__version__
    assert set(env["libraries"]) == set(environment.LIBRARIES)
    line = environment.describe(env)
    assert f"numpy {np.__version__}" in line and f"{env['cpus']} CPUs" in line
    head = subprocess.run(
        ["git", "rev-parse", "--short=12", "HEAD"],
        cwd=environment.ROOT,
        capture_output=True,
        text=True,
    )
    if head.returncode == 0:  # a checkout: its commit, dirty or not
        assert env["commit"].split("+")[0] == head.stdout.strip()


def test_a_copy_outside_git_or_inside_another_repository_has_no_commit(monkeypatch, tmp_path):
    bench = tmp_path / "project" / "bench"
    bench.mkdir(parents=True)
    (bench / "environment.py").write_text("# a source export\n")
    monkeypatch.setattr(environment, "ROOT", tmp_path / "project")
    monkeypatch.setattr(environment, "__file__", str(bench / "environment.py"))
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))
    assert environment.commit() is None  # no repository at all
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t"]
    subprocess.run([*git, "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "other.txt").write_text("x")
    subprocess.run([*git, "-C", str(tmp_path), "add", "other.txt"], check=True)
    subprocess.run([*git, "-C", str(tmp_path), "commit", "-qm", "x"], check=True)
    assert environment.commit() is None  # the outer repository's commit is not this code's
    assert "commit unknown" in environment.describe({**environment.environment(), "commit": None})


def test_bench_results_do_not_make_the_code_dirty(monkeypatch, tmp_path):
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-C", str(tmp_path)]
    for rel in ("bench/environment.py", f"{environment.RESULTS}/merge.md"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("v1\n")
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "x"], check=True)
    monkeypatch.setattr(environment, "ROOT", tmp_path)
    monkeypatch.setattr(environment, "__file__", str(tmp_path / "bench/environment.py"))
    (tmp_path / environment.RESULTS / "merge.md").write_text("a bench rewrote it\n")
    assert not environment.commit().endswith("+dirty")
    (tmp_path / "bench/environment.py").write_text("v2\n")
    assert environment.commit().endswith("+dirty")


def test_a_library_that_does_not_import_is_none_and_left_out_of_the_line(monkeypatch):
    monkeypatch.setattr(environment, "LIBRARIES", {"numpy": "numpy", "nope": "no_such_module_x"})
    env = environment.environment()
    assert env["libraries"]["nope"] is None
    assert "nope" not in environment.describe(env)


def test_pairs_made_under_other_library_versions_are_made_again(monkeypatch, tmp_path):
    from bench.data.sets import cached

    made = []

    def make():
        made.append(1)
        return len(made)

    assert cached(tmp_path, "pairs", make) == 1
    assert cached(tmp_path, "pairs", make) == 1  # read back, not made again
    (path,) = tmp_path.iterdir()
    assert path.name.endswith(f"{environment.cache_suffix()}.pkl")
    monkeypatch.setattr(environment, "_version", lambda module: "0.0")
    assert cached(tmp_path, "pairs", make) == 2  # another numpy: another cache entry
    assert len(list(tmp_path.iterdir())) == 2
