"""Issue 40, the output side: foreign formats recognised (a KITTI pose file is paired by frame index, a device
is not read to the end), only what slamkit made is replaced (temporaries, locks and reports carry its marker;
eval writes only into a run folder or --out; device nodes and FIFOs are never replaced; the Python API checks
as the CLI does), export checks the source still holds the frames it posed, and the exit codes say what
happened (a run that posed nothing, a signal while starting).

Every case uses real files: a KITTI pose file (the real one of ../shared/data when present, else one written by
slamkit from a rendered sequence), a foreign results folder with a report.md and plots/, user files named like
slamkit's temporaries, a FIFO and /dev/zero, an image folder changed after the run.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import pycolmap
import pytest

import slamkit
from slamkit.cli import main
from slamkit.config import SlamConfig
from slamkit.errors import FormatError, OutputError, SlamkitError
from slamkit.eval.report import evaluate_run
from slamkit.exporter import export
from slamkit.exporter.runfolder import load_run
from slamkit.io import atomic_write_text, write_kitti, write_tum
from slamkit.io.run import save_run
from slamkit.io.run_dir import check_output
from slamkit.io.trajectory import MAX_TEXT_BYTES
from slamkit.runner import EXIT_NOTHING_POSED, EXIT_POOR_MATCH, run_to_folder
from slamkit.sources.synthetic import synthetic_source, write_tum_sequence

from conftest import image_folder_run, shared_data

pycolmap.logging.minloglevel = 2
ROOT = Path(__file__).resolve().parents[1]
SPEC = "synthetic:handheld?frames=40"


def _digest(folder: Path) -> dict:
    """Path -> (kind, SHA-256) of everything below ``folder``: equal before and after means nothing changed."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        out[rel] = ("dir", "") if p.is_dir() else ("file", hashlib.sha256(p.read_bytes()).hexdigest())
    return out


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "slamkit.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})


@pytest.fixture(scope="module")
def skip_run(tmp_path_factory) -> Path:
    """A run of every 2nd frame of a 40-frame rendered sequence (source frames 0, 2, 4, ...)."""
    out = tmp_path_factory.mktemp("runs") / "skip2"
    outcome = run_to_folder(SPEC, out, SlamConfig().with_overrides(frame_skip=2, init_frames=10), evaluate_ate=False)
    assert outcome.exit_code == 0 and outcome.summary["frames_posed"] >= 10, outcome.message
    return out


