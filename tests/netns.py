"""Lossy test networks on one machine: network namespaces, veth pairs and nftables.

``tc netem`` is not in this kernel, so loss is injected with an nftables ``netdev`` egress rule
(``numgen random mod 100 < P drop``) on a veth device.

Topology of one :class:`Lab`: a hidden hub namespace holds a bridge; every host namespace is joined
to it by one veth pair and gets the address ``127.10.0.<i+1>/24`` (``route_localnet=1``, ``lo`` up).
A packet from host A to host B crosses A's egress rule and then the hub port towards B, so
``Lab(n, loss_pct=20)`` drops 20 % of the packets on every directed path ("20 % each way"), and
``ingress_pct`` adds loss on the way into a host. Addresses repeat between labs: every lab lives
in namespaces of its own, so parallel labs never collide; only namespace names are unique
(``pgvd-<pid>-<seq>-...``), and namespaces left behind by a dead process are removed on entry.

Use from a test::

    lab_or_skip()                      # pytest.skip with the exact reason when impossible
    with Lab(3, loss_pct=20) as lab:
        proc = lab.popen(0, [sys.executable, "-c", "..."])
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_PREFIX = "pgvd-"
_STALE = re.compile(rf"^{_PREFIX}(\d+)-\d+-")
_SEQ = itertools.count()
SUBNET = "127.10.0"
_EXEC = ("ip", "netns", "exec")


def pgvd_argv(*args: str) -> list[str]:
    """The command line of ``pgvd ARGS`` through this interpreter (works before pip install)."""
    return [sys.executable, "-c", "import sys; from agent.cli import main; sys.exit(main())", *args]


class NetnsError(RuntimeError):
    """A namespace, link or nftables command failed; the message holds the command and stderr."""


def _cmd(argv: Sequence[str], stdin: str | None = None) -> str:
    proc = subprocess.run(list(argv), input=stdin, capture_output=True, text=True, timeout=20)
    if proc.returncode != 0:
        raise NetnsError(f"`{' '.join(argv)}` failed: {proc.stderr.strip() or proc.returncode}")
    return proc.stdout


def _nft(ns: str, script: str) -> None:
    _cmd(["ip", "netns", "exec", ns, "nft", "-f", "-"], stdin=script)


def _loss_table(table: str, dev: str, pct: int) -> str:
    """An nftables table dropping ``pct`` % of the packets leaving ``dev`` (uniformly at random)."""
    return (
        f"table netdev {table} {{\n chain c {{\n"
        f'  type filter hook egress device "{dev}" priority 0; policy accept;\n'
        f"  numgen random mod 100 < {pct} counter drop\n }}\n}}\n"
    )


def _split_table(dev: str, others: Sequence[str]) -> str:
    """An nftables table dropping every packet from ``dev`` to the addresses ``others``."""
    return (
        f"table netdev split {{\n chain c {{\n"
        f'  type filter hook egress device "{dev}" priority -10; policy accept;\n'
        f"  ip daddr {{ {', '.join(others)} }} counter drop\n }}\n}}\n"
    )


def _delete_table(ns: str, table: str) -> None:
    subprocess.run(
        ["ip", "netns", "exec", ns, "nft", "delete", "table", "netdev", table],
        capture_output=True,
        timeout=20,
    )


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _delete_namespace(ns: str) -> None:
    """Kill what still runs inside ``ns`` (processes a lab started), then delete it."""
    pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True, timeout=20)
    for pid in pids.stdout.split():
        with contextlib.suppress(ProcessLookupError, ValueError):
            os.kill(int(pid), signal.SIGKILL)
    subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)


def clean_stale() -> list[str]:
    """Delete the ``pgvd-<pid>-...`` namespaces whose creating process is gone."""
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=20)
    stale = []
    for line in out.stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        match = _STALE.match(name)
        if match and not _alive(int(match.group(1))):
            _delete_namespace(name)
            stale.append(name)
    return stale


@lru_cache(maxsize=1)
def unavailable_reason() -> str | None:
    """Why labs cannot be built here (None when they can); probed once per process."""
    if os.geteuid() != 0:
        return f"needs root for network namespaces (euid {os.geteuid()})"
    for tool, package in (("ip", "iproute2"), ("nft", "nftables")):
        if shutil.which(tool) is None:
            return f"`{tool}` not found (apt-get install {package})"
    probe = f"{_PREFIX}{os.getpid()}-probe-x"
    try:
        clean_stale()
        _cmd(["ip", "netns", "add", probe])
        _cmd(["ip", "-n", probe, "link", "add", "p0", "type", "veth", "peer", "name", "p1"])
        _nft(probe, _loss_table("probe", "p0", 10))
    except (NetnsError, OSError, subprocess.TimeoutExpired) as exc:
        return f"network namespaces with nftables egress loss unavailable: {exc}"
    finally:
        _delete_namespace(probe)
    return None


def lab_or_skip() -> None:
    """``pytest.skip`` with the exact reason when labs cannot be built on this machine."""
    import pytest

    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(reason)


@dataclass
class Host:
    """One namespace of a lab: its name, address and the host-side device of its veth pair."""

    index: int
    ns: str
    addr: str
    dev: str = "eth0"

    def endpoint(self, port: int, proto: str = "tcp") -> str:
        """A Zenoh locator of this host, e.g. ``tcp/127.10.0.1:7447``."""
        return f"{proto}/{self.addr}:{port}"


@dataclass
class Lab:
    """``n`` hosts on one bridge, with optional per-host egress/ingress loss in percent."""

    n: int
    loss_pct: int = 0
    ingress_pct: int = 0
    hosts: list[Host] = field(default_factory=list)
    logdir: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="pgvd-lab-")))
    _procs: list[subprocess.Popen] = field(default_factory=list)
    _hub: str = ""

    def __enter__(self) -> Lab:
        if not 1 <= self.n <= 250:
            raise ValueError(f"a lab holds 1..250 hosts, not {self.n}")
        clean_stale()
        tag = f"{_PREFIX}{os.getpid()}-{next(_SEQ)}-"
        self._hub = tag + "hub"
        try:
            self._build(tag)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(keep_logs=exc_type is not None)

    def _build(self, tag: str) -> None:
        _cmd(["ip", "netns", "add", self._hub])
        _cmd(["ip", "-n", self._hub, "link", "add", "br0", "type", "bridge"])
        _cmd(["ip", "-n", self._hub, "link", "set", "br0", "up"])
        for i in range(self.n):
            host = Host(i, f"{tag}h{i}", f"{SUBNET}.{i + 1}")
            self.hosts.append(host)
            _cmd(["ip", "netns", "add", host.ns])
            peer = ["peer", "name", host.dev, "netns", host.ns]
            _cmd(["ip", "-n", self._hub, "link", "add", f"p{i}", "type", "veth", *peer])
            _cmd(["ip", "-n", self._hub, "link", "set", f"p{i}", "master", "br0", "up"])
            for key in ("all", "default", host.dev):
                sysctl = f"net.ipv4.conf.{key}.route_localnet=1"
                _cmd(["ip", "netns", "exec", host.ns, "sysctl", "-q", "-w", sysctl])
            _cmd(["ip", "-n", host.ns, "addr", "add", f"{host.addr}/24", "dev", host.dev])
            _cmd(["ip", "-n", host.ns, "link", "set", "lo", "up"])
            _cmd(["ip", "-n", host.ns, "link", "set", host.dev, "up"])
            self.set_loss(i, self.loss_pct, self.ingress_pct)

    def set_loss(self, index: int, egress_pct: int, ingress_pct: int = 0) -> None:
        """Drop ``egress_pct`` % of what host ``index`` sends, ``ingress_pct`` % of what it gets."""
        for pct in (egress_pct, ingress_pct):
            if not 0 <= pct <= 100:
                raise ValueError(f"loss must be 0..100 %, not {pct}")
        host = self.hosts[index]
        _delete_table(host.ns, "lossy")
        _delete_table(self._hub, f"lossy{index}")
        if egress_pct:
            _nft(host.ns, _loss_table("lossy", host.dev, egress_pct))
        if ingress_pct:
            _nft(self._hub, _loss_table(f"lossy{index}", f"p{index}", ingress_pct))

    def partition(self, *groups: Sequence[int]) -> None:
        """Cut every packet between hosts of different groups (both ways), until :meth:`heal`."""
        where = {i: g for g, members in enumerate(groups) for i in members}
        for i, host in enumerate(self.hosts):
            others = [h.addr for j, h in enumerate(self.hosts) if where.get(j, -1) != where.get(i)]
            _delete_table(host.ns, "split")
            if others:
                _nft(host.ns, _split_table(host.dev, others))

    def heal(self) -> None:
        """Undo :meth:`partition`."""
        for host in self.hosts:
            _delete_table(host.ns, "split")

    def resolve(self, src: int, dst: int) -> None:
        """Pin host ``dst``'s address in host ``src``'s neighbour table.

        The loss rule drops ARP too. While a dropped request waits a second to be sent
        again, the kernel queues only the last ~250 packets for that neighbour and drops the
        rest, outside the rule and uncounted: a slow sender (a loaded machine) then loses
        more than the rule's share. A packet count that must match the rule pins first.
        """
        target = self.hosts[dst]
        link = json.loads(_cmd(["ip", "-n", target.ns, "-j", "link", "show", target.dev]))
        host, mac = self.hosts[src], link[0]["address"]
        entry = [target.addr, "lladdr", mac, "dev", host.dev, "nud", "permanent"]
        _cmd(["ip", "-n", host.ns, "neigh", "replace", *entry])

    def dropped(self, index: int) -> int:
        """Packets the loss rule of host ``index`` dropped on egress so far."""
        out = subprocess.run(
            [
                "ip",
                "netns",
                "exec",
                self.hosts[index].ns,
                "nft",
                "list",
                "table",
                "netdev",
                "lossy",
            ],
            capture_output=True,
            text=True,
            timeout=20,
        ).stdout
        match = re.search(r"counter packets (\d+)", out)
        return int(match.group(1)) if match else 0

    def snmp(self, index: int, proto: str, field_name: str) -> int:
        """A counter of host ``index``'s IP stack, e.g. ``snmp(0, "Udp", "OutDatagrams")``."""
        lines = [
            line.split()
            for line in _cmd([*_EXEC, self.hosts[index].ns, "cat", "/proc/net/snmp"]).splitlines()
            if line.startswith(f"{proto}:")
        ]
        return int(lines[1][lines[0].index(field_name)])

    def popen(
        self,
        index: int,
        argv: Sequence[str],
        name: str | None = None,
        env: dict[str, str] | None = None,
        stdin: bool = False,
    ) -> subprocess.Popen:
        """Start ``argv`` inside host ``index`` (cwd = project root, own session, output logged).

        stdout is a pipe (read it for results); stderr goes to ``<logdir>/<name>.err``; stdin
        is a pipe if ``stdin`` (to drive the process), else empty.
        """
        err = open(self.logdir / f"{name or f'h{index}-{len(self._procs)}'}.err", "wb")  # noqa: SIM115
        full_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        proc = subprocess.Popen(
            ["ip", "netns", "exec", self.hosts[index].ns, *argv],
            cwd=ROOT,
            env=full_env,
            stdout=subprocess.PIPE,
            stderr=err,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            text=True,
            start_new_session=True,
        )
        err.close()
        self._procs.append(proc)
        return proc

    def stderr_of(self, name: str) -> str:
        """The stderr a process started with ``name`` has written so far."""
        path = self.logdir / f"{name}.err"
        return path.read_text(errors="replace") if path.exists() else ""

    def close(self, keep_logs: bool = False) -> None:
        """Stop every process the lab started, then delete every namespace (always safe).

        The processes' stderr logs survive in :attr:`logdir` when ``keep_logs`` (a failed test).
        """
        for proc in self._procs:
            if proc.poll() is None:
                _signal_group(proc, signal.SIGTERM)
        for proc in self._procs:
            try:
                proc.wait(timeout=3)
            except subprocess.TimeoutExpired:
                _signal_group(proc, signal.SIGKILL)
                proc.wait(timeout=5)
            for stream in (proc.stdout, proc.stdin):
                if stream:
                    stream.close()
        self._procs.clear()
        for host in self.hosts:
            _delete_namespace(host.ns)
        if self._hub:
            _delete_namespace(self._hub)
        self.hosts.clear()
        if keep_logs:
            print(f"lab logs kept in {self.logdir}")
        else:
            shutil.rmtree(self.logdir, ignore_errors=True)


def read_line(proc: subprocess.Popen, timeout: float = 30.0) -> str:
    """The next line of ``proc``'s stdout; AssertionError after ``timeout`` s (never hangs).

    Reads the pipe byte by byte below Python's buffering, so that a line already read into a
    buffer can never hide from ``select``; use it for every line read of a lab process.
    """
    fd = proc.stdout.fileno()
    deadline = time.monotonic() + timeout
    line = bytearray()
    while not line.endswith(b"\n"):
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            raise AssertionError(f"no line from {proc.args!r} within {timeout} s: {line!r}")
        byte = os.read(fd, 1)
        if not byte:
            break
        line += byte
    return line.decode(errors="replace")


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, sig)
