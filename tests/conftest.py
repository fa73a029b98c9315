"""Shared test helpers: the real datasets beside the project (``../shared/data``), skipped when absent."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
"""The real sequences (7-Scenes, KITTI, TUM, video) of ``../shared/data``; absent on a fresh clone."""


def shared_data(name: str) -> Path:
    """``SHARED / name``, or skip the calling test with the reason when it is not there."""
    path = SHARED / name
    if not path.exists():
        pytest.skip(f"shared data {name!r} not found at {path} (../shared/data is not part of a fresh clone)")
    return path


@pytest.fixture
def shared():
    """The :func:`shared_data` helper as a fixture: ``shared("kitti-odometry")``."""
    return shared_data
