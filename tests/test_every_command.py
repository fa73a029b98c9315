"""Issue 28: every command that writes follows one set of output rules, every user error is one line naming
what is at fault, pipes are read once and never block forever, and a signal stops every command cleanly.

Each kind of bad input or fault is a row of a table (or a property over many values); each row asserts the
exit code, the one-line message and that nothing was lost (the bytes of every file that was there before).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings, strategies as st

import slamkit
from slamkit.cli import main
from slamkit.config import SlamConfig
from slamkit.errors import ArgumentTypeError, CalibrationError, OutputError, SlamkitError
from slamkit.exporter import export
from slamkit.io import read_tum
from slamkit.io.run_dir import check_output, out_dir_lock
from slamkit.io.trajectory import PIPE_TIMEOUT
from slamkit.runner import EXIT_NOTHING_POSED, run_to_folder
from slamkit.sources.synthetic import synthetic_source, write_tum_sequence

from conftest import image_folder_run

pycolmap.logging.minloglevel = 2

ROOT = Path(__file__).resolve().parents[1]


def _digest(folder: Path) -> dict:
    """Path -> SHA-256 of every file below ``folder``: equal before and after means nothing was lost."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _cli(*args: str, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "slamkit.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, **kw)


@pytest.fixture(scope="module")
def tum_source(tmp_path_factory) -> Path:
    """A TUM-layout dataset folder (6 synthetic frames, groundtruth.txt, camera.json): a source with files."""
    return _tum(tmp_path_factory.mktemp("src"))


def _tum(root: Path, frames: int = 6) -> Path:
    """A TUM folder whose name says freiburg3 (so it opens without --camera)."""
    return write_tum_sequence(synthetic_source("handheld", frames=frames), root / "rgbd_dataset_freiburg3_synth")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    """A saved run (3 frames of the default sequence: no map, but a complete run folder with its manifest)."""
    out = tmp_path_factory.mktemp("runs") / "run"
    outcome = run_to_folder("default", out, SlamConfig().with_overrides(max_frames=3), evaluate_ate=False)
    assert outcome.saved and (out / ".slamkit-run").is_file()
    return out


# ----------------------------------------------------------------------------------------------- gt: never overwrites
GT_CASES = [
    # (name, OUT relative to the case's folder, extra args, expected message)
    ("a source's own file", "SRC/groundtruth.txt", [], "is inside the source"),
    ("a source's own file, --overwrite", "SRC/groundtruth.txt", ["--overwrite"], "is inside the source"),
    ("a run's trajectory", "RUN/trajectory_tum.txt", [], "is inside"),
    ("a run's trajectory, --overwrite", "RUN/trajectory_tum.txt", ["--overwrite"], "slamkit output"),
    ("a file inside a run's sparse/", "RUN/session/session.json", ["--overwrite"], "slamkit output"),
    ("an existing file", "mine.txt", [], "exists; nothing was written"),
    ("a folder", "folder", ["--overwrite"], "is a folder"),
    ("an empty path", "", [], "an empty path"),
    ("a 300-character name", "x" * 300, [], "more than the file system allows"),
]


@pytest.mark.parametrize("name, out, extra, message", GT_CASES, ids=[c[0] for c in GT_CASES])
def test_gt_never_overwrites_what_is_not_its_own(tmp_path, tum_source, run_folder, capsys, name, out, extra,
                                                 message):
    src = tmp_path / "SRC" / tum_source.name
    shutil.copytree(tum_source, src)
    run = tmp_path / "RUN"
    shutil.copytree(run_folder, run)
    (tmp_path / "mine.txt").write_text("my notes\n")
    (tmp_path / "folder").mkdir()
    before = _digest(tmp_path)
    target = "" if out == "" else str(tmp_path / out.replace("SRC", f"SRC/{tum_source.name}"))
    assert main(["gt", str(src), target, *extra]) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert _digest(tmp_path) == before  # nothing changed: the dataset still opens, the run still checks


def test_gt_writes_a_new_file_and_replaces_only_with_overwrite(tmp_path, tum_source, capsys):
    out = tmp_path / "gt.txt"
    assert main(["gt", str(tum_source), str(out)]) == 0
    first = out.read_bytes()
    assert len(read_tum(out)) == 6
    out.write_text(first.decode().replace("1.", "2.", 1))  # a trajectory slamkit wrote, changed
    assert main(["gt", str(tum_source), str(out), "--overwrite"]) == 0
    assert out.read_bytes() == first and not list(tmp_path.glob(".gt.txt*"))  # atomic: no temporary left
    out.write_text("changed\n")  # not a trajectory slamkit wrote: kept, even with --overwrite (issue 50)
    assert main(["gt", str(tum_source), str(out), "--overwrite"]) == 2
    assert "not a trajectory file slamkit wrote" in capsys.readouterr().err and out.read_text() == "changed\n"


