"""Never lose a user's data (issue 22): ``--out`` checks before any work, the run-folder lock, and SIGTERM /
SIGHUP / repeated signals handled like Ctrl-C. Signals and locks are tested on real processes.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import pytest

import slamkit.cli
from slamkit.cli import main
from slamkit.config import SlamConfig
from slamkit.errors import OutputError
from slamkit.interrupt import StopRequest
from slamkit.io.atomic import atomic_dir
from slamkit.io.run import save_run
from slamkit.io.run_dir import RUN_MARKER, mark_temporary, out_dir_lock, remove_stale_temporaries, save_id
from slamkit.io.saved import check_run, check_session
from slamkit.pipeline import Slam
from slamkit.runner import EXIT_NOTHING_POSED
from slamkit.sources import open_source

REPO = Path(__file__).parents[1]
RUN = ["run", "default", "-q"]
RAN = (0, EXIT_NOTHING_POSED)
"""Exit codes of a run that went through its frames and saved: 5 frames make a map or none (exit 3); what these
tests check is the --out rules."""


def _digest(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _leftovers(parent: Path, name: str) -> list[Path]:
    return sorted(parent.glob(f".{name}.*"))


@pytest.fixture(scope="module")
def frames_folder(tmp_path_factory) -> Path:
    """12 frames of the default sequence as PNG files (an image-folder source)."""
    folder = tmp_path_factory.mktemp("inputs") / "imgs"
    folder.mkdir()
    src = open_source("default", max_frames=12)
    for i in range(len(src)):
        cv2.imwrite(str(folder / f"{i:04d}.png"), src[i].color[:, :, ::-1])
    return folder


# ----------------------------------------------------------------------------------------------- --out rules
def test_a_folder_of_other_files_is_refused_before_any_work(tmp_path, capsys):
    d = tmp_path / "d"
    d.mkdir()
    (d / "thesis.tex").write_text("important")
    assert main([*RUN, "--max-frames", "30", "--out", str(d)]) == 2
    err = capsys.readouterr().err
    assert f"--out {d}: folder is not empty and is not a slamkit run (thesis.tex)" in err and "--overwrite" in err
    assert "frames to process" not in err and len(err.strip().splitlines()) == 1   # refused before any frame
    assert sorted(p.name for p in d.iterdir()) == ["thesis.tex"] and (d / "thesis.tex").read_text() == "important"
    # a slamkit run folder that the user added a file to is not slamkit's alone any more: refused too
    run = tmp_path / "run"
    assert main([*RUN, "--max-frames", "5", "--init-frames", "2", "--out", str(run)]) in RAN
    (run / "notes.txt").write_text("mine")
    assert main([*RUN, "--max-frames", "5", "--init-frames", "2", "--out", str(run)]) == 2
    assert "(notes.txt)" in capsys.readouterr().err and (run / "notes.txt").read_text() == "mine"
    # --overwrite does not make them slamkit's (issue 50): still refused, nothing deleted
    assert main([*RUN, "--max-frames", "5", "--init-frames", "2", "--out", str(d), "--overwrite"]) == 2
    assert "even with --overwrite" in capsys.readouterr().err and (d / "thesis.tex").read_text() == "important"


def test_a_slamkit_run_folder_is_replaced_and_an_empty_folder_used(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()  # empty: fine
    assert main([*RUN, "--max-frames", "5", "--init-frames", "2", "--out", str(run)]) in RAN
    first = save_id(run)
    assert main([*RUN, "--max-frames", "6", "--init-frames", "2", "--out", str(run)]) in RAN
    assert save_id(run) not in (None, first) and json.loads((run / "summary.json").read_text())["frames"] == 6
    # a run folder saved before the marker existed (no .slamkit-run) is recognised by its session
    (run / RUN_MARKER).unlink()
    assert main([*RUN, "--max-frames", "5", "--init-frames", "2", "--out", str(run)]) in RAN
    assert _leftovers(tmp_path, "run") == []


def test_python_api_refuses_a_foreign_folder_even_with_overwrite(tmp_path):
    slam = Slam("default", SlamConfig().with_overrides(max_frames=4, init_frames=2))
    slam.run()
    d = tmp_path / "d"
    d.mkdir()
    (d / "data.csv").write_text("1,2,3")
    with pytest.raises(OutputError, match=r"not a slamkit run \(data.csv\).*even with --overwrite"):
        slam.save(d)
    with pytest.raises(OutputError, match=r"not a slamkit run \(data.csv\)"):
        save_run(slam, d, overwrite=True)
    assert (d / "data.csv").read_text() == "1,2,3"
    with pytest.raises(OutputError, match="not a slamkit run"):  # defence in depth: atomic_dir alone refuses too
        with atomic_dir(d, overwrite=True):
            pass
    assert sorted(p.name for p in d.iterdir()) == ["data.csv"]
    (d / "data.csv").unlink()  # the user's decision, not slamkit's
    save_run(slam, d)
    assert (d / "summary.json").is_file()
    slam.save(d)  # now a slamkit run: replaced without asking
    check_run(d)


@pytest.mark.parametrize("where", ["same", "inside", "containing", "symlink"])
def test_out_equal_to_inside_or_around_the_source_is_refused(frames_folder, tmp_path, capsys, where):
    src = tmp_path / "imgs"
    src.mkdir()
    for p in frames_folder.iterdir():
        (src / p.name).write_bytes(p.read_bytes())
    before = _digest(tmp_path)
    out = {"same": src, "inside": src / "run", "containing": tmp_path, "symlink": tmp_path / "link"}[where]
    if where == "symlink":
        out.symlink_to(src, target_is_directory=True)
        before = _digest(tmp_path)
    code = main([*RUN[:1], str(src), "--camera", "500", "--overwrite", "-q", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and f"--out {out}:" in err and "source" in err, err
    assert _digest(tmp_path) == before  # the input images are untouched
    # the Python API refuses it too
    slam = Slam(str(src), SlamConfig().with_overrides(camera="500", max_frames=2))
    with pytest.raises(OutputError, match="source"):
        slam.save(out)
    assert _digest(tmp_path) == before


@pytest.mark.parametrize("out, message", [
    ("", "--out '': an empty path"),
    (".", "is the current folder"),
    ("/proc/slamkit-test/run", "cannot"),
    ("FILE", "exists and is not a folder"),
    ("FILE/run", "cannot"),
])
def test_an_unwritable_out_fails_before_the_first_frame(tmp_path, capsys, monkeypatch, out, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "FILE").write_text("a file")
    assert main([*RUN, "--max-frames", "30", "--out", out]) == 2
    err = capsys.readouterr().err
    assert message in err and "frames to process" not in err and len(err.strip().splitlines()) == 1, err
    assert (tmp_path / "FILE").read_text() == "a file"


# ----------------------------------------------------------------------------------------------- lock
def test_lock_is_exclusive_and_names_the_holder(tmp_path):
    out = tmp_path / "run"
    with out_dir_lock(out) as lock:
        assert lock == tmp_path / ".run.lock"
        assert lock.read_text().split() == ["slamkit-lock", str(os.getpid())]  # slamkit's marker, the holder
        with pytest.raises(OutputError, match=rf"process {os.getpid()} is writing this run folder"):
            with out_dir_lock(out):
                pass
    assert not lock.exists()  # removed when released
    lock.write_text("slamkit-lock    999999999\n")  # left by a killed process: flock is gone with it, no block
    with out_dir_lock(out):
        pass
    assert not lock.exists()


def test_stale_temporaries_are_removed_and_a_moved_run_put_back(tmp_path):
    out = tmp_path / "run"
    (tmp_path / ".run.abc123.tmp" / "sparse").mkdir(parents=True)  # a killed save
    mark_temporary(tmp_path / ".run.abc123.tmp", out)
    old = tmp_path / ".run.xyz.old" / "run"                         # killed between the two renames
    old.mkdir(parents=True)
    mark_temporary(old.parent, out)
    (old / "summary.json").write_text("{}")
    remove_stale_temporaries(out)
    assert (out / "summary.json").read_text() == "{}" and _leftovers(tmp_path, "run") == []


def _default_signals() -> None:
    """In the child, before exec: SIGINT and SIGHUP as in a terminal, even when the tests were started by
    ``nohup`` or a non-interactive shell (which leave them ignored, and an ignored SIGHUP stays ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


class Proc:
    """A ``python -m slamkit.cli`` process whose output lines are collected by threads (never blocks)."""

    def __init__(self, args: list[str]):
        self.p = subprocess.Popen([sys.executable, "-m", "slamkit.cli", *args], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, cwd=REPO,
                                  env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                  preexec_fn=_default_signals)
        self.lines: queue.Queue = queue.Queue()
        self.out: list[str] = []
        self.err: list[str] = []
        for stream, sink in ((self.p.stdout, self.out), (self.p.stderr, self.err)):
            threading.Thread(target=self._read, args=(stream, sink), daemon=True).start()

    def _read(self, stream, sink):
        for line in stream:
            sink.append(line)
            self.lines.put(line)

    def wait_for(self, text: str, timeout: float = 120) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if text in self.lines.get(timeout=0.2):
                    return True
            except queue.Empty:
                if self.p.poll() is not None and self.lines.empty():
                    return False
        return False

    def signal(self, signum: int) -> None:
        try:
            self.p.send_signal(signum)
        except ProcessLookupError:  # already gone
            pass

    def wait(self, timeout: float = 120) -> int:
        try:
            return self.p.wait(timeout)
        finally:
            self.p.kill()
            time.sleep(0.1)

    @property
    def stderr(self) -> str:
        return "".join(self.err)


def test_a_second_writer_fails_fast_naming_the_first(tmp_path):
    out = tmp_path / "run"
    first = Proc([*RUN, "--max-frames", "60", "-v", "--out", str(out)])
    try:
        assert first.wait_for("frame 2 ["), first.stderr
        second = subprocess.run([sys.executable, "-m", "slamkit.cli", *RUN, "--max-frames", "5", "--out", str(out)],
                                capture_output=True, text=True, cwd=REPO, timeout=120)
        assert second.returncode == 2, second.stderr
        assert f"--out {out}: process {first.p.pid} is writing this run folder" in second.stderr
        assert "frames to process" not in second.stderr and "Traceback" not in second.stderr
        assert first.wait() == 0, first.stderr
    finally:
        first.p.kill()
    assert json.loads((out / "summary.json").read_text())["frames"] == 60  # the first run, whole
    assert _leftovers(tmp_path, "run") == []


# ----------------------------------------------------------------------------------------------- signals
@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_sigterm_and_sighup_save_like_ctrl_c_and_the_run_resumes(tmp_path, signum, code):
    out = tmp_path / "o" / "t"
    proc = Proc([*RUN, "--max-frames", "60", "-v", "--out", str(out)])
    try:
        assert proc.wait_for("frame 5 ["), proc.stderr
        proc.signal(signum)
        assert proc.wait() == code, proc.stderr
    finally:
        proc.p.kill()
    name = signal.Signals(signum).name
    assert f"{name} received" in proc.stderr and f"{name}: interrupted after frame" in proc.stderr
    assert "--resume" in proc.stderr and "Traceback" not in proc.stderr and "SIGTERM (@" not in proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert 6 <= summary["frames"] < 60
    check_run(out)
    check_session(out / "session")
    assert _leftovers(out.parent, "t") == []
    if signum == signal.SIGTERM:
        assert main([*RUN, "--max-frames", "60", "--out", str(out), "--resume"]) == 0
        frames = (out / "frames.csv").read_text()
        assert json.loads((out / "summary.json").read_text())["frames"] == 60 and ",error," not in frames


@pytest.mark.parametrize("delay", [0.0, 0.1, 0.2, 0.3])
def test_repeated_signals_leave_the_old_run_or_the_new_one_and_say_which(tmp_path, delay):
    """The third signal stops at once: in the frame (the old run stays), in the save (old or new, whole), or
    after it (the new run); never a mix, never a temporary folder left, and the last line says which."""
    out = tmp_path / "r"
    assert main([*RUN, "--max-frames", "20", "--out", str(out)]) == 0
    old_id, old_files = save_id(out), _digest(out)
    proc = Proc([*RUN, "--max-frames", "60", "-v", "--out", str(out), "--resume"])
    try:
        assert proc.wait_for("frame 25 ["), proc.stderr
        proc.signal(signal.SIGTERM)
        assert proc.wait_for("SIGTERM received"), proc.stderr
        time.sleep(delay)  # the frame finishes, then the save: the next signals land in one or the other
        proc.signal(signal.SIGTERM)
        if proc.wait_for("SIGTERM again", 30):  # signals sent at once are merged into one
            proc.signal(signal.SIGTERM)
        assert proc.wait() == 143, proc.stderr
    finally:
        proc.p.kill()
    err = proc.stderr
    last = err.strip().splitlines()[-1]
    assert "Traceback" not in err and _leftovers(tmp_path, "r") == []
    check_run(out)  # whichever run it holds is whole: every file as its manifest says
    check_session(out / "session")
    frames = json.loads((out / "summary.json").read_text())["frames"]
    if "still holds the previous run, unchanged" in last or "was left as it was" in last:
        assert "stopped at once" in last
        assert save_id(out) == old_id and _digest(out) == old_files and frames == 20
    else:
        assert any(s in last for s in ("holds this run", "interrupted after frame")), last
        assert save_id(out) != old_id and 25 < frames < 60


def test_a_last_signal_after_the_save_says_the_folder_holds_this_run(tmp_path, monkeypatch, capfd):
    """The third signal raised after the save but before the run's outcome is returned (here: while its ATE is
    evaluated): the command says the folder holds this run, as it does, not that it was left as it was."""
    import slamkit.runner
    from slamkit.interrupt import Interrupted

    out = tmp_path / "r"
    assert main([*RUN, "--max-frames", "12", "--out", str(out)]) == 0
    old_id = save_id(out)
    capfd.readouterr()

    def evaluate(outcome):
        raise Interrupted(signal.SIGTERM)

    monkeypatch.setattr(slamkit.runner, "_evaluate", evaluate)
    assert main([*RUN, "--max-frames", "14", "--out", str(out), "--resume"]) == 143
    last = capfd.readouterr().err.strip().splitlines()[-1]
    assert "stopped at once" in last and "holds this run, saved" in last, last
    assert save_id(out) not in (None, old_id) and json.loads((out / "summary.json").read_text())["frames"] == 14


def test_a_signal_landing_in_a_destructor_still_ends_the_command_without_a_traceback(monkeypatch, capfd):
    """A SIGTERM whose handler runs inside a ``__del__`` (a progress bar being collected as a command ends) is
    an exception Python cannot propagate: the command still exits 143, and no traceback is printed."""

    class SignalsWhenCollected:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)  # the handler runs here, inside __del__

    def presets(args):
        SignalsWhenCollected()  # collected at once
        return 0

    monkeypatch.setattr(slamkit.cli, "cmd_presets", presets)
    assert main(["presets"]) == 143
    assert "Traceback" not in capfd.readouterr().err


