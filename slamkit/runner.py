"""Run SLAM on a source into a run folder, safely: the library behind ``slamkit run``.

>>> outcome = run_to_folder("default", "runs/demo", SlamConfig())     # doctest: +SKIP
>>> outcome.exit_code, outcome.summary["fraction_posed"]              # doctest: +SKIP

What :func:`run_to_folder` guarantees, in order:

1. ``out`` is checked before any frame is read (:func:`slamkit.io.run_dir.check_out_dir`): only an empty
   folder or an earlier slamkit run is replaced (``overwrite`` widens nothing: a user's folder, the home or
   current folder is never replaced), the input is never inside or equal to the output, an unwritable
   place fails at once.
2. ``out`` is locked for the whole run (:func:`slamkit.io.run_dir.out_dir_lock`): a second writer fails fast.
3. SIGINT, SIGTERM and SIGHUP stop the run between frames (:class:`slamkit.interrupt.StopRequest`): the frame
   in progress finishes, what was built is saved atomically, and the exit code is 128 + the signal (130,
   143, 129). A stage that raises stops the run too; the frames before it are saved (exit code 1). The third
   signal aborts at once without saving: ``out`` then holds the previous run (or the new one, if the save had
   already replaced it), and the outcome says which.
4. The run folder is replaced atomically, with a manifest of every file (checked before it is read again).
"""

from __future__ import annotations

import contextlib
import dataclasses
import signal
from collections.abc import Callable
from pathlib import Path

from .config import SlamConfig
from .errors import SlamkitError
from .eval import evaluate
from .interrupt import Interrupted, StopRequest, exit_code, signal_name
from .io.run import save_run
from .io.run_dir import check_out_dir, out_dir_lock, remove_stale_temporaries, save_id
from .pipeline import Slam, StepResult
from .session import find_session
from .state import ROTATION_ONLY, describe_stages

__all__ = ["EXIT_CODES", "EXIT_FAILED", "EXIT_NOTHING_POSED", "EXIT_OK", "EXIT_POOR_MATCH", "EXIT_USAGE",
           "RunOutcome", "run_to_folder", "summary_line"]

FINISHED, INTERRUPTED, FAILED, ABORTED = "finished", "interrupted", "failed", "aborted"

EXIT_OK = 0
"""A map was made (``run``), the command did what it was asked (the others)."""
EXIT_FAILED = 1
"""A stage failed (the frames before it are saved), or some runs of an ablation failed (posing no frame is failing)."""
EXIT_USAGE = 2
"""Bad input: a path, value or file at fault, named in one line; nothing was written."""
EXIT_NOTHING_POSED = 3
"""``run``: the run went through its frames and saved, but posed none of them: no map (the reason is printed)."""
EXIT_POOR_MATCH = 4
"""``eval``: fewer than half of the estimate's poses matched ground truth: the numbers are not a measure of the run."""
EXIT_CODES = (f"exit codes: {EXIT_OK} done (run: a map was made); {EXIT_FAILED} a stage failed (frames before it "
              f"saved) or an ablation run failed or posed no frame; {EXIT_USAGE} bad input (one line names it; nothing written); "
              f"{EXIT_NOTHING_POSED} run: ran but posed no frame (no map); {EXIT_POOR_MATCH} eval: less than half of "
              "the estimate matched ground truth; 128+N stopped by signal N (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP): a "
              "run saves what it built first; 141 the output pipe was closed")
"""The exit codes of every command, as ``slamkit --help`` lists them."""


@dataclasses.dataclass(frozen=True)
class RunOutcome:
    """How a run ended. ``status``: finished | interrupted (a signal; saved) | failed (a stage raised;
    saved) | aborted (the third signal; not saved). ``exit_code``: :data:`EXIT_OK` only when a map was made;
    :data:`EXIT_NOTHING_POSED` when a finished run posed no frame; 1 failed; 128 + the signal."""

    out: Path
    status: str
    exit_code: int
    message: str
    """Why the run stopped early ("" when finished), one line."""
    saved: bool
    """True when ``out`` holds this run (False only when aborted before the save replaced it)."""
    summary: dict
    error: BaseException | None = None
    """The exception a stage raised (status failed)."""
    ate: dict | None = None
    """``slamkit.eval.evaluate`` of the saved trajectory against the saved ground truth, when there is one."""
    evaluation_error: str = ""
    complete: bool = False
    """Every frame processed and the run finished (final bundle adjustment): nothing left to resume."""
    resumed_after: int | None = None
    """With ``resume``: the number of frames the resumed session had processed."""


