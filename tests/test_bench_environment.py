"""bench.environment: what a bench result was measured with."""

from __future__ import annotations

import subprocess

import numpy as np

from bench import environment


def test_the_record_names_the_installed_libraries_and_the_checkout():
    env = environment.environment()
    assert env["libraries"]["numpy"] == np.__version__
    assert set(env["libraries"]) == set(environment.LIBRARIES)
    line = environment.describe(env)
    assert f"numpy {np.__version__}" in line and f"{env['cpus']} CPUs" in line
    head = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        cwd=environment.ROOT,
        capture_output=True,
        text=True,
    )
    if head.returncode == 0:  # a checkout: its commit, dirty or not
        assert env["commit"].split("+")[0] == head.stdout.strip()


def test_outside_git_the_commit_is_unknown(monkeypatch, tmp_path):
    monkeypatch.setattr(environment, "ROOT", tmp_path)
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))
    assert environment.commit() is None
    assert "commit unknown" in environment.describe({**environment.environment(), "commit": None})


def test_an_uninstalled_library_is_none_and_left_out_of_the_line(monkeypatch):
    monkeypatch.setattr(environment, "LIBRARIES", ("numpy", "no-such-distribution-pgvd"))
    env = environment.environment()
    assert env["libraries"]["no-such-distribution-pgvd"] is None
    assert "no-such-distribution-pgvd" not in environment.describe(env)


def test_pairs_made_under_other_library_versions_are_made_again(monkeypatch, tmp_path):
    from bench.sets import cached

    made = []

    def make():
        made.append(1)
        return len(made)

    assert cached(tmp_path, "pairs", make) == 1
    assert cached(tmp_path, "pairs", make) == 1  # read back, not made again
    (path,) = tmp_path.iterdir()
    assert path.name.endswith(f"-e{environment.libraries_key()}.pkl")
    versions = {name: "0.0" for name in environment.LIBRARIES}
    monkeypatch.setattr(environment, "_version", versions.get)
    assert cached(tmp_path, "pairs", make) == 2  # another numpy: another cache entry
    assert len(list(tmp_path.iterdir())) == 2
