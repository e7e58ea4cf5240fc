"""Hostile and broken input on the fleet's keys: agents keep running, the global map is untouched.

Three keyed agents (``--key-file``) agree first; then a rogue process in a namespace of its own
(``tests/rogue.py``) publishes, one attack at a time: random bytes, truncated genuine tiles, an
oversized geometry and a NaN resolution (both correctly keyed, as a buggy insider would send),
a newer map of r1 without the fleet key and with a wrong one, replays of genuine old versions,
and a flood. After each attack the agents' drop counters must have grown under the expected
reason; at the end every agent is alive, holds the same versions and global map as before,
its memory stayed bounded, and ``pgvd status`` shows the drops by reason.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from netfleet import PORT, SOURCES, NetFleet, digests, wait_agreed
from netns import Lab, lab_or_skip, pgvd_argv, read_line

pytestmark = [pytest.mark.netns, pytest.mark.fleet, pytest.mark.slow]

#: attack -> drop reason it must raise (in every agent's status): what the decoder refused
#: (protocol.errors.REASONS) or, for a genuine old version, the agent's own stale_version.
#: Truncated keyed messages cut past the header also fail their MAC (auth): only the MAC
#: can tell, and it cannot tell a cut from a forgery.
ATTACKS = {
    "random": "framing",
    "truncated": "framing",
    "oversized": "limit",
    "nan": "value",
    "spoofed": "auth",
    "replay": "stale_version",
    "queries": "schema",  # malformed tile fetches at the latest queryables
}
FLOOD = (20_000, 1_000), (1_000, 60_000)  # (messages, bytes each)


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError(f"no VmRSS for pid {pid}")


def drops(fleet: NetFleet) -> dict[str, dict[str, int]]:
    return {r: dict((s or {}).get("drops", {})) for r, s in fleet.statuses().items()}


def growth(before: dict, after: dict) -> dict[str, dict[str, int]]:
    """Per agent, the drop reasons that grew from ``before`` to ``after``, and by how much."""
    return {
        r: {k: n - before[r].get(k, 0) for k, n in d.items() if n > before[r].get(k, 0)}
        for r, d in after.items()
    }


def command(rogue: subprocess.Popen, line: str) -> str:
    rogue.stdin.write(line + "\n")
    rogue.stdin.flush()
    return read_line(rogue).strip()


@pytest.fixture(scope="module")
def attacked() -> dict:
    lab_or_skip()
    out: dict = {"attacks": {}}
    with tempfile.TemporaryDirectory(prefix="pgvd-hostile-") as tmp, Lab(4) as lab:
        key = Path(tmp) / "fleet.key"
        key.write_text("a shared secret of the test fleet\n")
        fleet = NetFleet(lab, Path(tmp), extra=["--speed", "400", "--key-file", str(key)])
        connect = [a for h in lab.hosts[:3] for a in ("--connect", h.endpoint(PORT))]
        rogue_argv = [sys.executable, "tests/rogue.py", "--fleet", fleet.fleet, *connect]
        # It also listens, so that the pgvd status run from its host hears its forged replies.
        rogue_ep = lab.hosts[3].endpoint(PORT)
        rogue_argv += ["--key-file", str(key), "--listen", rogue_ep]
        rogue = lab.popen(3, rogue_argv, name="rogue", stdin=True)
        assert read_line(rogue).strip() == "READY", lab.stderr_of("rogue")
        for host, (robot, (source, frame)) in enumerate(SOURCES.items()):
            fleet.start(robot, host, source, frame)
        out["agreed_in"] = wait_agreed(fleet, 90)
        assert out["agreed_in"] is not None, "no agreement before the attacks"
        before = fleet.statuses()
        pids = {r: p.pid for r, p in fleet.procs.items()}
        out["rss_before"] = {r: rss_kb(pid) for r, pid in pids.items()}
        for attack, reason in ATTACKS.items():
            counts = drops(fleet)
            reply = command(rogue, attack)
            assert reply.startswith(f"done {attack} "), (reply, lab.stderr_of("rogue"))
            sent = int(reply.split()[2])
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                now = drops(fleet)
                grown = {r: now[r].get(reason, 0) - counts[r].get(reason, 0) for r in now}
                if all(g > 0 for g in grown.values()):
                    break
                time.sleep(0.3)
            by = growth(counts, now)
            out["attacks"][attack] = {"sent": sent, "reason": reason, "dropped": grown, "by": by}
        peak = dict(out["rss_before"])
        for n, size in FLOOD:
            counts = {r: s["counts"]["messages_received"] for r, s in fleet.statuses().items()}
            dropped = drops(fleet)
            reply = command(rogue, f"flood {n} {size}")
            for _ in range(10):  # the agents drain their queues for a few seconds
                peak = {r: max(peak[r], rss_kb(pid)) for r, pid in pids.items()}
                time.sleep(0.3)
            got = {
                r: s["counts"]["messages_received"] - counts[r] for r, s in fleet.statuses().items()
            }
            out["attacks"][f"flood {n}x{size}B"] = {
                "sent": n,
                "seconds": float(reply.split()[3]),
                "received": got,
                # framing (random bytes), and overload if the receive queue filled up
                "by": growth(dropped, drops(fleet)),
            }
        out["rss_peak"] = peak
        out["rogue_log"] = lab.stderr_of("rogue")
        time.sleep(2)
        out["rss_after"] = {r: rss_kb(pid) for r, pid in pids.items()}
        out["alive"] = not fleet.dead()
        out["agreed_after"] = wait_agreed(fleet, 30)
        after = fleet.statuses()
        out["before"], out["after"] = before, after
        assert command(rogue, "status").startswith("done status 2")
        status_argv = pgvd_argv(
            "status", "--fleet", fleet.fleet, "--json", *connect[:2], "--connect", rogue_ep
        )
        for name, argv in (
            ("status", [*status_argv, "--key-file", str(key)]),
            ("nokey", status_argv),
        ):
            status_cli = lab.popen(3, argv, name=name)
            stdout, _ = status_cli.communicate(timeout=60)
            out[name] = (status_cli.returncode, stdout, lab.stderr_of(name))
        rogue.stdin.close()
    for name, row in out["attacks"].items():
        print(f"{name}: {row}")
    print("RSS kB before/peak/after:", out["rss_before"], out["rss_peak"], out["rss_after"])
    return out


@pytest.mark.parametrize("attack", list(ATTACKS))
def test_every_agent_drops_and_counts_the_attack(attacked: dict, attack: str) -> None:
    row = attacked["attacks"][attack]
    assert row["sent"] > 0
    assert all(n > 0 for n in row["dropped"].values()), row


def test_agents_survive_with_bounded_memory(attacked: dict) -> None:
    assert attacked["alive"]
    for n, size in FLOOD:
        received = attacked["attacks"][f"flood {n}x{size}B"]["received"]
        assert all(got > n // 10 for got in received.values()), received  # the flood arrived
    for robot, before in attacked["rss_before"].items():
        # 21 000 messages (80 MB) were thrown at each agent; its queue is bounded in count
        # and drained by a decoder that rejects on the MAC before parsing anything.
        assert attacked["rss_peak"][robot] - before < 150_000, (robot, attacked["rss_peak"])


def test_malformed_fetches_get_no_map(attacked: dict) -> None:
    assert "malformed fetches answered: 0" in attacked["rogue_log"], attacked["rogue_log"][-500:]


def test_global_map_and_versions_are_unaffected(attacked: dict) -> None:
    before, after = attacked["before"], attacked["after"]
    assert attacked["agreed_after"] is not None
    assert digests(after) == digests(before) and len(digests(after)) == 1
    for robot in before:
        versions = {r: v["version"] for r, v in after[robot]["robots"].items()}
        assert versions == {r: v["version"] for r, v in before[robot]["robots"].items()}
        assert after[robot]["components"] == before[robot]["components"]


def test_pgvd_status_shows_the_drops_by_reason(attacked: dict) -> None:
    rc, stdout, stderr = attacked["status"]
    assert rc == 0
    statuses = json.loads(stdout)
    assert set(statuses) == set(SOURCES)  # the rogue's forged r8 and r9 are not among them
    assert "status/r9: reply carries no fleet MAC" in stderr, stderr
    assert "status/r8: reply carries no fleet MAC" in stderr, stderr
    for status in statuses.values():
        want = {"framing", "auth", "limit", "value", "stale_version", "schema"}
        assert want <= set(status["drops"]), status["drops"]
        assert "bad_message" not in status["drops"]  # every drop names what it broke


def test_without_the_key_pgvd_status_still_refuses_malformed_replies(attacked: dict) -> None:
    """No key, no proof of origin: the forged r9 is shown, the malformed r8 is refused."""
    rc, stdout, stderr = attacked["nokey"]
    assert rc == 0
    assert set(json.loads(stdout)) == {*SOURCES, "r9"}
    assert "status/r8: links[0] lacks fields" in stderr, stderr


def test_forged_messages_fail_for_the_intended_reason() -> None:
    """The rogue's keyed forgeries are refused for what they break, not for a bad forgery."""
    from rogue import Rogue

    from protocol import ProtocolError, decode, encode_map

    rogue = Rogue(None, "t", b"k")  # type: ignore[arg-type]

    def huge(body: dict) -> None:
        rogue._geometry(body)[:2] = [20_000, 20_000]

    def nan(body: dict) -> None:
        rogue._geometry(body)[2] = float("nan")

    decode(rogue.forged_manifest("r1", lambda body: None), b"k")  # an unedited forgery passes
    for edit, reason in ((huge, "side limit"), (nan, "must be finite")):
        with pytest.raises(ProtocolError, match=reason):
            decode(rogue.forged_manifest("r1", edit), b"k")
    for key, reason in ((None, "no MAC"), (b"wrong", "wrong MAC")):
        with pytest.raises(ProtocolError, match=reason):
            decode(encode_map("t", "r1", 10_000, rogue.grid(), key)[1], b"k")