def _open(source, out: Path, config: SlamConfig | None, resume: bool, resume_overrides: dict | None,
          notify: Callable[[str], None], map=None, localize_only: bool = False) -> tuple[Slam, int | None]:
    if resume:
        session = find_session(out)
        if session is None:
            notify(f"no session in {out}; starting a new run")
        else:
            slam = Slam.resume(session, source, resume_overrides or None)
            return slam, len(slam.records)
    return Slam(source, config or SlamConfig(), map=map, localize_only=localize_only), None


def run_to_folder(source, out: str | Path, config: SlamConfig | None = None, *, resume: bool = False,
                  resume_overrides: dict | None = None, overwrite: bool = False,
                  on_start: Callable[[Slam, int | None], None] | None = None,
                  on_result: Callable[[Slam, StepResult], None] | None = None,
                  notify: Callable[[str], None] | None = None, evaluate_ate: bool = True,
                  stop: StopRequest | None = None, map: str | Path | None = None,
                  localize_only: bool = False) -> RunOutcome:
    """Run (or with ``resume`` continue) SLAM on ``source`` and save it to ``out``; see the module docstring.

    source: a spec, path or FrameSource. config: the configuration of a new run. resume: continue the session
        saved in ``out`` when there is one (``resume_overrides``: the config values to change), else start anew.
    on_start(slam, resumed_after): before the first frame; on_result(slam, result): after every frame.
    notify(line): one-line notes (signals received, no session to resume); default: none.
    stop: a :class:`StopRequest` the caller has installed already (to keep handling signals after this returns,
        as the CLI does while it prints); None installs one for the duration of the call.
    map: a saved run folder whose map the frames are posed in and extend (only read; ``localize_only``: not
        extended), :mod:`slamkit.map_reuse`.
    Raises SlamkitError before any work for a bad ``out``, source, map or config (nothing is written then).
    """
    check_out_dir(out, [source, *([map] if map is not None else [])], overwrite)  # the raw value: "" is refused, not taken for "."
    out = Path(out)
    notify = notify or (lambda line: None)
    state: dict = {}

    def on_signal(signum: int, count: int) -> None:
        slam = state.get("slam")
        if slam is None or not slam.records:  # starting: nothing to save; the one final line says what happened
            return
        what = "finishing the final bundle adjustment" if slam.done else "finishing the frame in progress"
        if count == 1:
            notify(f"{signal_name(signum)} received: {what}, then saving to {out} "
                   f"(send it {StopRequest.abort_after - 1} more times to stop at once without saving)")
        elif count < StopRequest.abort_after:
            notify(f"{signal_name(signum)} again: still stopping; once more stops at once without saving")

    own = stop is None
    stop = stop if stop is not None else StopRequest()
    stop.on_signal = on_signal
    with out_dir_lock(out), stop if own else contextlib.nullcontext():
        remove_stale_temporaries(out)
        slam, resumed_after = _open(source, out, config, resume, resume_overrides, notify, map, localize_only)
        state["slam"] = slam
        check_out_dir(out, [source, slam.source, *([map] if map is not None else [])], overwrite)
        if on_start is not None and stop.signum is None:  # a signal while opening: stop now, not after on_start
            on_start(slam, resumed_after)
        if stop.signum is not None:  # before the first frame: nothing new to save
            return RunOutcome(out, INTERRUPTED, exit_code(stop.signum), f"{signal_name(stop.signum)} before the "
                              f"first frame; {out} was left as it was", False, slam.summary(),
                              resumed_after=resumed_after)
        outcome = _loop_and_save(slam, out, overwrite, stop, on_result)
        if outcome.saved and evaluate_ate:
            outcome = _evaluate(outcome)
    return dataclasses.replace(outcome, resumed_after=resumed_after)


