"""Which files and folders are slamkit's own: the markers and manifests of runs and sessions, the listings of
exports and reports, the marks of eval's report files, and from them the one rule of what may be replaced.

- **Marker and manifest.** Every saved run holds ``.slamkit-run`` (JSON: format, version, a save id, and the
  size and SHA-256 of every file the save wrote); a session folder holds ``.slamkit-session.json`` alike; an
  export (``.slamkit-export``) or a report folder (``.slamkit-report``) lists the files it wrote.
- **What may be replaced** (:func:`replace_refusal`, issue 50): an empty folder, or a slamkit output of that
  kind holding nothing else (:func:`foreign_entries`); never the home folder, a file system root or mount
  point, the current folder or one holding the home or current folder (:func:`protected_reason`), whatever
  they hold. ``overwrite`` widens nothing: slamkit never deletes a file it did not write.
  :func:`slamkit.io.run_dir.check_output` asks it before any work, :func:`slamkit.io.atomic.atomic_dir` again
  before it moves a folder aside.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import time
import uuid
from pathlib import Path

from ..errors import shown

RUN_MARKER = ".slamkit-run"
SESSION_MARKER = ".slamkit-session.json"
MANIFEST_FORMATS = {RUN_MARKER: "slamkit-run", SESSION_MARKER: "slamkit-session-files"}
MANIFEST_VERSION = 1

RUN_ENTRIES = frozenset({
    RUN_MARKER, "trajectory_tum.txt", "keyframes_tum.txt", "trajectory_kitti.txt", "sparse", "points.ply",
    "summary.json", "frames.csv", "camera.txt", "groundtruth_tum.txt", "session", "segments",
    # written later by `slamkit eval` into the run folder
    "report.md", "report.html", "evaluation.json", "plots", "map.html"})
"""Top-level names a slamkit run folder may hold: anything else is the user's, and the folder is not replaced."""

SESSION_ENTRY = re.compile(r"^(\.slamkit-session\.json|session\.json|state\.npz|segment_\d+)$")


TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"
"""The first line of every TUM file slamkit writes (:func:`slamkit.io.trajectory.write_tum`): ``gt --overwrite``
replaces only a file that begins with it."""
TEMP_MARKER = ".slamkit-temporary"
"""File inside every temporary folder (``.NAME.*.tmp``) and moved-aside old folder (``.NAME.*.old``) slamkit
makes beside an output: only folders holding it are removed or put back by :func:`remove_stale_temporaries`.
It is removed from a temporary folder just before the folder takes the output's name."""


def _resolved(p: Path) -> Path:
    return Path(os.path.realpath(p.expanduser()))


OUTPUT_KINDS = {"run": "slamkit run", "session": "slamkit session", "export": "slamkit export",
                "sweep": "slamkit sweep", "report": "slamkit report", "file": "file"}
"""What each command writes: a run folder (``run``, ``save``, the notebook's Save), a session folder
(``Slam.save_session``), an export folder, a sweep folder (``ablate``), a report folder (``eval --out``) or a
single file (``gt``).
:func:`check_output` knows each kind's own outputs."""

EXPORT_MARKER = ".slamkit-export"
"""File marking a folder written by :func:`slamkit.exporter.export`."""
REPORT_MARKER = ".slamkit-report"
"""File marking a folder that holds a report written by ``slamkit eval --out`` (replaced as a whole)."""
SWEEP_FILE = "sweep.json"
SWEEP_ENTRIES = re.compile(r"^(sweep\.json|runs|results\.(csv|parquet|md)|effects\.png|\..*\.tmp)$")
_SWEEP_TEMPORARY = re.compile(r"^(runs|\..*\.tmp)$")

_OWN_MARKERS = (RUN_MARKER, SESSION_MARKER, EXPORT_MARKER, REPORT_MARKER)