def test_a_second_writer_of_one_output_fails_at_once(tmp_path, tum_source, run_folder, capsys):
    """One writer at a time for every kind of output: gt (a file), export (a folder), a run, a sweep; each
    under a lock another writer holds (here this process, as a concurrent command would)."""
    out = tmp_path / "gt.txt"
    with out_dir_lock(out, flag="OUT", what="file"):
        assert main(["gt", str(tum_source), str(out)]) == 2
    assert f"process {os.getpid()} is writing this file" in _one_line(capsys.readouterr().err)
    assert not out.exists()
    for args in (["export", str(run_folder), "--format", "colmap", "--out", str(tmp_path / "ds")],
                 ["run", "default", "--max-frames", "3", "--out", str(tmp_path / "ds")],
                 ["ablate", "default", "--grid", "init_frames=10", "--workers", "0", "--out", str(tmp_path / "ds")]):
        with out_dir_lock(tmp_path / "ds"):
            assert main([*args, "-q"]) == 2, args
        err = capsys.readouterr().err  # (ablate prints its plan first; the error is still one line)
        assert f"process {os.getpid()} is writing this" in err.strip().splitlines()[-1] and "Traceback" not in err
        assert not (tmp_path / "ds").exists()


# ----------------------------------------------------------------------------------------------- export, ablate, run
def test_export_never_writes_into_a_run_or_the_source(tmp_path, run_folder):
    run = tmp_path / "run"
    shutil.copytree(run_folder, run)
    before = _digest(run)
    for out in (run / "ds", run / "sparse", run / "session" / "x"):
        with pytest.raises(OutputError, match="slamkit output") as e:
            export(run, out)
        assert "\n" not in str(e.value)
    with pytest.raises(OutputError, match="would replace the run folder"):
        export(run, tmp_path)
    assert _digest(run) == before
    # the run is still a run: it can be replaced by a new run (no "not a slamkit run (ds)")
    check_output(run, "run")


def test_ablate_out_onto_a_run_or_a_users_folder_is_refused(tmp_path, run_folder, capsys):
    run = tmp_path / "run"
    shutil.copytree(run_folder, run)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    before = _digest(tmp_path)
    for out, message in ((run, "is not a slamkit sweep"), (run / "sweep", "slamkit output"),
                         (mine, "is not a slamkit sweep")):
        assert main(["ablate", "default", "--grid", "init_frames=10", "--out", str(out), "--workers", "0"]) == 2
        assert message in _one_line(capsys.readouterr().err)
    assert _digest(tmp_path) == before


def test_run_out_inside_another_run_is_refused(tmp_path, run_folder, capsys):
    run = tmp_path / "run"
    shutil.copytree(run_folder, run)
    before = _digest(run)
    assert main(["run", "default", "--max-frames", "3", "-q", "--out", str(run / "sub")]) == 2
    assert "slamkit output" in _one_line(capsys.readouterr().err)
    assert _digest(run) == before


# ----------------------------------------------------------------------------------------------- values and paths
def _image_folder(root: Path, camera_txt: str | None = None) -> Path:
    folder = root / "images"
    write_tum_sequence(synthetic_source("handheld", frames=3), root / "tum")
    folder.mkdir()
    for p in sorted((root / "tum" / "rgb").glob("*.png")):
        shutil.copy(p, folder / p.name)
    if camera_txt is not None:
        (folder / "camera.txt").write_text(camera_txt)
    return folder


VALUE_CASES = [
    # (name, args after `run SOURCE --out OUT`, expected message)
    ("focal 1e12", ["--camera", "1e12"], "is not a focal length of a"),
    ("focal 1e-3", ["--camera", "0.001"], "is not a focal length of a"),
    ("empty --camera", ["--camera", ""], "--camera: '' is empty"),
    ("blank --camera", ["--camera", "  "], "is empty"),
    ("feature count beyond a C int", ["--num-features", "99999999999"], "num_features must be between"),
    ("feature count too small", ["--num-features", "3"], "num_features must be between"),
]


