"""Trajectory files: TUM RGB-D and KITTI odometry formats.

TUM: one pose per line, ``timestamp tx ty tz qx qy qz qw`` (seconds, metres, Hamilton quaternion x, y, z, w),
camera-to-world; lines starting with ``#`` are comments. KITTI: one pose per line, the 12 values of the
row-major 3x4 camera-to-world matrix ``[R | t]``; the file has no timestamps (KITTI keeps them in
``times.txt``, one per line).

Readers check every line and raise :class:`~slamkit.errors.FormatError` naming the file and the 1-based line
of the first problem: wrong number of values, a value that is not a finite number, a quaternion that is not
(close to) unit, a 3x3 block that is not a rotation, a timestamp not after the previous one. Blank lines and
``#`` comments (whole-line or trailing) are skipped everywhere; commas count as separators.

Writers print every number with ``repr`` (shortest text that reads back to the same float64), so a file
read back gives the same timestamps and positions bit for bit (rotations go through a quaternion in TUM and
agree to ~1e-16). Writes are atomic (:mod:`slamkit.io.atomic`).
"""

from __future__ import annotations

import os
import select
import stat
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from ..errors import ConfigError, FormatError, OutputError, missing_reason
from ..kernels.geometry import pose_from_rows, pose_from_tum, tum_from_pose
from ..types import Trajectory
from .atomic import atomic_write_text
from .ownership import TUM_HEADER  # the first line of every TUM file slamkit writes

__all__ = ["read_tum", "write_tum", "read_kitti", "write_kitti", "read_trajectory", "read_pose_file"]

#: a TUM quaternion whose norm is further than this from 1 is rejected (TUM rounds to 4 decimals)
QUATERNION_NORM_TOL = 1e-2
#: a KITTI 3x3 block with max |R^T R - I| above this, or det(R) <= 0, is rejected
ROTATION_TOL = 1e-3


# ---------------------------------------------------------------------------------------------- parsing

PIPE_TIMEOUT = 10.0
"""seconds: how long a pipe or FIFO (``--gt <(cat gt.txt)``, ``/dev/stdin``) may stay silent before the read
gives up with an error instead of blocking forever (a FIFO nobody writes to)."""


MAX_TEXT_BYTES = 64 * 2**20
"""bytes: the largest text file (trajectory, ground truth, times) slamkit reads: about a million TUM lines
(hours of motion capture at 100 Hz; parsing them takes about 1 GB of memory). A larger file, or a device
that never ends (``--gt /dev/zero``), is refused after reading at most this much."""


def _too_large(path: Path, size: str) -> FormatError:
    return FormatError(path, None, f"{size} is more than a trajectory file holds (at most "
                                   f"{MAX_TEXT_BYTES // 2**20} MB are read): not a trajectory file")


def _not_text(path: Path, data: bytes) -> None:
    """FormatError when ``data`` (the first bytes of a text file) holds a NUL byte: a binary file or device."""
    nul = data.find(b"\0")
    if nul >= 0:
        raise FormatError(path, data.count(b"\n", 0, nul) + 1, f"is not UTF-8 text (a NUL byte at byte {nul}: a binary "
                                                               "file or a device)")