# ----------------------------------------------------------------------------------------------- manifest
def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_manifest(folder: str | os.PathLike, marker: str = RUN_MARKER) -> Path:
    """Write ``folder/marker``: the size and SHA-256 of every file below ``folder`` (paths relative, with
    ``/``), a unique save id and the time. Called last, inside the temporary folder of an atomic save."""
    folder = Path(folder)
    files = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p != folder / marker and p.relative_to(folder).as_posix() != TEMP_MARKER:
            files[p.relative_to(folder).as_posix()] = {"size": p.stat().st_size, "sha256": file_sha256(p)}
    meta = {"format": MANIFEST_FORMATS[marker], "version": MANIFEST_VERSION, "id": uuid.uuid4().hex,
            "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "files": files}
    path = folder / marker
    path.write_text(json.dumps(meta, indent=1))
    return path


def read_manifest(folder: str | os.PathLike, marker: str = RUN_MARKER) -> dict | None:
    """The manifest in ``folder`` (None when there is none: a folder saved before manifests existed).
    ValueError (or OSError) with the reason when it cannot be read; :mod:`slamkit.io.saved` names the file."""
    path = Path(folder) / marker
    if not path.is_file():
        return None
    meta = json.loads(path.read_bytes().decode("utf-8"))
    if not isinstance(meta, dict) or meta.get("format") != MANIFEST_FORMATS[marker]:
        raise ValueError(f"not a slamkit manifest (format {meta.get('format') if isinstance(meta, dict) else meta!r})")
    if meta.get("version") != MANIFEST_VERSION or not isinstance(meta.get("files"), dict):
        raise ValueError(f"manifest version {meta.get('version')!r} not understood (this slamkit reads "
                         f"{MANIFEST_VERSION})")
    return meta


def save_id(folder: str | os.PathLike) -> str | None:
    """The id of the save that wrote the run in ``folder`` (None: none, or unreadable)."""
    try:
        return (read_manifest(folder) or {}).get("id")
    except (OSError, ValueError):
        return None


# ----------------------------------------------------------------------------------------------- what may be replaced
REPORT_FILES = ("report.md", "report.html", "evaluation.json", "map.html")
"""Files ``slamkit eval`` (and the app's Export HTML: ``map.html``) writes into a run or report folder."""
PLOT_FILES = frozenset({"trajectory.png", "error_over_time.png", "timings.png"})
"""What ``slamkit eval`` writes into ``plots/``."""
REPORT_MARKS = {"report.md": "<!-- slamkit eval report -->", "report.html": '<meta name="generator" content="slamkit eval">',
                "map.html": "<!-- slamkit eval map -->"}
"""The mark each report file's text carries (:mod:`slamkit.eval.report` writes it)."""
REPORT_OWN_CONTENT = {  # what makes a file slamkit's: its mark, or the text of a report an older slamkit wrote
    "report.md": (REPORT_MARKS["report.md"], "(Umeyama on the matched camera centres), timestamps matched within"),
    "report.html": (REPORT_MARKS["report.html"], "<title>slamkit evaluation</title>"),
    "evaluation.json": ('"generator": "slamkit eval"', '"alignment": "sim3"'),
    "map.html": (REPORT_MARKS["map.html"], "slamkit map"),
}
LISTING_HEADER = "# files written (paths relative to this folder, one a line):"
"""Line of an export's or report's marker file after which the files that save wrote are listed."""


def is_own_report_file(path: Path) -> bool:
    """True when ``path`` (a regular file named like one of :data:`REPORT_FILES`) holds slamkit's mark."""
    try:
        if path.is_symlink() or not path.is_file():
            return False
        with open(path, "rb") as f:
            text = f.read(1 << 20).decode("utf-8", "replace")
    except OSError:
        return False
    return any(mark in text for mark in REPORT_OWN_CONTENT.get(path.name, ()))


def _is_session_dir(path: Path) -> bool:
    try:
        meta = json.loads((path / "session.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("format") == "slamkit-session"


def write_listing(folder: str | os.PathLike, marker: str, title: str) -> Path:
    """Write ``folder/marker``: ``title`` and the relative path of every file below ``folder`` (called last,
    inside the temporary folder of an atomic save), so a later save replaces only files this one wrote."""
    folder = Path(folder)
    files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                   if p.is_file() and p.relative_to(folder).as_posix() not in (marker, TEMP_MARKER))
    path = folder / marker
    path.write_text(f"{title}\n{LISTING_HEADER}\n" + "".join(f"{f}\n" for f in files),
                    encoding="utf-8", errors="surrogateescape")
    return path


def _listing(folder: Path, marker: str) -> set[str] | None:
    """The files ``folder``'s marker lists (a run's or session's manifest, an export's or report's listing);
    None when it lists none (saved before listings existed) or cannot be read."""
    if marker in MANIFEST_FORMATS:
        try:
            meta = read_manifest(folder, marker)
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        return None if meta is None else set(meta["files"])
    try:
        lines = (folder / marker).read_text(encoding="utf-8", errors="surrogateescape").splitlines()
    except OSError:
        return None
    return set(lines[lines.index(LISTING_HEADER) + 1:]) if LISTING_HEADER in lines else None


def _report_entry(rel: str, path: Path) -> bool:
    """``rel`` is a file or folder ``slamkit eval`` wrote: a report file with its mark, ``plots/`` or a plot."""
    if rel in REPORT_FILES:
        return is_own_report_file(path)
    if rel == "plots":
        return path.is_dir() and not path.is_symlink()
    return rel.startswith("plots/") and rel[6:] in PLOT_FILES and path.is_file() and not path.is_symlink()


def _not_listed(folder: Path, listed: set[str], allowed) -> list[str]:
    """Entries below ``folder`` that slamkit did not write: files (links, sockets, ...) neither in ``listed``
    nor ``allowed(rel, path)``, and folders holding no listed file (one entry, ``NAME/``)."""
    holders = {f.rsplit("/", i)[0] for f in listed for i in range(1, f.count("/") + 1)}
    foreign: list[str] = []

    def walk(sub: Path, prefix: str) -> None:
        for name in sorted(os.listdir(sub)):
            rel, path = prefix + name, sub / name
            if path.is_dir() and not path.is_symlink():
                if rel in holders or allowed(rel, path):
                    walk(path, rel + "/")
                else:
                    foreign.append(rel + "/")
            elif rel not in listed and not allowed(rel, path):
                foreign.append(rel)

    walk(folder, "")
    return foreign


_OWN_TOP = {
    "export": frozenset({".slamkit-export", "images", "sparse", "transforms.json", "sparse_pc.ply"}),
    "report": frozenset({".slamkit-report", "plots", *REPORT_FILES}),
}
"""What an export or report folder saved before listings existed holds (top level)."""


def foreign_entries(path: str | os.PathLike, kind: str = "run") -> list[str]:
    """Entries of folder ``path`` that slamkit did not write as a ``kind`` output (:data:`OUTPUT_KINDS`), as
    paths relative to it (``notes.txt``, ``sparse/mine.txt``, ``old/``); empty when the folder is empty or
    holds nothing but a slamkit ``kind`` output. A run or session is recognised by its marker (files in its
    manifest are its own) or, saved before markers existed, by its ``session.json``; an export or a report by
    its marker (files in its listing). A run folder (or a session folder given to a run) may also hold what
    ``slamkit eval`` and the app wrote later (:data:`REPORT_FILES` with slamkit's mark, ``plots/``). Every
    other entry is the user's: a folder holding one is never replaced (:func:`replace_refusal`)."""
    path = Path(path)
    names = sorted(os.listdir(path))
    if not names:
        return []
    return _as_entries(path, _foreign_names(path, names, kind))


def _as_entries(path: Path, names: list[str]) -> list[str]:
    """``names`` with ``/`` after each (real) folder's name: ``thesis/``."""
    return [n + "/" if "/" not in n and (path / n).is_dir() and not (path / n).is_symlink() else n for n in names]


def _foreign_names(path: Path, names: list[str], kind: str) -> list[str]:
    if kind in ("run", "session"):
        marker = next((m for m in ((RUN_MARKER, SESSION_MARKER) if kind == "run" else (SESSION_MARKER,))
                       if (path / m).is_file()), None)
        if marker is None and kind == "run" and (path / "session" / "session.json").is_file() \
                and _is_session_dir(path / "session"):
            marker = RUN_MARKER  # a run saved before markers existed
        elif marker is None and _is_session_dir(path):
            marker = SESSION_MARKER  # a session saved before markers existed
        if marker is None:
            return names
        extra = _report_entry if kind == "run" else (lambda rel, p: False)

        def allowed(rel: str, p: Path) -> bool:
            return rel == marker or rel.startswith(f"{RUN_MARKER}.") or extra(rel, p)

        listed = _listing(path, marker) if (path / marker).is_file() else None
        if listed is not None:
            return _not_listed(path, listed, allowed)
        if marker == SESSION_MARKER:
            return [n for n in names if not (SESSION_ENTRY.match(n) or allowed(n, path / n))]
        return [n for n in names if not (allowed(n, path / n) or n in RUN_ENTRIES - {"plots", *REPORT_FILES})]
    if kind in ("export", "report"):
        marker = EXPORT_MARKER if kind == "export" else REPORT_MARKER
        if not (path / marker).is_file():
            return names
        listed = _listing(path, marker)
        allowed = (lambda rel, p: rel == marker or (kind == "report" and _report_entry(rel, p)))
        if listed is not None:
            return _not_listed(path, listed, allowed)
        return [n for n in names if n not in _OWN_TOP[kind]]
    if kind == "sweep":  # a sweep writes its own files among others (never replaces or removes one)
        if (path / SWEEP_FILE).is_file():
            return []
        own = SWEEP_ENTRIES if (path / "runs").is_dir() else _SWEEP_TEMPORARY  # a sweep not yet marked: its runs/
        return [n for n in names if not own.match(n)]  # the user's results.csv alone is never written over
    raise ValueError(f"kind must be one of {', '.join(OUTPUT_KINDS)} (got {kind!r})")


def is_run_folder(path: str | os.PathLike) -> bool:
    """True when ``path`` is a folder slamkit saved a run in: its marker, or the session of a run saved
    before markers existed. Another tool's results folder (trajectory files, a report.md) is not."""
    path = Path(path)
    try:
        return (path / RUN_MARKER).is_file() or ((path / "session" / "session.json").is_file()
                                                 and _is_session_dir(path / "session"))
    except OSError:
        return False


def _home_folders() -> list[Path]:
    homes = []
    with contextlib.suppress(RuntimeError, KeyError, OSError):
        homes.append(Path.home())
    if os.environ.get("HOME"):
        homes.append(Path(os.environ["HOME"]))
    return [_resolved(h) for h in homes]


def protected_reason(path: str | os.PathLike) -> str | None:
    """Why folder ``path`` is never an output slamkit replaces or writes into, even when it holds a slamkit
    output: a file system root or mount point, the home folder or one holding it, the current folder or one
    holding it. None otherwise. (A source folder is refused by :func:`check_output`, which knows the
    sources.)"""
    real = _resolved(Path(path))
    if real.parent == real:
        return "is a file system root"
    for home in _home_folders():
        if real == home:
            return "is the home folder"
        if real in home.parents:
            return f"holds the home folder {home}"
    try:
        cwd = _resolved(Path.cwd())
    except OSError:  # the current folder was removed: nothing to protect there
        cwd = None
    if real == cwd:
        return "is the current folder"
    if cwd is not None and real in cwd.parents:
        return "holds the current folder"
    with contextlib.suppress(OSError):
        if os.path.ismount(real):
            return "is the root of a mounted file system"
    return None


def found_text(entries: list[str]) -> str:
    """A few of ``entries`` and their count, for a message: ``notes.txt`` or ``5 entries: a, b, c and 2 more``."""
    if len(entries) == 1:
        return shown(entries[0])
    more = f" and {len(entries) - 3} more" if len(entries) > 3 else ""
    return f"{len(entries)} entries: {', '.join(shown(e) for e in entries[:3])}{more}"


def replace_refusal(path: str | os.PathLike, kind: str = "run") -> str | None:
    """Why folder ``path`` may not be replaced by (or, a sweep, written into as) a ``kind`` output — the one
    rule every writer goes through, :func:`check_output` before any work and
    :func:`slamkit.io.atomic.atomic_dir` again just before it moves the old folder aside: None when ``path``
    is missing, an empty folder or a slamkit ``kind`` output holding nothing else (:func:`foreign_entries`);
    else the reason, starting with what was found there. ``overwrite`` never widens it: a folder slamkit did
    not write is never deleted."""
    path = Path(path)
    even = _even_with_overwrite(kind)
    why = protected_reason(path) if (path.exists() or path.is_symlink()) else None
    if why:
        return f"{why}; slamkit never replaces or writes into it{even} — give a new folder inside it"
    try:
        if not (path.exists() or path.is_symlink()):
            return None
        if not path.is_dir():
            return "exists and is not a folder"
        foreign = foreign_entries(path, kind)
    except OSError as e:
        return f"cannot be listed ({e.strerror or e})"
    if not foreign:
        return None
    what = OUTPUT_KINDS[kind]
    if _is_kind(path, kind):
        return (f"is a {what} folder but also holds what slamkit did not write ({found_text(foreign)}); nothing was "
                f"written — slamkit never deletes a file it did not write{even}: move them out, or choose another "
                "folder")
    return (f"folder is not empty and is not a {what} ({found_text(foreign)}); nothing was written — choose "
            f"another folder, or a new folder inside it; slamkit replaces only its own folders{even} (remove it "
            "yourself if you mean to)")


def _even_with_overwrite(kind: str) -> str:
    """", even with --overwrite" for the outputs of the commands that have the flag (``run``: a run folder;
    ``gt``: a file), else "": no message advises a flag its command does not have."""
    return ", even with --overwrite" if kind in ("run", "file") else ""


def _is_kind(path: Path, kind: str) -> bool:
    """``path`` carries the marker of a slamkit ``kind`` output (or, a run or session saved before markers
    existed, its ``session.json``)."""
    if kind == "run":
        return is_run_folder(path) or _is_kind(path, "session")
    if kind == "session":
        return (path / SESSION_MARKER).is_file() or _is_session_dir(path)
    marker = {"export": EXPORT_MARKER, "report": REPORT_MARKER, "sweep": SWEEP_FILE}.get(kind)
    return marker is not None and (path / marker).is_file()


def is_replaceable(path: str | os.PathLike, kind: str = "run") -> bool:
    """True when ``path`` is missing, an empty folder, or a ``kind`` folder slamkit wrote (nothing else in it),
    and not a protected folder (:func:`replace_refusal`)."""
    return replace_refusal(path, kind) is None


__all__ = ["EXPORT_MARKER", "OUTPUT_KINDS", "REPORT_FILES", "REPORT_MARKER", "RUN_MARKER", "SESSION_MARKER",
           "TEMP_MARKER", "TUM_HEADER", "file_sha256", "foreign_entries", "is_own_report_file", "is_replaceable",
           "is_run_folder", "protected_reason", "read_manifest", "replace_refusal", "save_id", "write_listing",
           "write_manifest"]