# ----------------------------------------------------------------------------------------------- rule 3: KITTI
def test_a_kitti_pose_file_is_paired_by_the_source_frame_index(tmp_path, skip_run, capsys):
    """The sequence's ground truth as KITTI's own pose file (one line per source frame, no time): with frame skip
    2 the run's frame k is source frame 2k, and the ATE equals the one against the run's own TUM ground truth."""
    kitti = tmp_path / "poses.txt"
    write_kitti(kitti, synthetic_source("handheld", frames=40).ground_truth())
    assert main(["eval", str(skip_run), "--json-only"]) == 0
    reference = json.loads(capsys.readouterr().out)
    assert main(["eval", str(skip_run), "--gt", str(kitti), "--json-only"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert result["pairing"] == "frame index" and "paired by frame index" in captured.err
    assert result["matched"] == reference["matched"] == json.loads((skip_run / "summary.json").read_text())[
        "frames_posed"]
    assert result["ate"]["rmse"] == pytest.approx(reference["ate"]["rmse"], rel=1e-9, abs=1e-12)
    # the report (run folder) pairs the same way and says so
    res = evaluate_run(skip_run, gt=kitti, plots=False, map_view=False)
    assert res["all_frames"]["ate"]["rmse"] == pytest.approx(reference["ate"]["rmse"], rel=1e-9, abs=1e-12)
    assert "paired by frame index" in (skip_run / "report.md").read_text()


def test_a_kitti_pose_file_without_the_runs_frame_list_is_refused_with_the_reason(tmp_path, skip_run, capsys):
    kitti = tmp_path / "poses.txt"
    write_kitti(kitti, synthetic_source("handheld", frames=40).ground_truth())
    loose = tmp_path / "estimate.txt"  # the trajectory outside its run folder: no frame ids
    shutil.copy(skip_run / "trajectory_tum.txt", loose)
    assert main(["eval", str(loose), "--gt", str(kitti)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "a KITTI pose file" in line and "cannot be paired by index" in line and "slamkit eval RUN" in line
    # the run's own KITTI file holds its posed frames only: not line by line against every frame
    assert main(["eval", str(skip_run / "trajectory_kitti.txt"), "--gt", str(kitti)]) == 2
    assert "lines pair only when both hold every frame" in _one_line(capsys.readouterr().err)


def test_real_kitti_07_poses_give_the_same_ate_as_its_tum_ground_truth(tmp_path, capsys):
    """KITTI 07 at every 3rd frame (source frames 0, 3, ..., 57) against the real poses/07.txt."""
    kitti = shared_data("kitti-odometry")
    run = tmp_path / "k07"
    outcome = run_to_folder(str(kitti / "sequences" / "07"), run,
                            SlamConfig().with_overrides(max_frames=20, frame_skip=3), evaluate_ate=False)
    if outcome.summary["frames_posed"] < 3:
        pytest.skip(f"KITTI 07 at every 3rd frame posed {outcome.summary['frames_posed']} frames: nothing to pair")
    assert main(["eval", str(run), "--json-only"]) == 0
    reference = json.loads(capsys.readouterr().out)
    assert main(["eval", str(run), "--gt", str(kitti / "poses" / "07.txt"), "--json-only"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert "(160 poses, 12 values a line, no timestamps): paired by frame index" in captured.err
    assert result["matched"] == reference["matched"] == outcome.summary["frames_posed"]
    assert result["ate"]["rmse"] == pytest.approx(reference["ate"]["rmse"], rel=1e-9)


def test_eval_warns_and_exits_non_zero_when_less_than_half_is_matched(tmp_path, capsys):
    gt = synthetic_source("handheld", frames=30).ground_truth()
    write_tum(tmp_path / "gt.txt", gt.subset(slice(0, 12)))  # ground truth of the first 12 frames only
    write_tum(tmp_path / "est.txt", gt)
    assert main(["eval", str(tmp_path / "est.txt"), "--gt", str(tmp_path / "gt.txt")]) == EXIT_POOR_MATCH
    captured = capsys.readouterr()
    assert json.loads(captured.out)["matched"] == 12
    warning = _one_line(captured.err)
    assert "only 12 of 30 poses" in warning and "not a measure of the run" in warning
    write_tum(tmp_path / "gt.txt", gt.subset(slice(0, 15)))  # exactly half: no warning
    assert main(["eval", str(tmp_path / "est.txt"), "--gt", str(tmp_path / "gt.txt")]) == 0
    assert capsys.readouterr().err == ""


def test_a_device_or_huge_file_as_ground_truth_is_refused_without_reading_it(tmp_path, capsys):
    est = tmp_path / "est.txt"
    write_tum(est, synthetic_source("handheld", frames=10).ground_truth())
    assert main(["eval", str(est), "--gt", "/dev/zero"]) == 2
    assert "/dev/zero:1: is not UTF-8 text (a NUL byte" in _one_line(capsys.readouterr().err)
    huge = tmp_path / "huge.txt"
    with open(huge, "wb") as f:  # sparse: no disk used, and it must not be read
        f.truncate(MAX_TEXT_BYTES + 1)
    assert main(["eval", str(est), "--gt", str(huge)]) == 2
    assert "is more than a trajectory file holds" in _one_line(capsys.readouterr().err)
    big = tmp_path / "big.txt"  # text without NUL, through a pipe: read up to the limit, then refused
    writer = subprocess.Popen(["sh", "-c", f"yes '1 0 0 0 0 0 0 1' | head -c {MAX_TEXT_BYTES + 2**20}"],
                              stdout=subprocess.PIPE)
    try:
        with pytest.raises(FormatError, match="sent more than that"):
            slamkit.read_trajectory(f"/dev/fd/{writer.stdout.fileno()}")
    finally:
        writer.kill()
        writer.wait()
    assert not big.exists()


# ----------------------------------------------------------------------------------------------- rule 4: ownership
def test_eval_never_writes_into_a_folder_that_is_not_a_run(tmp_path, capsys):
    """Another tool's results folder (trajectory files, its own report.md and plots/): eval refuses to write
    there; with --out the report goes where --out says, and the folder is unchanged."""
    theirs = tmp_path / "orbslam_results"
    theirs.mkdir()
    gt = synthetic_source("handheld", frames=30).ground_truth()
    write_tum(theirs / "trajectory_tum.txt", gt)
    write_tum(theirs / "groundtruth_tum.txt", gt)
    (theirs / "report.md").write_text("# my report\n")
    (theirs / "plots").mkdir()
    (theirs / "plots" / "trajectory.png").write_bytes(b"my figure")
    before = _digest(theirs)
    assert main(["eval", str(theirs), "--no-map-view"]) == 2
    assert "not a slamkit run folder" in _one_line(capsys.readouterr().err)
    assert _digest(theirs) == before
    with pytest.raises(OutputError, match="not a slamkit run folder"):
        evaluate_run(theirs, map_view=False)
    report = tmp_path / "report"
    assert main(["eval", str(theirs), "--no-map-view", "--out", str(report)]) == 0
    assert _digest(theirs) == before
    assert (report / "report.md").is_file() and (report / "plots" / "trajectory.png").stat().st_size > 10_000
    assert main(["eval", str(theirs), "--no-map-view", "--out", str(report)]) == 0  # its own report: replaced
    assert main(["eval", str(theirs), "--no-map-view", "--out", str(theirs / "plots")]) == 2  # theirs: never
    assert _digest(theirs) == before


def test_a_report_file_slamkit_did_not_write_is_kept_in_a_run_folder(tmp_path, skip_run, capsys):
    run = tmp_path / "run"
    shutil.copytree(skip_run, run)
    assert main(["eval", str(run), "--no-map-view"]) == 0  # its own report: written, and again
    assert main(["eval", str(run), "--no-map-view"]) == 0
    capsys.readouterr()
    (run / "report.md").write_text("# the user's notes\n")
    assert main(["eval", str(run), "--no-map-view"]) == 2
    assert "report.md: not a report slamkit wrote" in _one_line(capsys.readouterr().err)
    assert (run / "report.md").read_text() == "# the user's notes\n"
    (run / "report.md").unlink()
    (run / "plots" / "mine.png").write_bytes(b"user")
    assert main(["eval", str(run), "--no-map-view"]) == 2
    assert "mine.png, which slamkit eval did not write" in _one_line(capsys.readouterr().err)
    assert (run / "plots" / "mine.png").read_bytes() == b"user" and not (run / "report.md").exists()


def test_user_files_named_like_temporaries_and_locks_are_never_touched(tmp_path, capsys):
    out = tmp_path / "out"
    (out / ".victim.mine.tmp").mkdir(parents=True)
    (out / ".victim.mine.tmp" / "data.bin").write_bytes(b"mine")
    (out / ".victim.backup.old" / "victim").mkdir(parents=True)
    (out / ".victim.backup.old" / "victim" / "thesis.tex").write_text("important")
    (out / ".victim.lock").write_text("my lock notes\n")
    before = _digest(out)
    assert main(["run", SPEC, "--max-frames", "12", "--out", str(out / "victim"), "-q"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert ".victim.lock exists and is not a slamkit lock" in line and "nothing was written" in line
    assert _digest(out) == before
    # without the lock file in the way the run goes ahead, and still leaves the look-alikes alone
    (out / ".victim.lock").unlink()
    before = _digest(out)
    assert main(["run", SPEC, "--max-frames", "12", "--init-frames", "6", "--out", str(out / "victim"), "-q"]) in (
        0, EXIT_NOTHING_POSED)
    after = _digest(out)
    assert {k: v for k, v in after.items() if not k.startswith("victim")} == before
    assert sorted(p.name for p in out.iterdir()) == [".victim.backup.old", ".victim.mine.tmp", "victim"]


def test_a_fifo_device_or_symlink_is_never_replaced_by_a_file(tmp_path, capsys):
    src = write_tum_sequence(synthetic_source("handheld", frames=4), tmp_path / "rgbd_dataset_freiburg3_x")
    fifo = tmp_path / "gt.fifo"
    os.mkfifo(fifo)
    assert main(["gt", str(src), str(fifo), "--overwrite"]) == 2
    assert "is a FIFO; slamkit replaces only regular files" in _one_line(capsys.readouterr().err)
    assert fifo.exists() and not fifo.is_file()
    link = tmp_path / "link.txt"
    (tmp_path / "target.txt").write_text("mine")
    link.symlink_to(tmp_path / "target.txt")
    assert main(["gt", str(src), str(link), "--overwrite"]) == 2
    assert "is a symbolic link" in _one_line(capsys.readouterr().err)
    assert link.is_symlink() and (tmp_path / "target.txt").read_text() == "mine"
    for device in ("/dev/null", "/dev/zero"):  # checked before anything is written: nothing is ever tried
        with pytest.raises(OutputError, match="is a device node"):
            check_output(device, "file", overwrite=True, flag="OUT")
    with pytest.raises(OutputError, match="is a FIFO"):
        atomic_write_text(fifo, "x")


def test_the_python_api_refuses_a_folder_inside_the_source_as_the_cli_does(tmp_path, capsys):
    tum = write_tum_sequence(synthetic_source("handheld", frames=6), tmp_path / "rgbd_dataset_freiburg3_x")
    (tum / "depth").mkdir()
    (tum / "depth" / "0.png").write_bytes(b"depth")
    slam = slamkit.Slam(slamkit.open_source(str(tum)), SlamConfig())
    before = _digest(tum)
    with pytest.raises(OutputError, match="is inside the source"):
        save_run(slam, tum / "depth", overwrite=True)
    assert main(["run", str(tum), "--out", str(tum / "depth"), "--overwrite"]) == 2
    assert "is inside the source" in _one_line(capsys.readouterr().err)
    assert _digest(tum) == before


# ----------------------------------------------------------------------------------------------- rule 5: export
def test_export_refuses_when_the_source_changed_after_the_run(tmp_path):
    """The run's images are re-read by export: two swapped files, or one re-encoded at another size, are named
    (frame and file) instead of exporting the wrong images under the run's poses."""
    src, folder, run, outcome = image_folder_run(tmp_path, "sideways", 20, init_frames=8)
    assert outcome.exit_code == 0
    export(run, tmp_path / "ok", frames="all")  # unchanged: exported
    posed = [f.index for f in load_run(run).frames]  # frame k is the k-th file (no frame skip)
    files = sorted(folder.glob("*.png"))
    a, b = files[posed[1]], files[posed[2]]
    a_bytes, b_bytes = a.read_bytes(), b.read_bytes()
    a.write_bytes(b_bytes)
    b.write_bytes(a_bytes)
    with pytest.raises(SlamkitError, match=rf"frame {posed[1]} \(dataset frame {posed[1]}\) is not the image the "
                                           rf"run posed: {a}.*SHA-256 differs") as e:
        export(run, tmp_path / "ds", frames="all")
    assert "\n" not in str(e.value) and not (tmp_path / "ds").exists()
    a.write_bytes(a_bytes)
    b.write_bytes(b_bytes)
    first = files[posed[0]]
    cv2.imwrite(str(first), cv2.resize(cv2.imread(str(first)), (320, 240)))
    with pytest.raises(SlamkitError, match=rf"frame {posed[0]} .* is 320x240 pixels, the run saw 640x480"):
        export(run, tmp_path / "ds", frames="all")
    assert not (tmp_path / "ds").exists()


# ----------------------------------------------------------------------------------------------- rule 7: exit codes
def test_help_documents_the_exit_codes(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "3 run: ran but posed no frame (no map)" in text and "128+N stopped by signal N (130 Ctrl-C" in text
    assert "4 eval: less than half of the estimate matched" in text


@pytest.mark.parametrize("when", [1, 300, 1000, "started"])
def test_ctrl_c_while_starting_is_one_line_and_the_signal_code(tmp_path, when):
    """SIGINT at several moments of start-up: after the ``when``-th module imported once slamkit's own code runs
    (``python -X importtime`` prints a line per import: the moment is the same however busy the machine is), or
    just after the run's first line. One line and the signal's exit code, never a traceback, nothing written."""
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-X", "importtime", "-m", "slamkit.cli", "run", SPEC, "--out", str(out),
                             "-q"], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        imports, sent, seen = -1, False, []
        for line in proc.stderr:  # import lines, then slamkit's own
            seen.append(line)
            if imports < 0 and line.rstrip().endswith(" slamkit.interrupt"):
                imports = 0  # slamkit's guard is installed right after this import (slamkit/__init__.py)
            elif imports >= 0 and line.startswith("import time:"):
                imports += 1
            if (imports == when or (when == "started" and "frames to process" in line)
                    or (isinstance(when, int) and imports >= 0 and not line.startswith("import time:"))):
                proc.send_signal(signal.SIGINT)
                sent = True
                break
        assert sent, "".join(seen[-5:])
        rest = proc.stderr.read()  # to the end: the process exits
        proc.wait(timeout=300)
    finally:
        proc.kill()
    err = [x for x in rest.splitlines() if not x.startswith("import time:")]
    text = "\n".join(err)
    assert proc.returncode in (130, -signal.SIGINT), text  # 130 from slamkit, or the SIGINT Python re-raises
    assert "Traceback" not in text, text
    if when == "started" and "interrupted after frame" in text:  # a quick machine: frames were done, and saved
        assert proc.returncode == 130 and (out / "summary.json").is_file(), text
        return
    assert len(err) == 1 and err[0].startswith("slamkit: SIGINT") and not out.exists(), text
    if when == 1:
        assert err[0] == "slamkit: SIGINT: stopped while starting; nothing was read or written"
    if when == "started":
        assert err[0].endswith("before the first frame; " + f"{out} was left as it was"), text


def test_ablate_scheduler_garbage_is_one_line(tmp_path, capsys):
    for value, why in (("garbage", "expected HOST:PORT"), ("tcp://host:99999", "not a number from 1 to 65535"),
                       ("http://host:8786", "scheme 'http'")):
        assert main(["ablate", "default", "--scheduler", value, "--out", str(tmp_path / "sweep")]) == 2
        line = _one_line(capsys.readouterr().err)
        assert "--scheduler" in line and why in line, line
    assert not (tmp_path / "sweep").exists()
