"""One exception hierarchy for misuse and bad input.

Expected outcomes of SLAM (too little parallax, a lost frame, a failed keyframe) are *statuses* in step
results, never exceptions. Exceptions are for things the user must fix: a missing path, a malformed line,
a bad configuration value. Every message names the file, line or parameter at fault.
"""

from __future__ import annotations

import errno
import os
import re
from pathlib import Path


_NUMPY_SCALAR = re.compile(r"np\.(?:float|int|uint|bool|str)_?\d*\(([^()]*)\)")


class SlamkitError(Exception):
    """Base class of every error slamkit raises on purpose. Its text never shows numpy's scalar reprs
    (``np.float64(0.5)`` reads as ``0.5``), however the message was formatted."""

    def __str__(self) -> str:
        return shown(_NUMPY_SCALAR.sub(r"\1", super().__str__()))


def shown(text: str | os.PathLike) -> str:
    """``text`` (a message or a path) as printable text: bytes of a file name that are not UTF-8 (held by Python
    as lone surrogates, ``os.fsdecode``) are shown as ``\\xfe``, so that printing or saving it cannot fail."""
    text = os.fspath(text) if isinstance(text, os.PathLike) else str(text)
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:  # a surrogate that is no escaped byte
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


class SourceError(SlamkitError):
    """A frame source cannot be opened: missing path, empty folder, no images matched, unknown layout."""


class ImageReadError(SourceError):
    """An image file (or video frame) could not be decoded."""

    def __init__(self, path: str | Path, reason: str = "could not be decoded (corrupt or not an image)"):
        self.path = Path(path)
        super().__init__(f"{self.path}: {reason}")


class FormatError(SlamkitError):
    """A text file does not follow its format. Names the file and the 1-based line number."""

    def __init__(self, path: str | Path, line: int | None, reason: str):
        self.path = Path(path)
        self.line = line
        self.reason = reason
        where = f"{self.path}:{line}" if line is not None else f"{self.path}"
        super().__init__(f"{where}: {reason}")


class CalibrationError(SlamkitError):
    """Camera intrinsics are invalid or do not fit the images."""


class AssociationError(SlamkitError):
    """Timestamps of two streams (images, ground truth, estimate) could not be associated well enough."""


class ConfigError(SlamkitError, ValueError):
    """A configuration value is out of range or contradicts another one. Names the parameter."""


class OutputError(SlamkitError):
    """An output folder or file cannot be written."""


class ArgumentTypeError(SlamkitError, TypeError):
    """A Python API argument (or config field) has the wrong type. Names the argument and the type given."""


def check_type(value, types: type | tuple[type, ...], name: str, hint: str = "") -> None:
    """ArgumentTypeError naming ``name`` unless ``value`` is an instance of ``types`` (``bool`` is not taken
    for a number)."""
    types = types if isinstance(types, tuple) else (types,)
    if isinstance(value, types) and not (isinstance(value, bool) and bool not in types):
        return
    names = {"Integral": "an int", "Real": "a number", "NoneType": "None", "bool_": "", "str": "a string",
             "bool": "True or False"}
    wanted = " or ".join(dict.fromkeys(n for n in (names.get(t.__name__, t.__name__) for t in types) if n))
    shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:37] + "..."
    raise ArgumentTypeError(f"{name}: expected {wanted}, got {type(value).__name__} {shown}"
                            + (f"; {hint}" if hint else ""))


class SessionError(SlamkitError):
    """A saved run or session is missing, damaged, or does not belong to the given source."""


def missing_reason(path: str | os.PathLike) -> str:
    """Why ``path`` cannot be opened, in a few words for a message: "does not exist", "is a loop of symbolic
    links", "is a symbolic link to X, which does not exist", or the OS's reason. "" when it exists."""
    try:
        os.stat(path)
        return ""
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "is a loop of symbolic links"
        if os.path.islink(path):
            return f"is a symbolic link to {os.readlink(path)}, which does not exist"
        if e.errno in (errno.ENOENT, errno.ENOTDIR):
            return "does not exist"
        return f"cannot be opened ({e.strerror or e})"
