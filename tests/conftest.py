"""Shared test helpers: the real datasets beside the project (``../shared/data``), skipped when absent."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
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


def notebook_stream(nb, name: str | None = None) -> str:
    """What the executed notebook ``nb`` printed (``name``: "stdout" or "stderr"; both when None), cell by cell.

    Within a cell the stream outputs are concatenated as written: the kernel flushes its output buffer on a
    timer, so one ``print`` can arrive as two outputs on a busy machine (joining them with a newline would break
    the line a test looks for). Cells are separated by a newline."""
    cells = []
    for c in nb.cells:
        if c.cell_type == "code":
            cells.append("".join(o.get("text", "") for o in c.get("outputs", [])
                                 if o.output_type == "stream" and (name is None or o.get("name") == name)))
    return "\n".join(cells)


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


def _pyramid_camera():
    from slamkit.camera import Intrinsics

    return Intrinsics(640, 480, 500.0, 500.0, 320.0, 240.0)


def pyramid_noise_map(num_keyframes: int = 5, n: int = 400, seed: int = 0, per_observation: bool = False):
    """A map of known points and poses whose keypoints carry ORB's pyramid noise: (map, true points (n, 3), true
    poses (4x4 cam_from_world), octaves). Keyframes 0.25 m apart along x look at points 4-6 m away; a keypoint
    at octave o (0-7) sits at its exact projection plus noise of 1.2^o px per axis (ORB-SLAM's model: 1 px at
    the finest level), and its size says its level (31 px x 1.2^o, as OpenCV's ORB). Each point has one octave
    in every keyframe ((n,) octaves), or with ``per_observation`` one drawn per keyframe ((keyframes, n))."""
    from slamkit.features import Features
    from slamkit.map import SlamMap, rigid_from_matrix

    camera = _pyramid_camera()
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1.5, -1.0, 4.0], [2.5, 1.0, 6.0], (n, 3))
    octave = None if per_observation else rng.integers(0, 8, n)
    octaves = []
    poses = []
    for k in range(num_keyframes):
        T = np.eye(4)
        T[:3, 3] = [-0.25 * k, 0.0, 0.0]
        poses.append(T)
    slam_map = SlamMap(camera)
    for k, T in enumerate(poses):
        level = rng.integers(0, 8, n) if per_observation else octave
        octaves.append(level)
        sigma = 1.2 ** level
        Xc = X @ T[:3, :3].T + T[:3, 3]
        exact = Xc[:, :2] / Xc[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
        kp = exact + rng.normal(0.0, 1.0, (n, 2)) * sigma[:, None]
        feats = Features(kp, rng.integers(0, 256, (n, 32), dtype=np.uint8), np.ones(n, np.float32), True,
                         sizes=(31.0 * sigma).astype(np.float32), image_size=(camera.width, camera.height))
        slam_map.add_image(k, k / 10, kp, feats, np.zeros((n, 3), np.uint8))
    ids = list(range(1, num_keyframes + 1))
    for a in ids:
        for b in ids:
            if a < b:
                slam_map.add_matches(a, b, np.stack([np.arange(n), np.arange(n)], axis=1))
    slam_map.observe(*ids)
    for image_id, T in zip(ids, poses):
        slam_map.register(image_id, rigid_from_matrix(T))
    for i in range(n):
        slam_map.add_point(X[i], tuple((image_id, i) for image_id in ids), np.zeros(3, np.uint8))
    slam_map.changed()
    return slam_map, X, poses, (np.array(octaves) if per_observation else octave)


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
