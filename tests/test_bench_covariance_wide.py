"""bench.studies.covariance_wide: the reported covariance of accepted poses against their errors."""

from __future__ import annotations

import numpy as np
import pytest

from bench.studies.covariance_wide import accepted_right, errors_and_covariances, groups, markdown
from pgvd.grid import rigid_matrix


def _record(name: str, building: str, set_: str, error: tuple[float, float, float], **kw) -> dict:
    """An accepted pair whose pose is ``error`` (tx px, ty px, psi rad) off a truth, with the
    covariance diag(4, 1, 1e-4)."""
    truth = rigid_matrix(0.3, 10.0, -5.0)
    psi, tx, ty = 0.3 + error[2], 10.0 + error[0], -5.0 + error[1]
    rec = {
        "pair": name,
        "method": "pgvd",
        "kind": "overlap",
        "accepted": True,
        "set": set_,
        "source": f"{building}-sim",
        "building": building,
        "truth": truth.tolist(),
        "matrix": rigid_matrix(psi, tx, ty).tolist(),
        "result": {"covariance": np.diag([4.0, 1.0, 1e-4]).tolist()},
        "heading_deg": abs(np.degrees(error[2])),
        "cell_err": 1.0,
        "cell_tolerance": 3.0,
    }
    rec.update(kw)
    return rec


def test_each_pose_is_weighed_by_its_own_covariance() -> None:
    recs = [
        _record("a", "intel", "standard", (2.0, 0.0, 0.0)),  # NEES 1
        _record("b", "willow", "drifted", (0.0, 1.0, 0.02)),  # NEES 1 + 4 = 5
        _record("c", "willow", "standard", (0.0, 0.0, 0.0), cell_err=9.0),  # accepted wrong
        _record("d", "willow", "standard", (0.0, 0.0, 0.0), accepted=False),
    ]
    right, wrong = accepted_right(recs)
    assert [r["pair"] for r in right] == ["a", "b"] and wrong == 1
    errors, covs = errors_and_covariances(right)
    full = np.einsum("ni,ni->n", errors, np.linalg.solve(covs, errors[..., None])[..., 0])
    assert full == pytest.approx([1.0, 5.0])
    rows = groups(right)
    assert [r["pair"] for r in rows["buildings the calibration never saw"]] == ["b"]
    assert [r["pair"] for r in rows["drifted"]] == ["b"] and "low" not in rows
    text = markdown(recs, "run.json", "python3 -m bench covariance_wide --merge run.json")
    assert "| all | 2 | 3.00 |" in text and "| drifted | 1 | 5.00 |" in text
    assert "(2; 1 accepted at a wrong pose are left out, and so are the fr079 gmapping" in text
