"""bench.studies.acceptance: the leave-one-building-out estimate of the threshold's false
accepts."""

from __future__ import annotations

from bench.studies.acceptance import buildings, held_out_rows


def _record(pair: str, building: str, margin: float, **info: str) -> dict:
    return {"pair": pair, "building": building, "info": info, "result": {"margin": margin}}


def test_a_threshold_set_without_a_building_is_tested_on_it():
    classes = {
        "right": [(_record("a-ok", "a", 0.9), 0.9), (_record("b-ok", "b", 0.8), 0.8)],
        "wrong": [(_record("a-bad", "a", 0.5), 0.5)],
        "negative": [
            (_record("b-mirror", "b", 0.7), 0.7),
            (_record("x", "cross", 0.3, building_a="a", building_b="c"), 0.3),
        ],
    }
    assert buildings(classes["negative"][1][0]) == {"a", "c"}
    rows = {r.split(" | ")[0].strip("| "): r for r in held_out_rows(classes)}
    # without b, the largest false margin is a's 0.5: b's mirror at 0.7 passes, b's right pose too
    assert rows["b"] == "| b | 0.51 | 1/1 (100 %) | 1/1 (100 %) | b-mirror |"
    # without a, b's mirror sets 0.71: a's wrong pose and the cross negative stay out
    assert rows["a"] == "| a | 0.71 | 1/1 (100 %) | 0/2 (0 %) | - |"
    # c holds only the cross negative
    assert rows["c"] == "| c | 0.71 | - | 0/1 (0 %) | - |"
