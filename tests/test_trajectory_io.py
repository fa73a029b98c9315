"""Trajectory files (TUM, KITTI) and atomic writes."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slamkit.errors import ConfigError, FormatError, OutputError, SlamkitError
from slamkit.geometry import pose_from_tum
from slamkit.io import (atomic_dir, atomic_write_bytes, atomic_write_text, read_kitti, read_trajectory,
                        read_tum, write_kitti, write_tum)
from slamkit.io import trajectory as trajectory_module
from slamkit.io.run_dir import write_manifest
from slamkit.types import Trajectory

GOOD_Q = "0 0 0 1"


def random_trajectory(n: int = 50, seed: int = 0, t0: float = 1305031098.6659) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.uniform(0.01, 0.05, n))
    q = rng.normal(size=(n, 4))
    p = rng.normal(scale=3.0, size=(n, 3))
    return Trajectory(t, pose_from_tum(p, q))


def leftovers(folder: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


# ------------------------------------------------------------------------------------------ round trips

def test_tum_round_trip_is_exact(tmp_path):
    traj = random_trajectory()
    path = write_tum(tmp_path / "est.txt", traj)
    back = read_tum(path)
    np.testing.assert_array_equal(back.timestamps, traj.timestamps)
    np.testing.assert_array_equal(back.positions, traj.positions)
    np.testing.assert_allclose(back.poses, traj.poses, rtol=0, atol=1e-15)
    assert path.read_text().startswith("# timestamp tx ty tz qx qy qz qw\n")
    # writing what was read gives the same numbers again
    again = read_tum(write_tum(tmp_path / "again.txt", back))
    np.testing.assert_array_equal(again.timestamps, back.timestamps)
    np.testing.assert_allclose(again.poses, back.poses, rtol=0, atol=1e-15)


def test_kitti_round_trip_is_bit_exact(tmp_path):
    traj = random_trajectory(seed=1)
    path = write_kitti(tmp_path / "07.txt", traj)
    lines = path.read_text().splitlines()
    assert len(lines) == len(traj) and all(len(line.split()) == 12 for line in lines)
    back = read_kitti(path)
    np.testing.assert_array_equal(back.poses, traj.poses)
    np.testing.assert_array_equal(back.timestamps, np.arange(len(traj)))
    with_times = read_kitti(path, timestamps=traj.timestamps)
    np.testing.assert_array_equal(with_times.timestamps, traj.timestamps)
    # a KITTI times.txt
    times = tmp_path / "times.txt"
    times.write_text("".join(f"{t:e}\n" for t in np.arange(len(traj)) * 0.1))
    np.testing.assert_allclose(read_kitti(path, times).timestamps, np.arange(len(traj)) * 0.1)


def test_empty_trajectory_round_trip(tmp_path):
    empty = Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    assert len(read_tum(write_tum(tmp_path / "e.tum", empty))) == 0
    assert len(read_kitti(write_kitti(tmp_path / "e.kitti", empty))) == 0
    with pytest.raises(FormatError, match="no data lines"):
        read_trajectory(tmp_path / "e.tum")


def test_read_trajectory_guesses_format(tmp_path):
    traj = random_trajectory(seed=2)
    tum = read_trajectory(write_tum(tmp_path / "a.txt", traj))
    np.testing.assert_array_equal(tum.timestamps, traj.timestamps)
    kitti = read_trajectory(write_kitti(tmp_path / "b.txt", traj))
    np.testing.assert_array_equal(kitti.poses, traj.poses)
    (tmp_path / "c.txt").write_text("# hello\n1 2 3 4 5\n")
    with pytest.raises(FormatError) as e:
        read_trajectory(tmp_path / "c.txt")
    assert e.value.line == 2 and "8 (TUM" in str(e.value)
    with pytest.raises(ConfigError, match="timestamps"):
        read_trajectory(tmp_path / "a.txt", timestamps=traj.timestamps)


def test_comments_blank_lines_crlf_bom_and_commas(tmp_path):
    path = tmp_path / "gt.txt"
    path.write_bytes(b"\xef\xbb\xbf# ground truth\r\n\r\n"
                     b"1.0 1 2 3 0 0 0 1\r\n"
                     b"   # indented comment\n"
                     b"2.5,4,5,6,0,0,0,2  # trailing comment; quaternion not unit -> rejected\n")
    with pytest.raises(FormatError) as e:
        read_tum(path)
    assert e.value.line == 5 and "norm" in str(e.value)
    path.write_bytes(path.read_bytes().replace(b"0,0,0,2", b"0,0,0,1.0001"))
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.timestamps, [1.0, 2.5])
    np.testing.assert_array_equal(traj.positions, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(traj.poses[1, :3, :3], np.eye(3), atol=1e-15)  # quaternion normalised


@pytest.mark.shared_data
def test_real_tum_ground_truth_reads_if_present(shared):
    traj = read_trajectory(shared("tum/groundtruth-only/fr1_xyz/groundtruth.txt"))
    assert len(traj) > 100 and np.all(np.diff(traj.timestamps) > 0)
    np.testing.assert_allclose(traj.positions[0], [1.3563, 0.6305, 1.6380])


# ------------------------------------------------------------------------------------------ malformed

TUM_BAD = [
    ("1 2 3 4 5 6 7", "expected 8 values"),
    ("1 2 3 4 0 0 0 1 9", "expected 8 values"),
    ("1 2 x 4 0 0 0 1", "not a number"),
    ("1 2 nan 4 0 0 0 1", "not a finite number"),
    ("1 inf 3 4 0 0 0 1", "not a finite number"),
    ("1 2 3 4 0 0 0 0", "norm 0"),
    ("1 2 3 4 1 1 1 1", "norm 2"),
]


@pytest.mark.parametrize("bad, reason", TUM_BAD)
def test_malformed_tum_line_names_file_and_line(tmp_path, bad, reason):
    path = tmp_path / "est.txt"
    path.write_text(f"# header\n0.5 0 0 0 {GOOD_Q}\n\n{bad}\n3 0 0 0 {GOOD_Q}\n")
    with pytest.raises(FormatError) as e:
        read_tum(path)
    assert e.value.line == 4 and e.value.path == path
    assert str(e.value).startswith(f"{path}:4: ") and reason in str(e.value)


@pytest.mark.parametrize("second", ["1.0", "0.5"])
def test_non_increasing_tum_timestamps_name_the_line(tmp_path, second):
    path = tmp_path / "est.txt"
    path.write_text(f"0.5 0 0 0 {GOOD_Q}\n1.0 0 0 0 {GOOD_Q}\n#\n{second} 0 0 0 {GOOD_Q}\n")
    with pytest.raises(FormatError) as e:
        read_tum(path)
    assert e.value.line == 4 and "strictly increasing" in str(e.value) and "line 2" in str(e.value)


KITTI_ROW = "1 0 0 0 0 1 0 0 0 0 1 0"


@pytest.mark.parametrize("bad, reason", [
    ("1 0 0 0 0 1 0 0 0 0 1", "expected 12 values"),
    ("1 0 0 0 0 1 0 0 0 0 1 zero", "not a number"),
    ("2 0 0 0 0 1 0 0 0 0 1 0", "not a rotation"),
    ("-1 0 0 0 0 1 0 0 0 0 1 0", "not a rotation"),  # a reflection, det -1
    ("1 0 0 0 0 1 0 0 0 0 1 -nan", "not a finite number"),
])
def test_malformed_kitti_line_names_file_and_line(tmp_path, bad, reason):
    path = tmp_path / "07.txt"
    path.write_text(f"{KITTI_ROW}\n{KITTI_ROW}\n{bad}\n")
    with pytest.raises(FormatError) as e:
        read_kitti(path)
    assert e.value.line == 3 and str(e.value).startswith(f"{path}:3: ") and reason in str(e.value)


def test_kitti_timestamps_must_fit(tmp_path):
    path = tmp_path / "07.txt"
    path.write_text(f"{KITTI_ROW}\n{KITTI_ROW}\n")
    times = tmp_path / "times.txt"
    times.write_text("0.0\n0.1\n0.2\n")
    with pytest.raises(FormatError, match="3 timestamps but"):
        read_kitti(path, times)
    times.write_text("0.1\n0.1\n")
    with pytest.raises(FormatError) as e:
        read_kitti(path, times)
    assert e.value.path == times and e.value.line == 2
    with pytest.raises(ConfigError):
        read_kitti(path, [0.0, 1.0, 2.0])
    with pytest.raises(ConfigError):
        read_kitti(path, [1.0, 0.0])


def test_missing_folder_and_binary_files(tmp_path):
    with pytest.raises(FormatError, match="no such file"):
        read_tum(tmp_path / "nope.txt")
    with pytest.raises(FormatError, match="folder"):
        read_kitti(tmp_path)
    path = tmp_path / "bin.txt"
    path.write_bytes(f"1 0 0 0 {GOOD_Q}\n".encode() + b"\xff\xfe\x00garbage\n")
    with pytest.raises(FormatError) as e:
        read_tum(path)
    assert e.value.line == 2 and "UTF-8" in str(e.value)


# ------------------------------------------------------------------------------------------ writing

def test_writers_refuse_trajectories_they_could_not_read_back(tmp_path):
    traj = random_trajectory(5)
    traj.timestamps[3] = traj.timestamps[2]
    with pytest.raises(OutputError, match="timestamp 3"):
        write_tum(tmp_path / "a.txt", traj)
    traj = random_trajectory(5)
    traj.poses[1, 0, 3] = np.nan
    with pytest.raises(OutputError, match="pose 1"):
        write_kitti(tmp_path / "b.txt", traj)
    assert leftovers(tmp_path, set()) == []


def test_writers_do_not_change_the_trajectory(tmp_path):
    traj = random_trajectory(5)
    t, P = traj.timestamps.copy(), traj.poses.copy()
    write_tum(tmp_path / "a.txt", traj)
    write_kitti(tmp_path / "b.txt", traj)
    np.testing.assert_array_equal(traj.timestamps, t)
    np.testing.assert_array_equal(traj.poses, P)


def test_failure_mid_write_keeps_old_file(tmp_path):
    path = tmp_path / "out.txt"
    path.write_text("old contents\n")

    def chunks():
        yield "new line 1\n"
        yield "new line 2\n"
        raise RuntimeError("formatting failed half-way")

    with pytest.raises(RuntimeError, match="half-way"):
        atomic_write_text(path, chunks())
    assert path.read_text() == "old contents\n"
    assert leftovers(tmp_path, {"out.txt"}) == []


def test_failure_while_formatting_a_trajectory_keeps_old_file(tmp_path, monkeypatch):
    path = write_tum(tmp_path / "est.txt", random_trajectory(10, seed=3))
    before = path.read_bytes()
    calls = {"n": 0}
    real_fmt = trajectory_module._fmt

    def exploding_fmt(x):
        calls["n"] += 1
        if calls["n"] > 30:  # a few lines are already in the temporary file
            raise ValueError("cannot format this number")
        return real_fmt(x)

    monkeypatch.setattr(trajectory_module, "_fmt", exploding_fmt)
    with pytest.raises(ValueError, match="cannot format"):
        write_tum(path, random_trajectory(10, seed=4))
    assert path.read_bytes() == before
    assert leftovers(tmp_path, {"est.txt"}) == []


def test_atomic_write_bytes_creates_parents_and_keeps_mode(tmp_path):
    path = atomic_write_bytes(tmp_path / "a" / "b" / "c.bin", b"\x00\x01")
    assert path.read_bytes() == b"\x00\x01"
    os.chmod(path, 0o640)
    atomic_write_bytes(path, [b"x", b"y"])
    assert path.read_bytes() == b"xy" and stat.S_IMODE(path.stat().st_mode) == 0o640
    fresh = atomic_write_text(tmp_path / "fresh.txt", "hi")
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(fresh.stat().st_mode) == 0o666 & ~mask


def test_output_folder_that_cannot_exist_raises_output_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("I am a file")
    with pytest.raises(OutputError) as e:
        write_tum(blocker / "sub" / "est.txt", random_trajectory(3))
    assert str(blocker) in str(e.value)
    with pytest.raises(OutputError):
        atomic_write_text(tmp_path, "a folder cannot be replaced by a file")
    with pytest.raises(OutputError):
        with atomic_dir(blocker):
            pass


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root can write to read-only folders")
def test_read_only_folder_raises_output_error(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(OutputError) as e:
            write_kitti(folder / "07.txt", random_trajectory(3))
        assert str(folder) in str(e.value)
    finally:
        folder.chmod(0o700)


def test_atomic_dir_replaces_folder_or_keeps_the_old_one(tmp_path):
    out = tmp_path / "run"
    with atomic_dir(out) as d:
        assert d != out and d.parent == tmp_path
        (d / "a.txt").write_text("first")
    assert (out / "a.txt").read_text() == "first"
    for overwrite in (False, True):  # a folder slamkit did not write (no marker) is never replaced (issue 50)
        with pytest.raises(OutputError, match="not a slamkit run"):
            with atomic_dir(out, overwrite=overwrite) as d:
                (d / "b.txt").write_text("second")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]
    (out / "a.txt").unlink()
    with atomic_dir(out) as d:  # a run folder: its manifest lists what it wrote
        (d / "a.txt").write_text("first")
        write_manifest(d)
    with atomic_dir(out, overwrite=True) as d:
        (d / "b.txt").write_text("second")
        write_manifest(d)
    assert sorted(p.name for p in out.iterdir()) == [".slamkit-run", "b.txt"]
    with pytest.raises(KeyError):
        with atomic_dir(out, overwrite=True) as d:
            (d / "c.txt").write_text("third")
            raise KeyError("boom")
    assert sorted(p.name for p in out.iterdir()) == [".slamkit-run", "b.txt"]
    assert leftovers(tmp_path, {"run"}) == []


# ------------------------------------------------------------------------------------------ fuzzing

TOKENS = ["0", "1", "-1", "0.5", "1e3", "1e400", "nan", "-inf", "x", "", "#", ",", "0 0 0 1", "1.0001",
          "\t", "1305031098.6659", "\u00e9", "0x10", "1_0", "--1"]
token_lines = st.lists(st.lists(st.sampled_from(TOKENS), min_size=0, max_size=14).map(" ".join), max_size=8)
texts = st.one_of(st.text(max_size=300), token_lines.map("\n".join),
                  st.binary(max_size=200).map(lambda b: b.decode("latin-1")))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=texts)
def test_fuzz_readers_return_a_trajectory_or_a_slamkit_error(text):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "fuzz.txt"
        path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
        for reader in (read_tum, read_kitti, read_trajectory):
            try:
                traj = reader(path)
            except SlamkitError:
                continue
            assert isinstance(traj, Trajectory)
            assert np.isfinite(traj.poses).all() and np.all(np.diff(traj.timestamps) > 0)
