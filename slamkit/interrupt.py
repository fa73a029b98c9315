"""Interruptions that never leave half a frame: Ctrl-C (SIGINT), SIGTERM and SIGHUP.

``timeout``, batch schedulers, Dask and ``docker stop`` send SIGTERM; closing a terminal sends SIGHUP. Both
are handled like Ctrl-C: the current frame finishes, then :class:`Interrupted` (a ``KeyboardInterrupt``, so
``except KeyboardInterrupt`` keeps working) is raised carrying the signal, and the caller saves.

- :func:`deferred_interrupt` holds those signals back for the duration of a block (one SLAM step, a save)
  and re-delivers the first one when the block ends; a second one inside the block interrupts at once.
- :class:`StopRequest` is a handler for a whole run (``slamkit run``): it records the signals and never
  raises while a frame or a save is in progress, so the run stops between frames and is saved; only the
  third signal (:attr:`StopRequest.abort_after`) stops at once, without saving.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator

__all__ = ["HELD_SIGNALS", "Interrupted", "StopRequest", "deferred_interrupt", "exit_code", "notify",
           "quiet_startup_interrupt", "signal_name", "signals_blocked"]

HELD_SIGNALS: tuple[int, ...] = tuple(s for s in (getattr(signal, n, None) for n in ("SIGINT", "SIGTERM", "SIGHUP"))
                                      if s is not None)
"""The signals that stop a run cleanly (SIGHUP does not exist on Windows)."""


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:  # pragma: no cover - not a known signal
        return f"signal {signum}"


def exit_code(signum: int) -> int:
    """The shell's exit code for a process stopped by ``signum``: 128 + signum (130 SIGINT, 143 SIGTERM)."""
    return 128 + int(signum)


class Interrupted(KeyboardInterrupt):
    """A run was stopped by a signal; ``signum`` says which (SIGINT for a plain Ctrl-C)."""

    def __init__(self, signum: int = signal.SIGINT):
        self.signum = int(signum)
        super().__init__(signal_name(self.signum))

    @property
    def exit_code(self) -> int:
        return exit_code(self.signum)


def raise_interrupted(signum: int, frame) -> None:
    """A signal handler: raise :class:`Interrupted` at once."""
    raise Interrupted(signum)


class StopRequest:
    """Signal handler of a run: remembers the signals; the loop checks :attr:`signum` between frames.

    The first signal asks to stop after the current frame (and the save); the second only says that the run
    is already stopping; the ``abort_after``-th raises :class:`Interrupted` wherever the program is (the work
    of this run is then not saved; see :func:`slamkit.runner.run_to_folder`), later ones are only recorded. Use as a context manager to
    install it for SIGINT, SIGTERM and SIGHUP (main thread only; elsewhere it is inert).
    """

    abort_after = 3

    def __init__(self, on_signal: Callable[[int, int], None] | None = None):
        self.signals: list[int] = []
        self.on_signal = on_signal
        """Called as ``on_signal(signum, count)`` when a signal arrives (e.g. to print what happens next)."""
        self._previous: dict[int, object] = {}

    @property
    def signum(self) -> int | None:
        """The first signal received, or None."""
        return self.signals[0] if self.signals else None

    def __call__(self, signum: int, frame) -> None:
        self.signals.append(int(signum))
        if self.on_signal is not None:
            self.on_signal(int(signum), len(self.signals))
        if len(self.signals) == self.abort_after:  # once: later signals do not cut the clean-up short
            raise Interrupted(signum)

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for s in HELD_SIGNALS:
                if signal.getsignal(s) is not signal.SIG_IGN:  # nohup's SIGHUP, a background job's SIGINT
                    self._previous[s] = signal.signal(s, self)
        return self

    def __exit__(self, *exc) -> None:
        for s, previous in self._previous.items():
            signal.signal(s, previous if previous is not None else signal.SIG_DFL)
        self._previous.clear()


@contextlib.contextmanager
def deferred_interrupt() -> Iterator[None]:
    """Hold SIGINT, SIGTERM and SIGHUP back until the block ends, then deliver the first one received.

    Wrapped around one SLAM step (and around saving), so an interrupt never leaves half a frame in the map:
    the step completes, then the signal's handler runs (Python's SIGINT handler raises KeyboardInterrupt).
    A second signal inside the block interrupts at once (:class:`Interrupted`). Only in the main thread
    (signal handlers live there) and only for signals with a Python handler: a signal that is ignored or has
    its OS default action (SIGTERM, SIGHUP in a plain Python process) is left alone. Under a
    :class:`StopRequest` nothing is changed: it never raises inside a frame by itself.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in HELD_SIGNALS}
    held = [s for s, h in previous.items() if callable(h) and not isinstance(h, StopRequest)]
    if not held:
        yield
        return
    received: list[tuple] = []

    def hold(signum, frame):
        if received:
            raise Interrupted(signum)
        received.append((signum, frame))

    for s in held:
        signal.signal(s, hold)
    try:
        yield
    finally:
        for s in held:
            signal.signal(s, previous[s])
    if received:
        signum, frame = received[0]
        previous[signum](signum, frame)


@contextlib.contextmanager
def signals_blocked() -> Iterator[None]:
    """Block SIGINT, SIGTERM and SIGHUP at the OS level for a few system calls that must not be separated
    (the two renames that replace a folder); signals that arrive meanwhile are delivered afterwards."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, HELD_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def notify(message: str) -> None:
    """Print one line on stderr from a signal handler (os.write: no re-entrant call into a buffered stream)."""
    try:
        os.write(sys.stderr.fileno(), (message.rstrip("\n") + "\n").encode())
    except (OSError, ValueError, AttributeError):
        pass


STARTUP_MESSAGE = "slamkit: {signal}: stopped while starting; nothing was read or written"


def _is_command() -> bool:
    """True when this process is the ``slamkit`` command (the console script or ``python -m slamkit.cli``)."""
    if sys.argv and os.path.basename(sys.argv[0]) == "slamkit":
        return True
    argv = list(getattr(sys, "orig_argv", None) or sys.argv)
    return any(a == "-m" and b in ("slamkit.cli", "slamkit") for a, b in zip(argv, argv[1:]))


def quiet_startup_interrupt() -> None:
    """In the ``slamkit`` command only: a Ctrl-C that lands while the program starts (importing pycolmap,
    OpenCV, numba: seconds), before the command's own handlers run, ends it with one line instead of a
    traceback. Python still exits by SIGINT (the shell's code 130). Called first by ``slamkit/__init__``;
    a library user's (or notebook's) exception display is never changed."""
    if not _is_command():
        return
    previous = sys.excepthook

    def hook(kind, value, tb) -> None:
        if issubclass(kind, KeyboardInterrupt):
            notify(STARTUP_MESSAGE.format(signal=signal_name(getattr(value, "signum", signal.SIGINT))))
            return
        previous(kind, value, tb)

    sys.excepthook = hook
