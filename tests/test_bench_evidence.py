"""bench.studies.evidence: a failed pair's truth handed to the decision, against its wrong
finalists."""

from __future__ import annotations

from bench.studies.evidence import assess, classify, markdown, truth_stays
from pgvd.overlay import Agreement
from pgvd.params import MergeParams
from pgvd.scoring import fine_maps


def test_classify_orders_the_causes():
    truth = Agreement(200, 5)
    look_alike = Agreement(400, 60)  # more walls agree, more conflict: evidence 160 < 180
    assert classify(truth, [look_alike], True, None, 0.62) == "margin"
    assert classify(truth, [look_alike], False, (True, 0.9), 0.62) == "search"
    assert classify(truth, [look_alike], False, (True, 0.3), 0.62) == "faint"
    assert classify(truth, [look_alike], False, (False, 0.9), 0.62) == "refinement"
    assert classify(truth, [look_alike], False, None, 0.62) == "weighting"
    # a wrong pose that agrees as much and conflicts no more: no weight prefers the truth
    assert classify(truth, [look_alike, Agreement(200, 5)], False, None, 0.62) == "dominated"


def test_assess_hands_the_truth_to_the_decision(intel_split):
    """Real maps: with only a wrong pose (B slid 3 m) among the finalists, the truth is
    picked, refined within the bounds and accepted, so the pair was lost by the search."""
    wrong = intel_split.truth.copy()
    wrong[0, 2] += 60.0
    record = {"set": "standard", "finalists": [wrong.tolist()], "matrix": wrong.tolist()}
    params = MergeParams(diagnostics=False)
    maps = fine_maps(intel_split.a.probability(), intel_split.b.probability(), params)
    assert truth_stays(intel_split, maps, params)
    row = assess(intel_split, record, maps, params)
    assert row["class"] == "search" and row["truth_margin"] >= 0.62
    truth_agree, truth_disagree = row["truth"]
    rival_agree, rival_disagree = row["rival"]
    assert truth_agree > rival_agree and truth_disagree < rival_disagree
    # no finalist at all: the truth is weighed against its probes alone
    row = assess(intel_split, {**record, "finalists": []}, maps, params)
    assert row["class"] == "search" and row["rival"] is None


def test_markdown_counts_each_class_per_set():
    rows = [
        {"pair": "l0", "set": "low", "class": "faint", "truth": [200, 0], "truth_margin": 0.3,
         "rival": [400, 60]},
        {"pair": "l1", "set": "low", "class": "search", "truth": [180, 2], "truth_margin": 0.9,
         "rival": None},
        {"pair": "d0", "set": "drifted", "class": "weighting", "truth": [900, 300],
         "truth_margin": None, "rival": [100, 20]},
    ]  # fmt: skip
    stays = {"low": [True, True, False, True], "drifted": [True, True]}
    text = markdown(rows, stays, "python3 -m bench evidence")
    assert "| low | 4 | 1 | 2 | 0 | 1 | 1 | 0 | 0 | 0 |" in text
    assert "| drifted | 2 | 0 | 1 | 0 | 0 | 0 | 0 | 1 | 0 |" in text
    assert "| l0 | faint | 200 / 0 | 0.30 | 400 / 60 |" in text
    assert "| d0 | weighting | 900 / 300 | - | 100 / 20 |" in text
    assert "standard" not in text.split("agree / disagree")[0]
