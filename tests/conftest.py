"""Shared fixtures: the real data set lives in ``../shared`` beside the project root."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


@pytest.fixture(scope="session")
def shared() -> Path:
    """Path of the shared real data (maps/, logs/); skips when it is absent."""
    if not (SHARED / "maps").is_dir():
        pytest.skip(f"shared data not found at {SHARED}")
    return SHARED