def _read_bytes(path: Path) -> bytes:
    """The file's bytes, read once (so a pipe works) and at most :data:`MAX_TEXT_BYTES` of them. A FIFO or
    pipe is read without ever blocking longer than :data:`PIPE_TIMEOUT` seconds of silence; a regular file
    larger than the limit is refused before it is read; a device is read in chunks and refused as soon as it
    sends a NUL byte (``/dev/zero``, ``/dev/urandom``) or more than the limit."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FormatError(path, None, "no such file") from None
    except OSError as e:
        raise FormatError(path, None, f"cannot be read ({e.strerror or e})") from e
    if stat.S_ISDIR(st.st_mode):
        raise FormatError(path, None, "is a folder, not a trajectory file")
    if stat.S_ISREG(st.st_mode) and st.st_size > MAX_TEXT_BYTES:
        raise _too_large(path, f"{st.st_size / 2**20:.0f} MB")
    fifo = stat.S_ISFIFO(st.st_mode)
    fd = os.open(path, os.O_RDONLY | (os.O_NONBLOCK if fifo else 0))
    chunks: list[bytes] = []
    total = 0
    try:
        while True:
            if fifo:
                ready, _, _ = select.select([fd], [], [], PIPE_TIMEOUT)
                if not ready:
                    raise FormatError(path, None, f"a pipe that sent nothing for {PIPE_TIMEOUT:g} s (no writer?); "
                                                  "give a file, or a pipe that is being written")
            try:
                chunk = os.read(fd, 1 << 16)
            except BlockingIOError:
                continue
            if not chunk:
                return b"".join(chunks)
            if not chunks:
                _not_text(path, chunk)
            elif b"\0" in chunk:
                _not_text(path, b"".join(chunks) + chunk)
            chunks.append(chunk)
            total += len(chunk)
            if total > MAX_TEXT_BYTES:
                raise _too_large(path, "it sent more than that")
    finally:
        os.close(fd)


def check_input_file(path: str | os.PathLike, flag: str) -> Path:
    """``path`` as a Path when it names something readable (a file or a pipe); else FormatError saying
    what is wrong with it and naming ``flag``: missing, a broken symlink, a symlink loop, a folder."""
    path = Path(path)
    why = missing_reason(path)
    if why:
        raise FormatError(path, None, f"{why} (given as {flag})")
    st = os.stat(path)
    if stat.S_ISDIR(st.st_mode):
        raise FormatError(path, None, f"is a folder, not a file (given as {flag})")
    return path


def _read_lines(path: Path) -> list[bytes]:
    try:
        data = _read_bytes(path)
    except FileNotFoundError:
        raise FormatError(path, None, "no such file") from None
    except IsADirectoryError:
        raise FormatError(path, None, "is a folder, not a trajectory file") from None
    except OSError as e:
        raise FormatError(path, None, f"cannot be read ({e.strerror or e})") from e
    if data.startswith(b"\xef\xbb\xbf"):  # UTF-8 byte order mark
        data = data[3:]
    return data.split(b"\n")


def _data_rows(path: Path, lines: list[bytes] | None = None) -> Iterator[tuple[int, list[str]]]:
    """Yield ``(line_number, tokens)`` of every non-blank, non-comment line (1-based line numbers) of the
    file, or of its ``lines`` when they were read already."""
    for lineno, raw in enumerate(_read_lines(path) if lines is None else lines, start=1):
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise FormatError(path, lineno, "is not UTF-8 text") from None
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if line:
            yield lineno, line.split()


def _parse_numbers(path: Path, lineno: int, tokens: list[str], n: int, layout: str) -> list[float]:
    if len(tokens) != n:
        raise FormatError(path, lineno, f"expected {n} values ({layout}), found {len(tokens)}")
    values = []
    for i, tok in enumerate(tokens, start=1):
        try:
            v = float(tok)
        except ValueError:
            raise FormatError(path, lineno, f"value {i} {tok[:40]!r} is not a number") from None
        if not np.isfinite(v):
            raise FormatError(path, lineno, f"value {i} {tok[:40]!r} is not a finite number")
        values.append(v)
    return values


def _read_table(path: Path, n: int, layout: str, text: list[bytes] | None = None) -> tuple[np.ndarray, list[int]]:
    """All data lines as an (N, n) float64 array plus their line numbers."""
    rows, lines = [], []
    for lineno, tokens in _data_rows(path, text):
        rows.append(_parse_numbers(path, lineno, tokens, n, layout))
        lines.append(lineno)
    return np.array(rows, dtype=np.float64).reshape(-1, n), lines


def _check_increasing(path: Path, timestamps: np.ndarray, lines: Sequence[int]) -> None:
    bad = np.flatnonzero(~(np.diff(timestamps) > 0))
    if len(bad):
        i = int(bad[0]) + 1
        raise FormatError(path, lines[i], f"timestamp {timestamps[i]!r} is not after the previous one "
                                          f"({timestamps[i - 1]!r} on line {lines[i - 1]}); "
                                          "timestamps must be strictly increasing")


# ---------------------------------------------------------------------------------------------- TUM

def read_tum(path: str | os.PathLike, _text: list[bytes] | None = None) -> Trajectory:
    """Read a TUM trajectory file -> Trajectory (camera-to-world poses, quaternions normalised).

    A file without data lines gives an empty Trajectory. FormatError names the file and line at fault.
    """
    path = Path(path)
    table, lines = _read_table(path, 8, "timestamp tx ty tz qx qy qz qw", _text)
    q = table[:, 4:8]
    norms = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(np.abs(norms - 1.0) <= QUATERNION_NORM_TOL))
    if len(bad):
        i = int(bad[0])
        raise FormatError(path, lines[i], f"quaternion (qx qy qz qw) has norm {norms[i]:.6g}, not 1")
    _check_increasing(path, table[:, 0], lines)
    poses = pose_from_tum(table[:, 1:4], q) if len(table) else np.zeros((0, 4, 4))
    return Trajectory(table[:, 0], poses)


def _fmt(x) -> str:
    return repr(float(x))


def write_tum(path: str | os.PathLike, traj: Trajectory) -> Path:
    """Write ``traj`` as a TUM file (``timestamp tx ty tz qx qy qz qw``, camera-to-world), atomically.

    Numbers are printed with ``repr`` (exact float64 round trip). OutputError if the folder cannot be
    written, or if the trajectory has non-finite values or timestamps that are not strictly increasing
    (the file could not be read back).
    """
    path = Path(path)
    timestamps = np.asarray(traj.timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(traj.poses, dtype=np.float64).reshape(-1, 4, 4)
    _check_writable(path, timestamps, poses)
    t, q = tum_from_pose(poses) if len(poses) else (np.zeros((0, 3)), np.zeros((0, 4)))

    def lines() -> Iterator[str]:
        yield TUM_HEADER + "\n"
        for ts, ti, qi in zip(timestamps, t, q):
            yield " ".join(_fmt(v) for v in (ts, *ti, *qi)) + "\n"

    return atomic_write_text(path, lines())


def _check_writable(path: Path, timestamps: np.ndarray, poses: np.ndarray) -> None:
    if len(timestamps) != len(poses):
        raise OutputError(f"{path}: not written: {len(timestamps)} timestamps but {len(poses)} poses")
    finite = np.isfinite(timestamps) & np.isfinite(poses).all(axis=(1, 2))
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise OutputError(f"{path}: not written: pose {i} (t={timestamps[i]!r}) has non-finite values")
    bad = np.flatnonzero(~(np.diff(timestamps) > 0))
    if len(bad):
        i = int(bad[0]) + 1
        raise OutputError(f"{path}: not written: timestamp {i} ({timestamps[i]!r}) is not after timestamp "
                          f"{i - 1} ({timestamps[i - 1]!r})")


# ---------------------------------------------------------------------------------------------- KITTI

def _read_times(path: Path) -> tuple[np.ndarray, list[int]]:
    table, lines = _read_table(path, 1, "one timestamp per line")
    return table[:, 0], lines


def read_kitti(path: str | os.PathLike,
               timestamps: np.ndarray | Sequence[float] | str | os.PathLike | None = None,
               _text: list[bytes] | None = None) -> Trajectory:
    """Read a KITTI pose file (12 values per line, row-major 3x4 camera-to-world) -> Trajectory.

    ``timestamps``: None gives 0, 1, 2, ... (the line index); an (N,) array of seconds; or the path of a
    KITTI ``times.txt`` (one value per line). Their count must equal the number of poses and they must be
    strictly increasing. FormatError names the file and line at fault.
    """
    path = Path(path)
    table, lines = _read_table(path, 12, "row-major 3x4 matrix r11 r12 r13 tx r21 ... tz", _text)
    poses = pose_from_rows(table) if len(table) else np.zeros((0, 4, 4))
    R = poses[:, :3, :3]
    ortho = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2)) if len(R) else np.zeros(0)
    det = np.linalg.det(R) if len(R) else np.zeros(0)
    bad = np.flatnonzero(~((ortho <= ROTATION_TOL) & (det > 0)))
    if len(bad):
        i = int(bad[0])
        raise FormatError(path, lines[i], f"the 3x3 block is not a rotation matrix (max |R^T R - I| = "
                                          f"{ortho[i]:.3g}, det = {det[i]:.6g})")
    if timestamps is None:
        ts = np.arange(len(poses), dtype=np.float64)
    elif isinstance(timestamps, (str, os.PathLike)):
        times_path = Path(timestamps)
        ts, time_lines = _read_times(times_path)
        if len(ts) != len(poses):
            raise FormatError(times_path, None, f"has {len(ts)} timestamps but {path} has {len(poses)} poses")
        _check_increasing(times_path, ts, time_lines)
    else:
        ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        if len(ts) != len(poses):
            raise ConfigError(f"timestamps: {len(ts)} given but {path} has {len(poses)} poses")
        if not np.isfinite(ts).all() or not (np.diff(ts) > 0).all():
            raise ConfigError("timestamps: must be finite and strictly increasing")
    return Trajectory(ts, poses)


def write_kitti(path: str | os.PathLike, traj: Trajectory) -> Path:
    """Write ``traj`` as a KITTI pose file (12 values per line), atomically. Timestamps are not stored.

    Values are printed with ``repr``, so reading the file back gives the same poses bit for bit.
    """
    path = Path(path)
    timestamps = np.asarray(traj.timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(traj.poses, dtype=np.float64).reshape(-1, 4, 4)
    _check_writable(path, timestamps, poses)
    rows = poses[:, :3, :].reshape(-1, 12)

    def lines() -> Iterator[str]:
        for row in rows:
            yield " ".join(_fmt(v) for v in row) + "\n"

    return atomic_write_text(path, lines())


# ---------------------------------------------------------------------------------------------- either

def _detect(path: Path) -> tuple[str, list[bytes]]:
    """("tum" | "kitti", the file's lines), told apart by the first data line; the file is read once."""
    text = _read_lines(path)  # once: a pipe cannot be read twice
    first = next(_data_rows(path, text), None)
    if first is None:
        raise FormatError(path, None, "has no poses (no data lines)")
    lineno, tokens = first
    if len(tokens) == 8:
        return "tum", text
    if len(tokens) == 12:
        return "kitti", text
    raise FormatError(path, lineno, f"{len(tokens)} values: expected 8 (TUM: timestamp tx ty tz qx qy qz qw) "
                                    "or 12 (KITTI: row-major 3x4 pose)")


def read_pose_file(path: str | os.PathLike) -> tuple[str, Trajectory]:
    """Read a TUM or KITTI pose file, told apart by its first data line: ``("tum", trajectory)`` with the
    file's timestamps, or ``("kitti", trajectory)`` whose timestamps are the line indices 0, 1, 2, ... (a
    KITTI file has none: :mod:`slamkit.eval.pairing` pairs it by frame index). The file is read once.
    FormatError when it has no data line or the first one has another number of values."""
    path = Path(path)
    kind, text = _detect(path)
    return kind, (read_tum(path, text) if kind == "tum" else read_kitti(path, None, text))


def read_trajectory(path: str | os.PathLike,
                    timestamps: np.ndarray | Sequence[float] | str | os.PathLike | None = None) -> Trajectory:
    """Read a TUM (8 values per line) or KITTI (12 values per line) file, told apart by the first data line.

    ``timestamps`` is used for KITTI files only (see :func:`read_kitti`; without it a KITTI file's timestamps
    are its line indices, which :func:`slamkit.eval.evaluate` never takes for seconds). FormatError when the
    file has no data line or the first one has another number of values.
    """
    path = Path(path)
    kind, text = _detect(path)
    if kind == "tum":
        if timestamps is not None:
            raise ConfigError(f"timestamps: given, but {path} is a TUM file with its own timestamps")
        return read_tum(path, text)
    return read_kitti(path, timestamps, text)
