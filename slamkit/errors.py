"""One exception hierarchy for misuse and bad input.

Expected outcomes of SLAM (too little parallax, a lost frame, a failed keyframe) are *statuses* in step
results, never exceptions. Exceptions are for things the user must fix: a missing path, a malformed line,
a bad configuration value. Every message names the file, line or parameter at fault.
"""

from __future__ import annotations

import dataclasses
import errno
import math
import numbers
import os
import re
from collections.abc import Mapping
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


C_INT_MAX = 2**31 - 1
"""The largest value of an integer setting without a range of its own: OpenCV, pycolmap and Ceres take a C
``int``, and a larger number raises deep inside them."""

_INTERVAL = re.compile(r"^\s*([\[(])\s*([^,]+?)\s*,\s*([^,]+?)\s*([\])])\s*$")
_BOUNDS = {"inf": math.inf, "-inf": -math.inf, "C_INT_MAX": C_INT_MAX}


def _interval(text: str) -> tuple[float, float, bool, bool]:
    """``"[0, 1)"`` -> (0.0, 1.0, low closed, high closed); bounds are numbers, ``inf`` or ``C_INT_MAX``."""
    m = _INTERVAL.match(text)
    if m is None:
        raise ValueError(f"not an interval: {text!r}")
    low, high = (_BOUNDS[b] if b in _BOUNDS else float(b) for b in (m[2], m[3]))
    return low, high, m[1] == "[", m[4] == "]"


def in_interval(value: float, text: str) -> bool:
    """Whether ``value`` lies in the interval ``text`` (``"[0, 1)"``, ``"(0, inf)"``, ``"[1, C_INT_MAX]"``)."""
    low, high, low_closed, high_closed = _interval(text)
    return (low < value or (low_closed and value == low)) and (value < high or (high_closed and value == high))


def is_seed(name: str) -> bool:
    """Whether a setting of this name is a random seed (any non-negative integer; :func:`native_seed`)."""
    return name == "seed" or name.endswith("_seed")


def check_number(value, name: str, interval: str | None = None, *, integer: bool = False, hint: str = "") -> None:
    """ConfigError naming ``name`` unless ``value`` is a finite number (an integer with ``integer``; at most
    :data:`C_INT_MAX` in magnitude unless ``name`` is a seed) within ``interval`` (``"[0, 1)"`` notation; None:
    any). NaN and infinity are refused before any comparison, which they would pass silently."""
    shown = f"{value!r}" if not isinstance(value, numbers.Number) or isinstance(value, numbers.Integral) else f"{value}"
    why = f"{name} must be {'an integer' if integer else 'a finite number'}"
    seed = is_seed(name.rsplit(".", 1)[-1])
    if interval is not None:
        low, high, low_closed, _ = _interval(interval)
        if high == math.inf:  # one-sided: ">= 1", with the C int bound of an integer that is not a seed
            why += f" {'>=' if low_closed else '>'} {low:g}" + (f" and <= {C_INT_MAX}" if integer and not seed else "")
        else:
            why += f" in {interval.replace('C_INT_MAX', str(C_INT_MAX))}"
    why += f" (got {shown}{'; ' + hint if hint else ''})"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ConfigError(why)
    if integer:
        if not isinstance(value, numbers.Integral):
            raise ConfigError(why)
        if abs(int(value)) > C_INT_MAX and not (seed and value >= 0):
            raise ConfigError(why if interval is not None else
                              f"{name} must be an integer of at most {C_INT_MAX} in magnitude (got {shown})")
    elif not math.isfinite(float(value)):
        raise ConfigError(why)
    if interval is not None and not in_interval(value, interval):
        raise ConfigError(why)


def check_fields(obj, prefix: str, ranges: Mapping[str, str | tuple[str, str] | Mapping] = {}, *,
                 nested: bool = True) -> None:
    """Check every number of the config dataclass ``obj`` where it is declared: ConfigError naming
    ``prefix.field`` for a value that is NaN or infinite, not an integer in an ``int`` field, beyond
    :data:`C_INT_MAX` (ints; seeds excepted), or outside the field's interval in ``ranges`` (``{field:
    "[0, 1)"}``, or ``{field: ("[0, 1)", "a hint for the message")}``). None is accepted where the field's type
    allows it; tuples of numbers are checked element by element. Config dataclasses inside ``obj`` are
    checked the same way (unless ``nested`` is False), with the ranges of ``ranges[field]`` when that is a
    mapping, else of their class attribute ``RANGES`` if they have one. Ranges name fields that exist (a typo
    is a bug)."""
    names = {f.name: f for f in dataclasses.fields(obj)}
    unknown = set(ranges) - set(names)
    if unknown:
        raise AssertionError(f"{type(obj).__name__}: ranges of unknown fields {sorted(unknown)}")
    for name, f in names.items():
        value, dotted = getattr(obj, name), f"{prefix}.{name}" if prefix else name
        spec = ranges.get(name)
        if dataclasses.is_dataclass(value):
            if nested:
                check_fields(value, dotted, spec if isinstance(spec, Mapping) else getattr(type(value), "RANGES", {}))
            continue
        interval, hint = (spec, "") if spec is None or isinstance(spec, str) else spec
        if value is None and "None" in str(f.type):
            continue
        if isinstance(value, tuple):
            for k, v in enumerate(value):
                if isinstance(v, numbers.Number):
                    check_number(v, f"{dotted}[{k}]", interval, integer=isinstance(v, numbers.Integral), hint=hint)
        elif isinstance(value, numbers.Number) and not isinstance(value, bool):
            check_number(value, dotted, interval, integer=str(f.type).startswith("int"), hint=hint)


def native_seed(seed: int) -> int:
    """A seed for OpenCV / pycolmap / Ceres, which take a 32-bit signed int: ``seed`` itself when it fits
    (``-1``, pycolmap's "random", included), else a value in ``[0, 2**31 - 1)`` derived from all of its bits by
    ``numpy.random.SeedSequence`` (deterministic: the same seed always gives the same runs)."""
    seed = int(seed)
    if -1 <= seed <= C_INT_MAX:
        return seed
    if seed < 0:
        raise ConfigError(f"seed must be a non-negative integer (got {seed})")
    import numpy as np

    return int(np.random.SeedSequence(seed).generate_state(1, np.uint64)[0] % C_INT_MAX)


class SessionError(SlamkitError):
    """A saved run or session is missing, damaged, or does not belong to the given source."""


class MapError(SessionError):
    """A saved run's map cannot be reused (``--map``): not a run, no map, another version or camera."""


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