def test_stop_request_keeps_ignored_signals_ignored():
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as under nohup
    try:
        with StopRequest():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            assert isinstance(signal.getsignal(signal.SIGTERM), StopRequest)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)


class _InterruptedOnce:
    """The default sequence, but reading frame ``k`` is interrupted once (Ctrl-C arriving twice inside a step:
    the second one cuts the frame short before it changed any state)."""

    def __init__(self, k: int):
        self.inner, self.k, self.fired = open_source("default", max_frames=24), k, False

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __len__(self):
        return len(self.inner)

    def __getitem__(self, i):
        if i == self.k and not self.fired:
            self.fired = True
            raise KeyboardInterrupt
        return self.inner[i]


def test_an_interrupted_frame_is_not_an_error_and_is_processed_on_resume(tmp_path):
    src = _InterruptedOnce(15)
    slam = Slam(src, SlamConfig().with_overrides(init_frames=10, prefetch=False))
    with pytest.raises(KeyboardInterrupt) as e:
        slam.run()
    assert len(slam.records) == 15 and slam._cursor == 15 and not slam.errors  # frame 15 is given back
    assert "interrupted at frame 15" in " ".join(e.value.__notes__)
    slam.save(tmp_path / "run")
    resumed = Slam.resume(tmp_path / "run", source=src.inner)
    assert resumed.step().frame_index == 15                    # the interrupted frame comes next
    resumed.run()
    frames = (tmp_path / "run" / "frames.csv").read_text()
    assert ",error," not in frames and not resumed.errors
    assert all(r.status != "error" for r in resumed.records) and len(resumed.records) == 24


class _FailingSave(Slam):
    def summary(self) -> dict:  # the save calls it after the model and trajectories are written
        raise RuntimeError("disk trouble")


def test_an_error_during_the_save_leaves_the_old_run_and_no_temporary_folder(tmp_path):
    cfg = SlamConfig().with_overrides(max_frames=5, init_frames=2)
    slam = Slam("default", cfg)
    slam.run()
    out = tmp_path / "run"
    slam.save(out)
    before = _digest(out)
    failing = _FailingSave("default", cfg)
    failing.run()
    with pytest.raises(RuntimeError, match="disk trouble"):
        save_run(failing, out)
    assert _digest(out) == before and _leftovers(tmp_path, "run") == []
