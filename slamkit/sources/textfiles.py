"""Line-oriented parsing of the small text files datasets ship (lists, timestamps, poses, calibrations).

One loop for every format: a data line is any line that is not blank and does not start with the comment
character; its fields are split on whitespace (or a delimiter such as ``","``) and converted one by one.
Every problem raises :class:`~slamkit.errors.FormatError` naming the file and the 1-based line number, so
a malformed ``rgb.txt``, ``groundtruth.txt``, ``calib.txt``, ``times.txt``, pose file or ``data.csv``
points the user at the line to fix.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..errors import FormatError, SourceError, missing_reason

Converter = Callable[[str], object]


def require_path(path: str | Path, what: str, kind: str = "file") -> Path:
    """``path`` as a Path when it exists as a ``kind`` ("file" or "dir"), else :class:`SourceError`."""
    p = Path(path).expanduser()
    ok = p.is_file() if kind == "file" else p.is_dir()
    if not ok:
        state = (missing_reason(p) or "does not exist") if not p.exists() else \
            f"is not a {'folder' if kind == 'dir' else 'file'}"
        raise SourceError(f"{what} {p} {state}")
    return p


def to_float(text: str) -> float:
    """Strict decimal float: like ``float`` but refuses ``1_000`` and surrounding junk."""
    if "_" in text:
        raise ValueError(f"{text!r} is not a number")
    return float(text)


def to_int(text: str) -> int:
    """Strict decimal integer (an optional sign and digits only)."""
    body = text[1:] if text[:1] in "+-" else text
    if not body.isascii() or not body.isdigit():
        raise ValueError(f"{text!r} is not an integer")
    return int(text)


def to_str(text: str) -> str:
    return text


_KIND_NAMES = {to_float: "a number", to_int: "an integer", to_str: "text"}


def data_lines(path: str | Path, comment: str | None = "#",
               delimiter: str | None = None) -> list[tuple[int, list[str]]]:
    """The data lines of a text file as ``(1-based line number, fields)``.

    Blank lines and lines whose first non-blank character is ``comment`` are skipped. Fields are split on
    whitespace when ``delimiter`` is None, else on ``delimiter`` and stripped (an empty field is an error).
    A missing file raises :class:`SourceError`; bytes that are not UTF-8 raise :class:`FormatError`.
    """
    path = require_path(path, "text file")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise SourceError(f"text file {path} cannot be read ({e.strerror or e})") from None
    out: list[tuple[int, list[str]]] = []
    # bytes.splitlines splits on \n, \r and \r\n only: line numbers match what an editor shows
    for number, line_bytes in enumerate(raw.splitlines(), start=1):
        try:
            line = line_bytes.decode("utf-8")
        except UnicodeDecodeError:
            raise FormatError(path, number, "is not UTF-8 text") from None
        if number == 1:
            line = line.lstrip("\ufeff")
        if "\x00" in line:
            raise FormatError(path, number, "contains a NUL byte (binary file?)")
        stripped = line.strip()
        if not stripped or (comment is not None and stripped.startswith(comment)):
            continue
        if delimiter is None:
            fields = stripped.split()
        else:
            fields = [f.strip() for f in stripped.split(delimiter)]
            if any(f == "" for f in fields):
                raise FormatError(path, number, f"has an empty field (fields separated by {delimiter!r})")
        out.append((number, fields))
    return out


def convert_fields(path: Path, number: int, fields: Sequence[str], converters: Sequence[Converter],
                   what: Sequence[str] | None = None) -> list:
    """Convert ``fields`` with ``converters`` one by one; a failure names the file, line and column."""
    values = []
    for col, (text, conv) in enumerate(zip(fields, converters)):
        try:
            values.append(conv(text))
        except (ValueError, OverflowError):
            name = f" ({what[col]})" if what is not None and col < len(what) else ""
            kind = _KIND_NAMES.get(conv, "valid")
            raise FormatError(path, number, f"field {col + 1}{name} is {text[:40]!r}, not {kind}") from None
    return values


def parse_rows(path: str | Path, converters: Sequence[Converter], *, comment: str | None = "#",
               delimiter: str | None = None, at_least: bool = False,
               what: Sequence[str] | None = None) -> tuple[list[list], np.ndarray]:
    """Parse every data line into ``len(converters)`` typed values.

    Returns (rows, lines): ``rows[i]`` is the converted list of line ``lines[i]`` (1-based, (N,) int64).
    With ``at_least`` extra trailing fields are allowed and ignored, otherwise the count must be exact.
    ``what`` names the columns in error messages (e.g. ``("timestamp", "filename")``).
    """
    path = Path(path)
    n = len(converters)
    rows, lines = [], []
    for number, fields in data_lines(path, comment, delimiter):
        if len(fields) < n or (not at_least and len(fields) != n):
            expected = f"at least {n}" if at_least else f"{n}"
            names = f" ({' '.join(what)})" if what else ""
            raise FormatError(path, number, f"expected {expected} fields{names}, got {len(fields)}")
        rows.append(convert_fields(path, number, fields[:n], converters, what))
        lines.append(number)
    return rows, np.asarray(lines, dtype=np.int64)


def check_finite(path: Path, values: np.ndarray, lines: np.ndarray, what: str = "value") -> None:
    """FormatError naming the first line of ``values`` (N, ...) that holds a NaN or an infinity."""
    if len(values) == 0:
        return
    bad = ~np.isfinite(values.reshape(len(values), -1)).all(axis=1)
    if bad.any():
        raise FormatError(path, int(lines[np.argmax(bad)]), f"{what} is not finite (nan or inf)")


def check_increasing(path: Path, values: Sequence[float] | np.ndarray, lines: np.ndarray,
                     what: str = "timestamp") -> None:
    """FormatError naming the first line whose ``values`` entry is not larger than the previous one."""
    v = np.asarray(values)
    if len(v) < 2:
        return
    bad = ~(v[1:] > v[:-1])
    if bad.any():
        k = int(np.argmax(bad)) + 1
        raise FormatError(path, int(lines[k]),
                          f"{what} {v[k]} is not larger than the previous one ({v[k - 1]} on line "
                          f"{int(lines[k - 1])}): {what}s must be strictly increasing")


def parse_float_rows(path: str | Path, ncols: int, comment: str | None = "#", *,
                     delimiter: str | None = None, at_least: bool = False, finite: bool = True,
                     increasing: int | None = None, what: Sequence[str] | None = None,
                     return_lines: bool = False):
    """Parse a table of numbers: one row of ``ncols`` floats per data line.

    Args:
        path: the text file.
        ncols: number of values per line (exact, or the first ``ncols`` when ``at_least``).
        comment: lines starting with this (after blanks) are skipped.
        delimiter: None for whitespace, else e.g. ``","``.
        finite: refuse NaN and infinities (FormatError naming the line).
        increasing: index of a column (e.g. 0 for timestamps) that must be strictly increasing.
        what: column names for messages.
        return_lines: also return the (N,) 1-based line numbers.

    Returns:
        (N, ncols) float64 array (N may be 0), or (array, lines) with ``return_lines``.
    """
    path = Path(path)
    rows, lines = parse_rows(path, [to_float] * ncols, comment=comment, delimiter=delimiter,
                             at_least=at_least, what=what)
    values = np.asarray(rows, dtype=np.float64).reshape(len(rows), ncols)
    if finite:
        check_finite(path, values, lines)
    if increasing is not None:
        name = what[increasing] if what is not None else f"column {increasing + 1}"
        check_increasing(path, values[:, increasing], lines, what=name)
    return (values, lines) if return_lines else values


def parse_keyed_rows(path: str | Path, comment: str | None = "#") -> dict[str, tuple[int, np.ndarray]]:
    """Parse ``KEY: v1 v2 ...`` lines (KITTI ``calib.txt``) into ``{KEY: (line, (n,) float64)}``.

    Values may be non-finite here; callers decide (a calibration raises CalibrationError).
    A line without ``:``, an empty key, a repeated key or a non-number raises FormatError.
    """
    path = Path(path)
    out: dict[str, tuple[int, np.ndarray]] = {}
    for number, fields in data_lines(path, comment):
        line = " ".join(fields)
        key, sep, rest = line.partition(":")
        key = key.strip()
        if not sep or not key or " " in key:
            raise FormatError(path, number, "expected 'KEY: values' (e.g. 'P0: 12 numbers')")
        if key in out:
            raise FormatError(path, number, f"key {key!r} repeats line {out[key][0]}")
        parts = rest.split()
        values = convert_fields(path, number, parts, [to_float] * len(parts), what=[key] * len(parts))
        out[key] = (number, np.asarray(values, dtype=np.float64))
    return out
