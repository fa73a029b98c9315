"""One exception hierarchy for misuse and bad input.

Expected outcomes of SLAM (too little parallax, a lost frame, a failed keyframe) are *statuses* in step
results, never exceptions. Exceptions are for things the user must fix: a missing path, a malformed line,
a bad configuration value. Every message names the file, line or parameter at fault.
"""

from __future__ import annotations

from pathlib import Path


class SlamkitError(Exception):
    """Base class of every error slamkit raises on purpose."""


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


class SessionError(SlamkitError):
    """A saved run or session is missing, damaged, or does not belong to the given source."""
