"""Issue 50, item 6: frame times come from what each frame is (its timestamp or its number), never from its
position among the frames that happened to be there or readable.

A rendered sequence written as a numbered image folder (``000000.png`` ...), with one frame replaced by a file of
another kind (``000005.gif``), one that cannot be decoded (``000009.png`` of garbage) and one missing
(``000012.png``): every other frame keeps its number's time, its ground truth, and the run's trajectory file
its time. The same for names that are timestamps, for a 7-Scenes folder with a missing frame, and the documented
rule for names that are not numbers (the place in the list of image files, unreadable ones counted).
"""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from slamkit.config import SlamConfig
from slamkit.io import read_tum
from slamkit.runner import run_to_folder
from slamkit.sources import open_folder, open_source
from slamkit.sources.synthetic import DEFAULT_FPS, synthetic_source, write_tum_sequence

N = 24
GIF, GARBAGE, MISSING = 5, 9, 12  # frame numbers: another kind of file, an undecodable PNG, no file


def _rendered(tmp_path: Path, motion: str = "handheld"):
    src = synthetic_source(motion, frames=N)
    tum = write_tum_sequence(src, tmp_path / "tum")
    rgb = sorted((tum / "rgb").glob("*.png"), key=lambda p: float(p.stem))
    assert len(rgb) == N and np.allclose(src.timestamps, np.arange(N) / DEFAULT_FPS)
    return src, tum, rgb


def _damaged_numbered_folder(tmp_path: Path):
    src, tum, rgb = _rendered(tmp_path)
    folder = tmp_path / "images"
    folder.mkdir()
    for k, p in enumerate(rgb):
        shutil.copy(p, folder / f"{k:06d}.png")
    (folder / f"{GIF:06d}.png").rename(folder / f"{GIF:06d}.gif")  # not an image file of the sequence
    (folder / f"{GARBAGE:06d}.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0garbage" * 50)  # cannot be decoded
    (folder / f"{MISSING:06d}.png").unlink()
    return src, tum, folder


def _camera_text(src) -> str:
    c = src.camera
    return f"{c.fx},{c.fy},{c.cx},{c.cy}"


def test_numbered_folder_times_and_ground_truth_come_from_the_numbers(tmp_path):
    src, tum, folder = _damaged_numbered_folder(tmp_path)
    numbers = [k for k in range(N) if k not in (GIF, MISSING)]
    f = open_folder(folder, camera=_camera_text(src), groundtruth=tum / "groundtruth.txt")
    assert list(f.frame_ids) == numbers
    np.testing.assert_allclose(f.timestamps, np.array(numbers) / DEFAULT_FPS, rtol=0, atol=1e-12)
    np.testing.assert_allclose(f.gt_poses, src.gt_poses[numbers], atol=1e-9)  # each frame its own pose
    # the same with frame skip: every other listed file, each with its own number's time
    g = open_folder(folder, frame_skip=2, camera=_camera_text(src))
    np.testing.assert_allclose(g.timestamps, np.array(numbers[::2]) / DEFAULT_FPS, rtol=0, atol=1e-12)


def test_a_run_on_the_damaged_folder_writes_each_frame_at_its_own_time(tmp_path):
    src, tum, folder = _damaged_numbered_folder(tmp_path)
    source = open_folder(folder, camera=_camera_text(src), groundtruth=tum / "groundtruth.txt")
    out = tmp_path / "run"
    outcome = run_to_folder(source, out, SlamConfig().with_overrides(init_frames=8))
    assert outcome.saved and outcome.summary["frames_posed"] >= N - 6
    rows = list(csv.DictReader((out / "frames.csv").open()))
    by_file = {r["file"]: r for r in rows}
    assert by_file[f"{GARBAGE:06d}.png"]["status"] == "skipped"  # unreadable: skipped, its place kept
    for r in rows:
        assert float(r["timestamp"]) == pytest.approx(int(Path(r["file"]).stem) / DEFAULT_FPS, abs=1e-6)
    est, gt = read_tum(out / "trajectory_tum.txt"), read_tum(out / "groundtruth_tum.txt")
    truth = read_tum(tum / "groundtruth.txt")
    posed = {int(Path(r["file"]).stem) for r in rows if r["status"] not in ("skipped", "lost", "error")}
    np.testing.assert_allclose(est.timestamps, np.array(sorted(posed)) / DEFAULT_FPS, atol=1e-6)
    # the run's ground truth is the rendered truth at those times, frame by frame
    idx = np.rint(gt.timestamps * DEFAULT_FPS).astype(int)
    np.testing.assert_allclose(gt.poses, truth.poses[idx], atol=1e-6)
    assert outcome.ate is not None and outcome.ate["rmse"] < 0.01  # metres: each pose against its own truth


def test_names_that_are_timestamps_are_the_times(tmp_path):
    src, tum, rgb = _rendered(tmp_path)
    folder = tmp_path / "stamps"
    folder.mkdir()
    for p in rgb:
        shutil.copy(p, folder / p.name)  # 0.000000.png 0.033333.png ...
    (folder / rgb[MISSING].name).unlink()
    (folder / rgb[GARBAGE].name).write_bytes(b"not an image")
    f = open_folder(folder, camera=_camera_text(src), groundtruth=tum / "groundtruth.txt")
    kept = [k for k in range(N) if k != MISSING]
    np.testing.assert_allclose(f.timestamps, [float(rgb[k].stem) for k in kept], rtol=0, atol=1e-12)
    np.testing.assert_allclose(f.gt_poses, src.gt_poses[kept], atol=1e-9)


def test_names_that_are_not_numbers_keep_their_place_unreadable_ones_counted(tmp_path):
    _, _, rgb = _rendered(tmp_path)
    folder = tmp_path / "named"
    folder.mkdir()
    letters = "abcdefgh"
    for k, c in enumerate(letters):
        shutil.copy(rgb[k], folder / f"view_{c}.png")
    (folder / "view_c.png").write_bytes(b"garbage")
    f = open_folder(folder, fps=10)
    assert [p.name for p in f.paths] == [f"view_{c}.png" for c in letters]
    np.testing.assert_allclose(f.timestamps, np.arange(len(letters)) / 10)
    with pytest.raises(Exception, match="view_c.png"):
        f[2]  # skipped when read (its reason names it); view_d.png keeps the time of the 4th place
    assert f[3].timestamp == pytest.approx(0.3)


def test_sevenscenes_folder_with_a_missing_frame(tmp_path):
    src, _, rgb = _rendered(tmp_path)
    seq = tmp_path / "scene" / "seq-01"
    seq.mkdir(parents=True)
    for k, p in enumerate(rgb):
        if k == MISSING:
            continue
        shutil.copy(p, seq / f"frame-{k:06d}.color.png")
        np.savetxt(seq / f"frame-{k:06d}.pose.txt", src.gt_poses[k], fmt="%.12e")
    f = open_source(tmp_path / "scene", camera=_camera_text(src))
    kept = [k for k in range(N) if k != MISSING]
    assert list(f.frame_ids) == kept
    np.testing.assert_allclose(f.timestamps, np.array(kept) / 30.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(f.gt_poses, src.gt_poses[kept], atol=1e-9)