@pytest.mark.parametrize("name, extra, message", VALUE_CASES, ids=[c[0] for c in VALUE_CASES])
def test_impossible_values_are_one_line_before_any_work(tmp_path, capsys, name, extra, message):
    folder = _image_folder(tmp_path)
    out = tmp_path / "out"
    assert main(["run", str(folder), "--out", str(out), "-q", *extra]) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert not out.exists()


def test_a_camera_txt_with_an_impossible_focal_is_named(tmp_path, capsys):
    folder = _image_folder(tmp_path, "1e12 1e12 320 240\n")
    assert main(["run", str(folder), "--out", str(tmp_path / "out"), "-q"]) == 2
    assert "is not a focal length of a 640x480 camera" in _one_line(capsys.readouterr().err)


@given(st.floats(min_value=1e-6, max_value=1e15, allow_nan=False))
@settings(max_examples=60, deadline=None)
def test_every_focal_is_accepted_exactly_when_it_is_sane(f):
    """Property: a focal length either builds a camera (field of view 1-170 degrees) or is one line naming it."""
    fov = 2 * np.degrees(np.arctan(320 / f))
    try:
        slamkit.Intrinsics(640, 480, f, f, 320, 240)
        assert 1 - 1e-9 <= fov <= 170 + 1e-9
    except CalibrationError as e:
        assert not 1 + 1e-6 <= fov <= 170 - 1e-6 and "fx=" in str(e) and "\n" not in str(e)


PATH_CASES = [
    ("/dev/null as the source", ["run", "/dev/null"], "is neither a folder nor a video file"),
    ("a symlink loop as the source", ["run", "LOOP"], "is a loop of symbolic links"),
    ("a broken symlink as the source", ["run", "BROKEN"], "which does not exist"),
    ("a 300-character --out", ["run", "default", "--max-frames", "3"], "more than the file system allows"),
]


@pytest.mark.parametrize("name, args, message", PATH_CASES, ids=[c[0] for c in PATH_CASES])
def test_paths_the_os_refuses_are_one_line(tmp_path, capsys, name, args, message):
    os.symlink(tmp_path / "LOOP2", tmp_path / "LOOP")
    os.symlink(tmp_path / "LOOP", tmp_path / "LOOP2")
    os.symlink(tmp_path / "gone", tmp_path / "BROKEN")
    args = [str(tmp_path / a) if a in ("LOOP", "BROKEN") else a for a in args]
    out = tmp_path / ("x" * 300 if "300" in name else "out")
    assert main([*args, "--out", str(out), "-q"]) == 2
    assert message in _one_line(capsys.readouterr().err)


# ----------------------------------------------------------------------------------------------- the Python API's types
API_CASES = [
    ("Slam(src, {})", lambda: slamkit.Slam("default", {}), "config: expected"),
    ("Slam(3)", lambda: slamkit.Slam(3), "source: expected"),
    ("SlamConfig(num_features='lots')", lambda: SlamConfig(num_features="lots"), "SlamConfig.num_features"),
    ("SlamConfig(tracker={...})", lambda: SlamConfig(tracker={"min_inliers": 3}), "SlamConfig.tracker:"),
    ("SlamConfig(prefetch=1)", lambda: SlamConfig(prefetch=1), "SlamConfig.prefetch"),
    ("SlamConfig(max_frames='10')", lambda: SlamConfig(max_frames="10"), "SlamConfig.max_frames"),
    ("ate('a', 'b')", lambda: slamkit.ate("a", "b"), "gt: expected"),
    ("evaluate(3, 4)", lambda: slamkit.evaluate(3, 4), "est: expected"),
]


@pytest.mark.parametrize("name, call, message", API_CASES, ids=[c[0] for c in API_CASES])
def test_wrong_types_through_the_python_api_are_a_type_error_naming_the_argument(name, call, message):
    with pytest.raises(TypeError, match=message) as e:
        call()
    assert isinstance(e.value, SlamkitError) and "\n" not in str(e.value)


@given(st.sampled_from(["num_features", "seed", "frame_skip", "thumbnail_width", "max_lost_frames"]),
       st.one_of(st.text(max_size=5), st.floats(allow_nan=False).filter(lambda x: not float(x).is_integer()),
                 st.lists(st.integers(), max_size=2), st.none(), st.booleans()))
@settings(max_examples=80, deadline=None)
def test_property_a_non_integer_for_an_int_field_names_the_field(field, value):
    with pytest.raises(ArgumentTypeError, match=f"SlamConfig.{field}: expected an int"):
        SlamConfig(**{field: value})