def _loop_and_save(slam: Slam, out: Path, overwrite: bool, stop: StopRequest,
                   on_result: Callable[[Slam, StepResult], None] | None) -> RunOutcome:
    status, code, message, error = FINISHED, 0, "", None
    before = save_id(out)
    try:
        while not slam.done and stop.signum is None:
            r = slam.step()
            if on_result is not None:
                on_result(slam, r)
        if stop.signum is None:
            slam.finish()
    except Interrupted as e:  # the abort_after-th signal: inside a frame, so this state is not saved
        return _aborted(slam, out, before, e.signum, "processing a frame")
    except KeyboardInterrupt:  # raised by other code than our handler (e.g. a callback)
        return _aborted(slam, out, before, signal.SIGINT, "processing a frame")
    except Exception as e:  # noqa: BLE001 - a stage failed: keep what was built, then report
        last = slam.records[-1] if slam.records else None
        failed = last is not None and last.index in slam.errors
        where = (f"frame {last.index} (frame id {last.frame_id}) failed" if failed
                 else "finishing the run failed" if slam.done else f"failed after frame {len(slam.records) - 1}")
        status, code, message, error = FAILED, 1, f"{where}: {type(e).__name__}: {e}", e
    if stop.signum is not None and status == FINISHED:
        status, code = INTERRUPTED, exit_code(stop.signum)
        message = (f"{signal_name(stop.signum)}: interrupted after frame {len(slam.records) - 1} "
                   f"({len(slam.records)}/{len(slam)} frames)" if not (slam.done and slam.finished) else
                   f"{signal_name(stop.signum)} received while finishing; the run is complete")
    try:
        save_run(slam, out, overwrite=overwrite, lock=False)
    except Interrupted as e:
        return _aborted(slam, out, before, e.signum, "saving")
    if stop.signum is not None and status == FINISHED:  # a signal during the save: the save completed
        status, code = INTERRUPTED, exit_code(stop.signum)
        message = f"{signal_name(stop.signum)} received while saving; the save completed"
    if status == FINISHED and not slam.summary().get("frames_posed"):  # ran through, but no map: not a success
        code = EXIT_NOTHING_POSED
    return RunOutcome(out, status, code, message, True, slam.summary(), error, complete=slam.done and slam.finished)


def _aborted(slam: Slam, out: Path, before: str | None, signum: int, during: str) -> RunOutcome:
    now = save_id(out)
    saved = now is not None and now != before
    if saved:
        held = f"{out} holds this run: its save had completed"
    elif before is not None:
        held = f"{out} still holds the previous run, unchanged (the frames of this run are not saved)"
    else:
        held = f"nothing was saved to {out}"
    message = f"{signal_name(signum)} again: stopped at once while {during}; {held}"
    return RunOutcome(out, ABORTED, exit_code(signum), message, saved, slam.summary())


def _evaluate(outcome: RunOutcome) -> RunOutcome:
    gt = outcome.out / "groundtruth_tum.txt"
    if not gt.exists() or outcome.summary["frames_posed"] < 3:
        return outcome
    try:
        ev = evaluate(outcome.out / "trajectory_tum.txt", gt)
    except SlamkitError as e:
        return dataclasses.replace(outcome, evaluation_error=str(e))
    return dataclasses.replace(outcome, ate={**ev["ate"], "matched": ev["matched"]})


def summary_line(s: dict) -> str:
    """The run's final console line: frames, posed, keyframes, points, speed; frames skipped or unreadable
    (with the first reason) and, when no map was built, why."""
    line = (f"frames {s['frames']}/{s['frames_total']}, posed {s['frames_posed']} "
            f"({100 * s['fraction_posed']:.1f} %), keyframes {s['keyframes']}, points {s['points3D']}, "
            f"{s['fps']:.1f} frames/s")
    if s.get("stage_ms_per_frame"):
        line += f" ({describe_stages(s['stage_ms_per_frame'])})"
    skipped, unreadable = s.get("frames_skipped", 0), s.get("frames_unreadable", 0)
    if skipped or unreadable:
        first = (s.get("unreadable_frames") or [{}])[0]
        line += f"; {skipped} frame{'s' if skipped != 1 else ''} skipped ({unreadable} unreadable"
        line += f", e.g. frame {first['frame']}: {first['error']})" if first else ")"
    if s.get("structure") == ROTATION_ONLY:
        line += f"; {ROTATION_ONLY} ({s.get('frames_rotation_only', 0)} frames turned only)"
    if s.get("not_initialized_reason") and s["frames"]:
        line += f"; no map: {s['not_initialized_reason']}"
    return line
