"""agent.counters: drops counted by reason, logged once per reason and sender, bounded."""

from __future__ import annotations

import logging

from agent.counters import MAX_LOGGED, Counters


def test_drops_are_counted_by_reason_and_logged_once_per_sender(caplog) -> None:
    counters = Counters()
    with caplog.at_level(logging.WARNING, logger="pgvd.agent"):
        for _ in range(3):
            counters.drop("auth", "r9", "wrong MAC")
        counters.drop("auth", "r8", "message carries no MAC but a fleet key is configured")
        counters.drop("limit", "r9", "map of 20000x20000 cells exceeds the side limit 16384")
    assert counters.snapshot()["drops"] == {"auth": 4, "limit": 1}
    logged = [r.getMessage() for r in caplog.records]
    assert logged == [
        "dropped message (auth) from r9: wrong MAC",
        "dropped message (auth) from r8: message carries no MAC but a fleet key is configured",
        "dropped message (limit) from r9: map of 20000x20000 cells exceeds the side limit 16384",
    ]


def test_forged_sender_ids_cannot_flood_the_log(caplog) -> None:
    counters = Counters()
    with caplog.at_level(logging.WARNING, logger="pgvd.agent"):
        for i in range(10 * MAX_LOGGED):
            counters.drop("framing", f"forged{i}", "not a pgvd message: bad magic")
        counters.drop("value", "forged0", "resolution must be finite, got nan")
    assert counters.snapshot()["drops"] == {"framing": 10 * MAX_LOGGED, "value": 1}
    assert len(caplog.records) == MAX_LOGGED + 1  # a new reason is still logged
    assert "(value) from forged0" in caplog.records[-1].getMessage()