# ----------------------------------------------------------------------------------------------- pipes and FIFOs
@pytest.fixture(scope="module")
def trajectory(tmp_path_factory) -> tuple[Path, Path]:
    """(estimate, ground truth): a TUM ground truth of 30 poses and a scaled, shifted copy of it."""
    folder = tmp_path_factory.mktemp("traj")
    src = synthetic_source("handheld", frames=30)
    gt = src.ground_truth()
    slamkit.write_tum(folder / "gt.txt", gt)
    est = slamkit.Trajectory(gt.timestamps, gt.poses.copy())
    est.poses[:, :3, 3] = 2.0 * est.poses[:, :3, 3] + 1.0
    slamkit.write_tum(folder / "est.txt", est)
    return folder / "est.txt", folder / "gt.txt"


def test_ground_truth_from_a_pipe_is_read_once(trajectory):
    est, gt = trajectory
    r = _cli("eval", str(est), "--gt", "/dev/stdin", input=gt.read_text())
    assert r.returncode == 0, r.stderr
    import json

    result = json.loads(r.stdout)
    assert result["matched"] == 30 and result["ate"]["rmse"] < 1e-9  # a Sim(3) copy: exact


def test_a_fifo_with_no_writer_fails_instead_of_hanging(tmp_path, trajectory):
    fifo = tmp_path / "gt.fifo"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    r = _cli("eval", str(trajectory[0]), "--gt", str(fifo), timeout=PIPE_TIMEOUT + 60)
    assert r.returncode == 2 and "sent nothing" in _one_line(r.stderr)
    assert time.monotonic() - t0 < PIPE_TIMEOUT + 30


EVAL_CASES = [
    ("--gt missing", ["--gt", "nope.txt"], "nope.txt: does not exist (given as --gt)"),
    ("--gt a folder", ["--gt", "."], "is a folder"),
    ("--gt a symlink loop", ["--gt", "LOOP"], "is a loop of symbolic links (given as --gt)"),
    ("--gt empty", ["--gt", "EMPTY"], "has no poses"),
]


@pytest.mark.parametrize("name, extra, message", EVAL_CASES, ids=[c[0] for c in EVAL_CASES])
def test_eval_names_the_ground_truth_at_fault(tmp_path, trajectory, capsys, monkeypatch, name, extra, message):
    monkeypatch.chdir(tmp_path)
    os.symlink(tmp_path / "LOOP2", tmp_path / "LOOP")
    os.symlink(tmp_path / "LOOP", tmp_path / "LOOP2")
    (tmp_path / "EMPTY").write_text("# no poses\n")
    assert main(["eval", str(trajectory[0]), *extra]) == 2
    assert message in _one_line(capsys.readouterr().err)


# ----------------------------------------------------------------------------------------------- full disk
@pytest.fixture
def small_disk(tmp_path):
    """A 256 KB tmpfs (root only; skipped elsewhere), unmounted afterwards."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a small tmpfs needs root to mount")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


def test_a_full_disk_is_one_line_and_the_previous_output_is_intact(small_disk, tum_source, capsys):
    out = small_disk / "gt.txt"
    gt_src = _tum(small_disk.parent)
    assert main(["gt", str(gt_src), str(out)]) == 0
    before = out.read_bytes()
    filler = small_disk / "filler"
    free = shutil.disk_usage(small_disk).free
    filler.write_bytes(b"\0" * max(0, free - 256))
    assert main(["gt", str(gt_src), str(out), "--overwrite"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("slamkit: error: no space left on the disk of") and "is intact" in line, line
    assert out.read_bytes() == before and sorted(p.name for p in small_disk.iterdir()) == ["filler", "gt.txt"]


# ----------------------------------------------------------------------------------------------- signals
def test_ablate_with_workers_stops_within_seconds_on_sigterm(tmp_path):
    """SIGTERM to `slamkit ablate --workers 2`: the runs in flight are stopped (not waited for) and the last
    line says truthfully how many runs are kept."""
    out = tmp_path / "sweep"
    proc = subprocess.Popen([sys.executable, "-m", "slamkit.cli", "ablate", "default", "--grid",
                             "init_frames=10,12", "--repeats", "1", "--workers", "2",
                             "--out", str(out), "-q"], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (out / "sweep.json").exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(3)  # the workers have started their runs (each takes minutes)
        assert proc.poll() is None
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        stopped_in = time.monotonic() - t0
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert stopped_in < 15, stopped_in
    last = err.strip().splitlines()[-1]
    kept = len(list((out / "runs").glob("*.json")))
    assert f"{kept} of 2 runs are kept" in last and "Traceback" not in err, err


# ----------------------------------------------------------------------------------------------- a source that changed
def test_export_after_images_were_deleted_names_the_source_and_the_counts(tmp_path):
    """The run's image folder lost frames after the run: the export says so (counts, folder), not "frame 10 is
    not frame 30"."""
    src, folder, run, outcome = image_folder_run(tmp_path, "handheld", 30, init_frames=10)
    assert outcome.saved
    for p in sorted(folder.glob("*.png"))[:10]:
        p.unlink()
    with pytest.raises(SlamkitError, match=r"has 20 frames now but had 30 when the run was made") as e:
        export(run, tmp_path / "ds", frames="all")
    assert str(folder) in str(e.value) and "\n" not in str(e.value)
    assert not (tmp_path / "ds").exists()


