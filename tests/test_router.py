"""``pgvd router``: a real Zenoh router; sites linked through two routers in separate namespaces."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from netns import ROOT, Lab, lab_or_skip, pgvd_argv, read_line

ROUTER_CONFIG = ROOT / "deploy" / "router.json5"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_router(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        pgvd_argv("router", *args),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def run_pgvd(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(pgvd_argv(*args), cwd=ROOT, capture_output=True, text=True, timeout=30)


def test_bad_config_is_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    missing = tmp_path / "none.json5"
    for args in (["--config", bad], ["--config", missing], ["--listen", "nosuch/1.2.3.4:5"]):
        proc = run_pgvd("router", *map(str, args))
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("pgvd router: error:")


def test_port_in_use_is_a_clean_error() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    first = start_router("--listen", endpoint)
    try:
        assert read_line(first).startswith("ready ")
        second = run_pgvd("router", "--listen", endpoint)
        assert second.returncode == 2
        assert "Address already in use" in second.stderr and second.stderr.count("\n") == 1
    finally:
        first.terminate()
        first.wait(timeout=10)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_closes_the_router_cleanly(sig: signal.Signals) -> None:
    port = free_port()
    peer_site = f"tcp/127.0.0.1:{free_port()}"  # nobody there: the router keeps retrying
    listen = f"tcp/127.0.0.1:{port}"
    router = start_router(
        "--config", str(ROUTER_CONFIG), "--listen", listen, "--connect", peer_site
    )
    try:
        ready = read_line(router).split()
        assert ready[0] == "ready" and json.loads(ready[-1]) == [f"tcp/127.0.0.1:{port}"]
        start = time.monotonic()
        router.send_signal(sig)
        assert router.wait(timeout=10) == 0
        print(f"{sig.name}: router exited in {time.monotonic() - start:.3f} s")
        assert router.stderr.read().strip() == "closed"
    finally:
        # a router left running listens on localhost, where the next tests' peers find it
        router.kill()
        router.wait()


@pytest.mark.netns
@pytest.mark.slow
def test_clients_of_two_linked_routers_exchange_puts_and_liveliness() -> None:
    """Site A and site B each run a router on their own host; a client of A reaches B's client."""
    lab_or_skip()
    with Lab(2, loss_pct=20) as lab:
        routers = []
        for i in (0, 1):
            link = ["--connect", lab.hosts[1].endpoint(7447)] if i == 0 else []
            args = ["--config", str(ROUTER_CONFIG), "--listen", "tcp/0.0.0.0:7447", *link]
            routers.append(lab.popen(i, pgvd_argv("router", *args), name=f"router{i}"))
        for i, router in enumerate(routers):
            assert read_line(router).startswith("ready "), lab.stderr_of(f"router{i}")
        # Wait for the inter-site link, so that what follows exercises router-to-router routing.
        opened = read_line(routers[1]).split()
        assert opened[:2] == ["open", "router"], opened
        client = {
            "mode": "client",
            "connect/endpoints": ["tcp/127.0.0.1:7447"],
            "scouting/multicast/enabled": False,
            "transport/shared_memory/enabled": False,
        }
        count = 200
        args = ["--count", str(count), "--config", json.dumps(client)]
        sub = lab.popen(1, [sys.executable, "tests/zprobe.py", "sub", *args], name="sub")
        assert read_line(sub).strip() == "READY", lab.stderr_of("sub")
        args += ["--interval", "0.002", "--settle", "1.0"]
        pub = lab.popen(0, [sys.executable, "tests/zprobe.py", "pub", *args], name="pub")
        result = json.loads(sub.communicate(timeout=60)[0].splitlines()[-1])
        assert json.loads(pub.communicate(timeout=30)[0].splitlines()[-1])["matched"]
        for router in routers:
            assert router.poll() is None, "a router died"
    assert sorted(result["seqs"]) == list(range(count))
    assert result["alive"], "the liveliness token of site A's client must reach site B"


def test_a_close_that_hangs_does_not_keep_the_router_alive(monkeypatch, capsys) -> None:
    """A Zenoh session whose close never returns (seen in CI with a --connect endpoint where
    nobody listens): the router waits CLOSE_TIMEOUT_S, says so, and exits 0 without it."""
    import threading

    from agent.cli import router

    never = threading.Event()

    class Listener:
        def undeclare(self) -> None:
            pass

    class Session:
        def close(self) -> None:
            never.wait()

    def exit_now(code: int) -> None:
        raise SystemExit(code)

    monkeypatch.setattr(router, "CLOSE_TIMEOUT_S", 0.1)
    monkeypatch.setattr(router.os, "_exit", exit_now)
    with pytest.raises(SystemExit) as stopped:
        router._close(Session(), Listener())
    never.set()
    assert stopped.value.code == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "the Zenoh session did not close within 0.1 s; exiting without it",
        "closed",
    ]
