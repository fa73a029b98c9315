"""Shared test helpers: the real datasets beside the project (``../shared/data``), skipped when absent."""

from __future__ import annotations

import os
from pathlib import Path

import psutil
import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
"""The real sequences (7-Scenes, KITTI, TUM, video) of ``../shared/data``; absent on a fresh clone."""


def shared_data(name: str) -> Path:
    """``SHARED / name``, or skip the calling test with the reason when it is not there."""
    path = SHARED / name
    if not path.exists():
        pytest.skip(f"shared data {name!r} not found at {path} (../shared/data is not part of a fresh clone)")
    return path


def image_folder_run(tmp_path: Path, motion: str, frames: int, init_frames: int):
    """A rendered ``motion`` written as a plain image folder (``tmp_path/images``, PNG files) and run into
    ``tmp_path/run`` with its exact camera: (source, image folder, run folder, the run's outcome)."""
    import shutil

    from slamkit.config import SlamConfig
    from slamkit.runner import run_to_folder
    from slamkit.sources.synthetic import synthetic_source, write_tum_sequence

    src = synthetic_source(motion, frames=frames)
    tum = write_tum_sequence(src, tmp_path / "tum")
    folder = tmp_path / "images"
    folder.mkdir()
    for p in sorted((tum / "rgb").glob("*.png")):
        shutil.copy(p, folder / p.name)
    cam = src.camera
    config = SlamConfig().with_overrides(init_frames=init_frames, camera=f"{cam.fx},{cam.fy},{cam.cx},{cam.cy}")
    run = tmp_path / "run"
    return src, folder, run, run_to_folder(str(folder), run, config, evaluate_ate=False)


@pytest.fixture
def shared():
    """The :func:`shared_data` helper as a fixture: ``shared("kitti-odometry")``."""
    return shared_data


def meshcat_servers() -> set[int]:
    """PIDs of the running meshcat servers (slamkit's ``_meshcat_server.py``) started from this test process:
    under pytest-xdist, only those whose environment names this worker (kernels and their servers inherit
    it), so a check for leaked servers does not see another worker's."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    out = set()
    for p in psutil.process_iter(["cmdline"]):
        if not any(str(a).endswith("_meshcat_server.py") for a in (p.info["cmdline"] or [])):
            continue
        if worker is not None:
            try:
                if p.environ().get("PYTEST_XDIST_WORKER") != worker:
                    continue
            except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
                continue
        out.add(p.pid)
    return out
