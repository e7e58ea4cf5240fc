"""deploy/: every config loads in Zenoh; TLS and access control do what their comments promise."""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh
from netns import ROOT, pgvd_argv, read_line

DEPLOY = ROOT / "deploy"
CERT_DIR = "/etc/pgvd/tls"  # where the example configs expect the certificates
MEMBERS = ("robot-1", "robot-2")


@pytest.mark.parametrize(
    ("name", "mode"),
    [
        ("peer.json5", "peer"),
        ("client.json5", "client"),
        ("router.json5", "router"),
        ("tls/router.json5", "router"),
        ("tls/client.json5", "client"),
        ("acl/router.json5", "router"),
    ],
)
def test_config_loads_with_its_role(name: str, mode: str) -> None:
    config = zenoh.Config.from_file(str(DEPLOY / name))
    assert json.loads(config.get_json("mode")) == mode


def test_systemd_unit_verifies(tmp_path: Path) -> None:
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze not found (apt-get install systemd)")
    # verify checks that ExecStart's binary exists; pgvd may not be in /usr/local/bin here.
    unit = (DEPLOY / "pgvd-agent.service").read_text().replace("/usr/local/bin/pgvd", "/bin/true")
    (tmp_path / "pgvd-agent.service").write_text(unit)
    verify = ["systemd-analyze", "verify", str(tmp_path / "pgvd-agent.service")]
    proc = subprocess.run(verify, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    lines = (DEPLOY / "pgvd-agent.env").read_text().splitlines()
    env = {line.split("=", 1)[0] for line in lines if line and not line.startswith("#")}
    # Every variable ExecStart uses comes from the env file or from systemd itself.
    used = set(re.findall(r"\$\{?([A-Z_]+)\}?", unit.split("[Service]", 1)[1]))
    assert used - {"STATE_DIRECTORY", "CREDENTIALS_DIRECTORY"} == env


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CA, a router certificate and client certificates made by deploy/tls/make-certs.sh."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl not found: the TLS examples' test certificates are made with it")
    out = tmp_path_factory.mktemp("tls")
    script = DEPLOY / "tls" / "make-certs.sh"
    names = ["router.site-a", *MEMBERS, "visitor"]
    subprocess.run(["sh", str(script), str(out), *names], check=True, timeout=60)
    other = out / "other-fleet"
    subprocess.run(["sh", str(script), str(other), "router.site-a", "robot-1"], check=True)
    return out


def example(name: str, certs: Path, tmp_path: Path, **edits: object) -> Path:
    """A copy of deploy/``name`` pointing at ``certs``, with config paths set to ``edits``."""
    config = zenoh.Config.from_json5((DEPLOY / name).read_text().replace(CERT_DIR, str(certs)))
    for path, value in edits.items():
        config.insert_json5(path.replace("__", "/"), json.dumps(value))
    out = tmp_path / name.replace("/", "-")
    out.write_text(str(config))  # the whole config as JSON
    return out


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def router(config: Path) -> Iterator[subprocess.Popen]:
    argv = pgvd_argv("router", "--config", str(config))
    proc = subprocess.Popen(
        argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        line = read_line(proc)
    except AssertionError as exc:
        # a router that never says ready: its stderr says why (read once it is dead,
        # since a live process's pipe would block)
        proc.kill()
        raise AssertionError(f"{exc}\nrouter stderr:\n{proc.communicate(timeout=10)[1]}") from None
    try:
        assert line.startswith("ready "), proc.stderr.read() if proc.poll() is not None else line
        yield proc
    finally:
        proc.terminate()
        assert proc.wait(timeout=10) == 0


def tls_client(certs: Path, tmp_path: Path, port: int, cn: str, ca: Path | None = None) -> Path:
    """deploy/tls/client.json5 as robot ``cn``, connecting to the local router on ``port``."""
    return example(
        "tls/client.json5",
        certs,
        tmp_path,
        connect__endpoints=[f"tls/localhost:{port}"],
        transport__link__tls__connect_certificate=str(certs / f"{cn}.pem"),
        transport__link__tls__connect_private_key=str(certs / f"{cn}.key"),
        transport__link__tls__root_ca_certificate=str(ca or certs / "ca.pem"),
    )


def can_open(config: Path) -> bool:
    try:
        zenoh.open(zenoh.Config.from_file(str(config))).close()
    except zenoh.ZError:
        return False
    return True


def test_tls_client_reaches_tls_router_and_plain_or_foreign_clients_cannot(
    certs: Path, tmp_path: Path
) -> None:
    port = free_port()
    config = example(
        "tls/router.json5", certs, tmp_path, listen__endpoints=[f"tls/127.0.0.1:{port}"]
    )
    with router(config):
        got: list[bytes] = []
        arrived = threading.Event()

        def on_sample(sample: zenoh.Sample) -> None:
            got.append(sample.payload.to_bytes())
            arrived.set()

        with open_as(certs, tmp_path, port, "robot-2") as sub_s:
            sub = sub_s.declare_subscriber("pgvd/fleet-a/**", on_sample)
            with open_as(certs, tmp_path, port, "robot-1") as pub_s:
                wait_matching(pub_s, "pgvd/fleet-a/x")
                pub_s.put("pgvd/fleet-a/x", b"over tls")
                assert arrived.wait(5)
            sub.undeclare()
        assert got == [b"over tls"]
        plain = zenoh.Config()
        plain_settings = {
            "mode": "client",
            "connect/endpoints": [f"tcp/127.0.0.1:{port}"],
            "scouting/multicast/enabled": False,
        }
        for key, value in plain_settings.items():
            plain.insert_json5(key, json.dumps(value))
        with pytest.raises(zenoh.ZError):
            zenoh.open(plain)
        foreign_ca = certs / "other-fleet" / "ca.pem"
        assert not can_open(tls_client(certs, tmp_path, port, "robot-1", ca=foreign_ca))


def wait_matching(session: zenoh.Session, key: str, timeout: float = 5.0) -> None:
    pub = session.declare_publisher(key)
    deadline = time.monotonic() + timeout
    while not pub.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.01)
    assert pub.matching_status.matching, "no subscriber matched through the router"
    pub.undeclare()


