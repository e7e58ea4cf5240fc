"""``pgvd agent`` refuses bad input with one line and exit code 2, before serving."""

from __future__ import annotations

import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from netns import ROOT, pgvd_argv, read_line

from agent.cli import main

LOG = Path(__file__).resolve().parents[1] / "agent" / "data" / "intel-corrected.log.gz"


def agent(tmp_path: Path, *extra: str) -> list[str]:
    src = f"carmen:{LOG}@0.0-0.05"
    return ["agent", "--robot", "r1", "--source", src, "--state-dir", str(tmp_path), *extra]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--robot", "r/1"], "robot id"),
        (["--source", "carmen:/nonexistent.log"], "source file not found"),
        (["--source", "tape:x"], "source must be"),
        (["--source", f"carmen:{Path(__file__).parent}"], "is a directory, not a file"),
        (["--source", f"map:{Path(__file__).parent}"], "is a directory, not a file"),
        (["--frame", "1,2"], "frame must be"),
        (["--key-file", "/nonexistent.key"], "cannot read key file"),
        (["--speed", "0"], "--speed"),
        (["--inbox-mib", "0"], "--inbox-mib must be > 0"),
        (["--lease-ms", "-5"], "--lease-ms must be > 0"),
        (["--listen", "garbage"], "Endpoints must be of the form"),
        (["--min-agreement", "1.5"], "--min-agreement"),
        (["--zenoh-config", "/nonexistent.json5"], "bad Zenoh config"),
        (["--source", "ros2:robot1/map"], "not an absolute ROS 2 topic"),
        (["--source", "rosbag:/nonexistent_bag"], "source file not found"),
        (["--ros-publish", "map merged"], "not an absolute ROS 2 topic"),
        (["--ros-links", "links"], "not an absolute ROS 2 topic"),
        (["--ros-publish", "/m", "--ros-links", "/m"], "--ros-links /m is the map's topic"),
        (["--ros-frame", "/world"], "--ros-frame"),
        (["--ros-frame", "r1/map"], "is a robot's map frame"),
        (["--resolution", "5"], "--resolution 5: a cell size of 5 m is outside"),
        (["--ros-domain", "300"], "domain id"),
        (["--ros-rate", "0"], "--ros-rate must be > 0"),
        (["--foxglove", "8765"], "HOST:PORT"),
        (["--known-pose", "r2=1,2"], "ROBOT=x,y,yaw"),
        (["--known-pose", "r/2=1,2,0.5"], "robot id"),
        (["--known-pose", "r2=1,2,0", "--known-pose", "r2=0,0,0"], "known pose of r2 given twice"),
    ],
)
def test_bad_arguments(tmp_path: Path, capsys, extra: list[str], message: str) -> None:
    assert main(agent(tmp_path, *extra)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_taken_listen_port_is_one_line(tmp_path: Path, capsys) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(agent(tmp_path, "--listen", f"tcp/127.0.0.1:{port}")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot open the Zenoh session" in err


def test_known_poses_reach_the_agent_options(tmp_path: Path) -> None:
    from agent.cli.agent import options_from_args
    from agent.cli.dispatch import build_parser

    argv = agent(tmp_path, "--known-pose", "r1=0,0,0", "--known-pose", "r2=4.0,-1.5,0.3")
    opts = options_from_args(build_parser(["agent"]).parse_args(argv))
    assert dict(opts.known_poses) == {"r1": (0.0, 0.0, 0.0), "r2": (4.0, -1.5, 0.3)}


@pytest.mark.parametrize(
    ("extra", "module", "message"),
    [
        (
            ["--source", "ros2:/robot1/map"],
            "rosbags",
            "--source ros2: needs rosbags, which is not installed: pip install 'pgvd-fleet[ros2]'",
        ),
        (["--source", "rosbag:/some/bag"], "rosbags", "--source rosbag: needs rosbags"),
        (["--ros-publish", "/map_merged"], "rosbags", "--ros-publish needs rosbags"),
        (["--ros-links", "/map_merged_links"], "rosbags", "--ros-links needs rosbags"),
        (
            ["--foxglove", "127.0.0.1:8765"],
            "foxglove",
            "--foxglove needs foxglove, which is not installed: pip install 'pgvd-fleet[view]'",
        ),
    ],
)
def test_a_missing_extra_is_named_in_one_line(
    tmp_path: Path, capsys, monkeypatch, extra: list[str], module: str, message: str
) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # as if it were not installed
    assert main(agent(tmp_path, *extra)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_an_agent_without_ros_needs_neither_extra(tmp_path: Path, monkeypatch) -> None:
    """rosbags (ros2) and foxglove-sdk (view) are extras: a carmen: agent runs without them."""
    from agent.cli.agent import options_from_args
    from agent.cli.dispatch import build_parser
    from protocol.ros2.types import typestore

    for module in ("rosbags", "foxglove"):
        monkeypatch.setitem(sys.modules, module, None)
    typestore.cache_clear()  # a type store made by an earlier test would hide an import
    opts = options_from_args(build_parser(["agent"]).parse_args(agent(tmp_path)))
    assert opts.source.kind == "carmen" and not opts.outputs.active


def test_a_map_file_that_never_reads_is_logged_once(tmp_path: Path) -> None:
    """A map: source whose file is there but unreadable is retried every poll, and said once.

    Before, the agent stayed up and silent; only ``pgvd status`` showed the read errors.
    """
    shutil.copy(ROOT / "examples" / "intel_a.pgm", tmp_path / "m.pgm")
    text = (ROOT / "examples" / "intel_a.yaml").read_text()
    bad = tmp_path / "m.yaml"
    bad.write_text(
        "".join(
            "resolution: -0.05\n" if ln.startswith("resolution") else ln
            for ln in text.splitlines(keepends=True)
        )
    )
    argv = pgvd_argv(
        "agent", "--robot", "r1", "--source", f"map:{bad}", "--state-dir", str(tmp_path / "s"),
        "--listen", "tcp/127.0.0.1:0",
    )  # fmt: skip
    # the agent logs to stderr: read it as the stdout of the process
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    proc.stdout = proc.stderr
    try:
        lines = [read_line(proc, timeout=30)]
        while " INFO " in lines[-1]:  # the agent's decisions and membership: always logged
            lines.append(read_line(proc, timeout=30))
        line = lines[-1]
        assert any(" INFO agent r1 up in fleet default" in ln for ln in lines), lines
        assert "WARNING source" in line and "resolution: a cell size of -0.05 m is outside" in line
        with pytest.raises(AssertionError, match="no line"):
            read_line(proc, timeout=2)  # retried every 0.5 s, not repeated
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