def test_a_featureless_sequence_says_why_and_eval_says_nothing_was_posed(tmp_path, trajectory, capsys):
    folder = tmp_path / "black"
    folder.mkdir()
    import cv2

    for i in range(12):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.zeros((240, 320, 3), np.uint8))
    run = tmp_path / "run"
    assert main(["run", str(folder), "--camera", "300", "--out", str(run), "-q"]) == EXIT_NOTHING_POSED  # no map
    err = capsys.readouterr().err
    assert "all 12 frames so far had fewer than 8 keypoints (featureless" in err, err
    assert f"no frame was posed, so no map was made (exit code {EXIT_NOTHING_POSED})" in err, err
    for extra in ([], ["--json-only"]):
        assert main(["eval", str(run), "--gt", str(trajectory[1]), *extra]) == 2
        assert "the run posed no frame, so there is nothing to evaluate" in _one_line(capsys.readouterr().err)


OLD_SESSION_EDITS = [
    ("cursor removed", lambda m: m["state"].pop("_cursor"), "entry '_cursor' is missing"),
    ("config removed", lambda m: m.pop("config"), "entry 'config' is missing"),
    ("records emptied", lambda m: m.__setitem__("records", {}), "not a session this slamkit can read"),
    ("a field of the wrong type", lambda m: m.__setitem__("config", {"num_features": "lots"}), "num_features"),
]


@pytest.mark.parametrize("name, edit, message", OLD_SESSION_EDITS, ids=[c[0] for c in OLD_SESSION_EDITS])
def test_a_hand_edited_session_without_manifest_is_one_line(tmp_path, run_folder, capsys, name, edit, message):
    """A session of the format before manifests (no .slamkit-run, no .slamkit-session.json) edited by hand:
    resuming it is one line naming the file, never a KeyError from deep inside."""
    import json

    run = tmp_path / "run"
    shutil.copytree(run_folder, run)
    (run / ".slamkit-run").unlink()
    (run / "session" / ".slamkit-session.json").unlink()
    meta = json.loads((run / "session" / "session.json").read_text())
    edit(meta)
    (run / "session" / "session.json").write_text(json.dumps(meta))
    assert main(["run", "default", "--max-frames", "5", "--out", str(run), "--resume", "-q"]) == 2
    assert message in _one_line(capsys.readouterr().err)


LONG = "a" * 300
LONG_INPUT_COMMANDS = [
    ["run", "LONG", "--out", "OUT", "-q"],
    ["eval", "LONG"],
    ["eval", "RUN", "--gt", "LONG"],
    ["export", "LONG", "--format", "colmap", "--out", "OUT", "-q"],
    ["gt", "LONG", "OUT.txt"],
]


@pytest.mark.parametrize("args", LONG_INPUT_COMMANDS, ids=[" ".join(a[:2]) for a in LONG_INPUT_COMMANDS])
def test_an_input_path_the_os_refuses_is_one_line_in_every_command(tmp_path, run_folder, capsys, args):
    args = [str(tmp_path / LONG) if a == "LONG" else str(run_folder) if a == "RUN" else
            str(tmp_path / a) if a.startswith("OUT") else a for a in args]
    assert main(args) == 2
    line = _one_line(capsys.readouterr().err)
    assert "too long" in line and LONG[:50] in line, line
    assert sorted(os.listdir(tmp_path)) == []