def open_as(certs: Path, tmp_path: Path, port: int, cn: str) -> zenoh.Session:
    return zenoh.open(zenoh.Config.from_file(str(tls_client(certs, tmp_path, port, cn))))


def received_through(config: Path, certs: Path, tmp_path: Path, port: int) -> dict[str, list]:
    """What robot-2 and a visitor hear when robot-1 (a member) and a visitor (not a member) both
    publish, hold a liveliness token and answer queries under the fleet's keys.

    Every role has a session of its own, so that nothing is delivered locally.
    """
    heard: dict[str, list] = {"robot-2": [], "visitor": []}
    with router(config):
        roles = {"robot-2": "robot-2", "visitor": "visitor", "robot-1": "robot-1", "pub": "visitor"}
        sessions = {role: open_as(certs, tmp_path, port, cn) for role, cn in roles.items()}
        try:
            subs = [
                sessions[role].declare_subscriber(
                    "pgvd/fleet-a/**", lambda s, role=role: heard[role].append(s.payload.to_bytes())
                )
                for role in heard
            ]
            held = [
                declared
                for role, name in (("robot-1", "robot-1"), ("pub", "visitor"))
                for declared in answer_as(sessions[role], name)
            ]
            wait_matching(sessions["robot-1"], "pgvd/fleet-a/tiles/1")
            sessions["robot-1"].put("pgvd/fleet-a/tiles/1", b"member")
            sessions["pub"].put("pgvd/fleet-a/tiles/2", b"visitor")
            time.sleep(0.5)
            asker = sessions["robot-2"]
            heard["alive"] = sorted(
                str(r.ok.key_expr)
                for r in asker.liveliness().get("pgvd/fleet-a/alive/*", timeout=2.0)
                if r.ok is not None
            )
            heard["replies"] = sorted(
                str(r.ok.key_expr)
                for r in asker.get("pgvd/fleet-a/latest/**", timeout=2.0)
                if r.ok is not None
            )
            for entity in [*subs, *held]:
                entity.undeclare()
        finally:
            for session in sessions.values():
                session.close()
    return heard


def answer_as(session: zenoh.Session, name: str) -> list:
    """A liveliness token and a ``latest`` queryable of robot ``name``, as an agent holds them."""
    reply_key = f"pgvd/fleet-a/latest/{name}/1/m"
    return [
        session.liveliness().declare_token(f"pgvd/fleet-a/alive/{name}"),
        session.declare_queryable(
            f"pgvd/fleet-a/latest/{name}/**", lambda q: q.reply(reply_key, name.encode())
        ),
    ]


def test_acl_lets_only_fleet_members_publish_hold_tokens_and_answer(
    certs: Path, tmp_path: Path
) -> None:
    port = free_port()
    listen = {"listen__endpoints": [f"tls/127.0.0.1:{port}"]}
    acl_router = example("acl/router.json5", certs, tmp_path, **listen)
    enforced = received_through(acl_router, certs, tmp_path, port)
    assert enforced == {
        "robot-2": [b"member"],
        "visitor": [b"member"],
        "alive": ["pgvd/fleet-a/alive/robot-1"],  # the visitor's token never got past
        "replies": ["pgvd/fleet-a/latest/robot-1/1/m"],  # nor its queryable
    }
    # Control: the same run without access control delivers the visitor's put, token and
    # replies, so the ACL is what dropped them above (and not, say, a lost sample).
    open_router = example(
        "acl/router.json5", certs, tmp_path, access_control__enabled=False, **listen
    )
    heard = received_through(open_router, certs, tmp_path, port)
    assert sorted(heard["robot-2"]) == [b"member", b"visitor"]
    assert heard["alive"] == ["pgvd/fleet-a/alive/robot-1", "pgvd/fleet-a/alive/visitor"]
    assert heard["replies"] == [
        "pgvd/fleet-a/latest/robot-1/1/m",
        "pgvd/fleet-a/latest/visitor/1/m",
    ]
