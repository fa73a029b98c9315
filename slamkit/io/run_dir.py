"""Run folders: how slamkit recognises its own output folders, decides whether ``--out`` may be written, and
keeps two processes from writing one folder at once.

- **Marker and manifest.** Every saved run holds ``.slamkit-run`` (JSON: format, version, a save id, and the
  size and SHA-256 of every file the save wrote); a session folder holds ``.slamkit-session.json`` alike. The
  manifest lets readers check a saved run before reading it (:mod:`slamkit.io.saved`), and the marker says
  "slamkit wrote this folder": only such a folder is ever replaced without ``overwrite=True``.
- **``check_out_dir``** runs before any frame is processed: a missing or empty folder, or a slamkit run
  folder, is fine; a file, a folder of other files (without ``overwrite``), a folder equal to, inside or
  containing the source, the current folder or one holding it are refused; the parent is created and a
  test file written, so an unwritable ``--out`` fails in a second, not after the whole run.
- **``out_dir_lock``**: an exclusive ``flock`` on ``PARENT/.NAME.lock`` for the whole run; a second writer
  fails at once naming the folder and the other process. The OS releases it when a process dies, so a lock
  file left by a killed process never blocks.
- **Only what slamkit made is replaced.** The lock file begins with :data:`LOCK_MAGIC`; temporary and
  moved-aside folders hold :data:`TEMP_MARKER`. A file or folder that only has the name of one (the user's
  ``.NAME.lock``, ``.NAME.mine.tmp/``) is never taken, removed or overwritten; only regular files are replaced
  (:func:`not_a_regular_file`: never a device node, FIFO or link).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import re
import shutil
import stat
import tempfile
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path

from ..errors import OutputError, shown

__all__ = ["EXPORT_MARKER", "OUTPUT_KINDS", "REPORT_MARKER", "RUN_MARKER", "SESSION_MARKER", "TEMP_MARKER",
           "check_out_dir", "check_output", "is_replaceable", "is_run_folder", "mark_temporary", "out_dir_lock",
           "read_manifest", "remove_stale_temporaries", "source_paths", "write_manifest"]

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

_PREFIX = re.compile(r"^(tum|kitti|7scenes|sevenscenes|euroc|video|folder):(.*)$", re.S)


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


# ----------------------------------------------------------------------------------------------- --out checks
def source_paths(source) -> list[Path]:
    """The files or folders a source reads, from its spec (``PATH``, ``layout:PATH``, ``folder/*.png``) or
    from an opened source (its image paths' folders, its video file); synthetic sources read none."""
    out: list[Path] = []
    if isinstance(source, (str, os.PathLike)):
        text = str(source)
        if text == "default" or text.startswith("synthetic:"):
            return []
        m = _PREFIX.match(text) if not isinstance(source, Path) else None
        p = Path(m.group(2) if m else text).expanduser()
        if not p.exists() and any(c in p.name for c in "*?["):
            p = p.parent
        return [p] if p.exists() else []
    for name in ("path", "video_path", "root", "folder"):
        v = getattr(source, name, None)
        if isinstance(v, (str, os.PathLike)) and Path(v).exists():
            out.append(Path(v))
    paths = getattr(source, "paths", None)
    if paths is not None and len(paths):
        out.extend({Path(paths[0]).parent, Path(paths[-1]).parent})
        root = _dataset_root(str(getattr(source, "name", "")), Path(paths[0]))
        if root is not None:
            out.append(root)
    return out


def _dataset_root(name: str, image: Path) -> Path | None:
    """The dataset folder of an opened source whose images live below it (TUM's ``ROOT/rgb/``, KITTI's
    ``SEQ/image_0/``, EuRoC's ``mav0/cam0/data/``, 7-Scenes' ``SCENE/seq-01/``): the highest folder above
    ``image`` named like a part of the source's name (``tum/ROOT``, ``kitti/SEQ``, ``7scenes/SCENE/SEQ``), so
    the Python API refuses ``save_run(slam, "ROOT/depth")`` as the CLI does with the spec ``ROOT``."""
    parts = [p for p in name.split("/")[1:] if p]
    if "/" not in name or not parts:
        return None
    found = None
    for folder in list(image.parents)[:5]:
        if folder.name in parts:
            found = folder
    return found


def _resolved(p: Path) -> Path:
    return Path(os.path.realpath(p.expanduser()))


def _overlap(out: Path, src: Path) -> str | None:
    o, s = _resolved(out), _resolved(src)
    if o == s:
        return "is the source"
    if o in s.parents:
        return "contains the source"
    if s.is_dir() and s in o.parents:
        return "is inside the source"
    return None


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


def check_output(out: str | os.PathLike, kind: str = "run", sources: Iterable = (), overwrite: bool = False,
                 flag: str = "--out") -> Path:
    """The one check every command that writes goes through, before any work (OutputError naming ``flag``
    and the path otherwise). ``kind``: one of :data:`OUTPUT_KINDS`.

    Always refused, ``overwrite`` or not: an empty path; a path component longer than the file system
    allows; a file system root; a folder :func:`protected_reason` names (the home folder, the current folder,
    one holding either, a mount point); a path equal to, inside or holding a source's file or folder
    (symlinks resolved); a path inside a slamkit run, session or export folder (their files are listed in a
    manifest: writing among them breaks the run); a folder where a file is expected and the reverse; an
    existing folder holding anything but a slamkit ``kind`` output (:func:`replace_refusal`: nothing slamkit
    did not write is ever deleted). ``overwrite`` only lets ``gt`` (kind ``file``) replace an existing
    trajectory file slamkit wrote (or an empty file); a slamkit folder of ``kind`` is replaced without it.
    The parent folder is created and a test file written in it, so an unwritable place fails now.
    ``sources``: specs, paths or opened sources (:func:`source_paths`).
    """
    what = OUTPUT_KINDS[kind]
    noun = "file" if kind == "file" else f"{what} folder"
    if not isinstance(out, (str, os.PathLike)):
        raise TypeError(f"{flag}: expected a path (str or os.PathLike), got {type(out).__name__}")
    if str(out).strip() == "":
        raise OutputError(f"{flag} '': an empty path; give the {noun} to write")
    out = Path(out).expanduser()
    _check_name_lengths(out, flag)
    real = _resolved(out)
    if real.parent == real:
        raise OutputError(f"{flag} {out}: a file system root cannot be a {noun}")
    why = protected_reason(out) if kind != "file" else None
    if why:
        example = "runs/NAME" if why.endswith("current folder") else shown(out / "runs" / "NAME")
        raise OutputError(f"{flag} {out}: {why}; slamkit never replaces or writes into it{_even_with_overwrite(kind)} "
                          f"— give a new folder, e.g. {example}")
    for src in source_paths_all(sources):
        why = _overlap(out, src)
        if why:
            raise OutputError(f"{flag} {out}: {why} ({src}); slamkit never writes into its input — give a "
                              f"{noun} outside it")
    owner = _inside_output(real)
    if owner is not None:
        raise OutputError(f"{flag} {out}: is inside {owner}, a slamkit output whose files are listed in its "
                          f"manifest (writing there breaks it); give a {noun} outside it")
    try:
        exists = out.exists() or out.is_symlink()
    except OSError as e:
        raise OutputError(f"{flag} {out}: cannot be used ({e.strerror or e})") from e
    if exists:
        if kind == "file":
            if out.is_dir():
                raise OutputError(f"{flag} {out}: is a folder; give a file name")
            kind_of = not_a_regular_file(out)
            if kind_of:
                raise OutputError(f"{flag} {out}: is {kind_of}; slamkit replaces only regular files (even with "
                                  "--overwrite) — give a file name")
            if not overwrite:
                raise OutputError(f"{flag} {out}: exists; nothing was written — choose another file name, or "
                                  "pass --overwrite to replace it")
            if not _own_trajectory_file(out):
                raise OutputError(f"{flag} {out}: exists and is not a trajectory file slamkit wrote (its first line "
                                  "is not slamkit's TUM header), so it is kept, even with --overwrite; nothing was "
                                  "written — choose another file name (or remove it yourself if you mean to)")
        elif not out.is_dir():
            raise OutputError(f"{flag} {out}: exists and is not a folder; give a folder for the {what}")
        else:
            why = replace_refusal(out, kind)
            if why:
                raise OutputError(f"{flag} {out}: {why}")
    above = next((p for p in out.parents if p.exists()), None)
    if above is not None and not above.is_dir():
        raise OutputError(f"{flag} {out}: cannot be created, {above} is a file")
    _check_writable(out.parent, f"{flag} {out}")
    return out


def _own_trajectory_file(path: Path) -> bool:
    """``path`` is empty or begins with the header slamkit's TUM writer puts first (``gt``'s output)."""
    from .trajectory import TUM_HEADER  # here: trajectory imports atomic, which imports this module

    try:
        with open(path, "rb") as f:
            head = f.read(len(TUM_HEADER) + 1)
    except OSError:
        return False
    return head == b"" or head.rstrip(b"\r\n") == TUM_HEADER.encode()


def check_out_dir(out: str | os.PathLike, sources: Iterable = (), overwrite: bool = False,
                  flag: str = "--out") -> Path:
    """:func:`check_output` for a run folder (``run``, ``Slam.save``, ``save_run``)."""
    return check_output(out, "run", sources, overwrite, flag)


def not_a_regular_file(path: Path) -> str | None:
    """What ``path`` is when it exists and is not a regular file ("a device node", "a FIFO", "a symbolic link
    (to ...)", ...); None for a regular file or nothing."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    mode = st.st_mode
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISLNK(mode):
        return f"a symbolic link (to {os.readlink(path)})"
    for test, name in ((stat.S_ISCHR, "a device node"), (stat.S_ISBLK, "a device node"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder")):
        if test(mode):
            return name
    return "not a regular file"


def _foreign(out: Path, kind: str) -> list[str]:
    """Names in folder ``out`` that are not a ``kind`` output's."""
    names = sorted(os.listdir(out))
    if kind == "run":
        return foreign_entries(out)
    if kind == "session":
        own = (out / SESSION_MARKER).is_file() or _is_session_dir(out)
        return [n for n in names if not (own and SESSION_ENTRY.match(n))]
    if kind in ("export", "report"):
        return [] if (out / (EXPORT_MARKER if kind == "export" else REPORT_MARKER)).is_file() else names
    if (out / SWEEP_FILE).is_file():  # a sweep: its own entries (and the user's notes beside them) are fine
        return []
    return [n for n in names if not SWEEP_ENTRIES.match(n)]


def _inside_output(real: Path) -> Path | None:
    """The slamkit run, session or export folder that holds ``real`` (resolved), or None."""
    for p in real.parents:
        try:
            if any((p / m).is_file() for m in _OWN_MARKERS):
                return p
        except OSError:
            return None
    return None


def _check_name_lengths(out: Path, flag: str) -> None:
    """OutputError for a path component the file system refuses for its length (``File name too long``)."""
    try:
        limit = os.pathconf(next((p for p in [out, *out.parents] if p.exists()), Path(".")), "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 255
    for part in out.parts:
        if len(os.fsencode(part)) > limit:
            raise OutputError(f"{flag} {out}: the name {part[:20]}... has {len(os.fsencode(part))} bytes, more "
                              f"than the file system allows ({limit}); give a shorter name")


def source_paths_all(sources) -> list[Path]:
    if isinstance(sources, (str, os.PathLike)) or not isinstance(sources, Iterable):
        sources = [sources]
    out: list[Path] = []
    for s in sources:
        if s is not None:
            out.extend(source_paths(s))
    return out


def _check_writable(parent: Path, flag: str) -> None:
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{flag}: its folder {parent} cannot be created ({e.strerror or e})") from e
    if not parent.is_dir():
        raise OutputError(f"{flag}: {parent} is not a folder")
    try:
        fd, name = tempfile.mkstemp(dir=parent, prefix=".slamkit-write-test.", suffix=".tmp")
    except OSError as e:
        raise OutputError(f"{flag}: cannot write in {parent} ({e.strerror or e})") from e
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(name)


# ----------------------------------------------------------------------------------------------- lock
LOCK_MAGIC = b"slamkit-lock "
"""How a lock file slamkit made begins: a file of another name pattern's owner is never taken or removed."""


def _lock_path(out: Path) -> Path:
    real = _resolved(out)
    return real.parent / f".{real.name}.lock"


def _lock_record(pid: int) -> bytes:
    """The lock file's content: the marker and the holder's pid, always the same length (rewritten in place,
    so a reader never sees the file without its marker)."""
    return LOCK_MAGIC + f"{pid:>12}\n".encode()


def _create_lock_file(path: Path) -> None:
    """Create ``path`` already holding the marker (a filled temporary file hard-linked to the name, so no
    process ever sees an empty lock file); nothing when it exists."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".slamkit-lock.", suffix=".new")
    try:
        os.write(fd, _lock_record(os.getpid()))
        os.close(fd)
        fd = -1
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass
        except OSError:  # a file system without hard links: create exclusively, then fill at once
            with contextlib.suppress(FileExistsError):
                new = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                try:
                    os.write(new, _lock_record(os.getpid()))
                finally:
                    os.close(new)
    finally:
        if fd >= 0:
            os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def _not_our_lock(flag: str, out, path: Path, what: str) -> OutputError:
    return OutputError(f"{flag} {out}: {path} exists and is not a slamkit lock ({what}), so it is left as it is "
                       f"and nothing was written: slamkit locks {out} under that name — move it away, or choose "
                       "another name")


@contextlib.contextmanager
def out_dir_lock(out: str | os.PathLike, flag: str = "--out", what: str = "run folder") -> Iterator[Path]:
    """Hold an exclusive lock on run folder ``out`` (``PARENT/.NAME.lock``, ``flock``) for the block.

    A second holder, in this process or another, gets OutputError at once naming the folder and the pid
    written in the lock file. The lock file carries slamkit's marker (:data:`LOCK_MAGIC`): a file of that name
    without it (the user's, a FIFO, a link) is never opened for writing, taken or removed — OutputError
    instead. The lock file is removed when the block ends. Without ``fcntl`` (Windows) the block runs
    unlocked.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield Path(out)
        return
    path = _lock_path(Path(out))
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            try:
                _create_lock_file(path)
            except OSError as e:
                if e.errno in (errno.ENOSPC, errno.EDQUOT):
                    kept = (f"the previous {'file' if what == 'file' else 'folder'} {out} is intact" if
                            Path(out).exists() else f"nothing was written to {out}")
                    raise OutputError(f"no space left on the disk of {path.parent}: not even the lock file {path.name} "
                                      f"could be written; {kept} — free some space (or choose another disk) and run "
                                      "the same command again") from None
                raise OutputError(f"{flag} {out}: lock file {path} cannot be created ({e.strerror or e})") from e
            continue
        if not stat.S_ISREG(st.st_mode):
            raise _not_our_lock(flag, out, path, "not a regular file")
        try:
            fd = os.open(path, os.O_RDWR | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
        except FileNotFoundError:  # removed by its holder meanwhile
            continue
        except OSError as e:
            raise OutputError(f"{flag} {out}: lock file {path} cannot be opened ({e.strerror or e})") from e
        if not stat.S_ISREG(os.fstat(fd).st_mode) or os.pread(fd, len(LOCK_MAGIC), 0) != LOCK_MAGIC:
            os.close(fd)
            raise _not_our_lock(flag, out, path, "no slamkit marker in it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            other = _read_pid(fd)
            os.close(fd)
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputError(f"{flag} {out}: cannot lock {path} ({e.strerror or e})") from e
            who = f"process {other}" if other else "another process"
            raise OutputError(f"{flag} {out}: {who} is writing this {what} (lock {path}); wait for it to "
                              f"finish or choose another {'file' if what == 'file' else 'folder'}") from None
        try:  # the file may have been removed by the previous holder between our open and flock: retry
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        with contextlib.suppress(OSError):  # the pid is a courtesy for the message; a full disk must not stop us
            os.pwrite(fd, _lock_record(os.getpid()), 0)
        yield path
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # while still holding it, so no one locks a file that is about to vanish
        os.close(fd)


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 64, 0)[len(LOCK_MAGIC):].decode().strip()
        return int(text) if text.isdigit() else None
    except (OSError, ValueError):
        return None


# ----------------------------------------------------------------------------------------------- clean-up
TEMP_MARKER = ".slamkit-temporary"
"""File inside every temporary folder (``.NAME.*.tmp``) and moved-aside old folder (``.NAME.*.old``) slamkit
makes beside an output: only folders holding it are removed or put back by :func:`remove_stale_temporaries`.
It is removed from a temporary folder just before the folder takes the output's name."""
_TEMP_TEXT = "slamkit temporary folder"


def mark_temporary(folder: Path, of: Path) -> None:
    """Write :data:`TEMP_MARKER` into ``folder``, a temporary folder slamkit just made beside ``of``."""
    (folder / TEMP_MARKER).write_text(f"{_TEMP_TEXT} of {shown(of.name)} (pid {os.getpid()}); removed when it is done\n",
                                      encoding="utf-8")  # whatever the locale: a name may be any text


def is_own_temporary(folder: Path) -> bool:
    """True when ``folder`` is a real folder (no link) holding slamkit's :data:`TEMP_MARKER`."""
    try:
        if folder.is_symlink() or not folder.is_dir():
            return False
        marker = folder / TEMP_MARKER
        if marker.is_symlink() or not marker.is_file():
            return False
        with open(marker, "rb") as f:
            return f.read(len(_TEMP_TEXT)) == _TEMP_TEXT.encode()
    except OSError:
        return False


def remove_stale_temporaries(out: str | os.PathLike) -> list[Path]:
    """Under the lock: remove temporary folders a killed process left beside ``out`` (``.NAME.*.tmp``), and
    put back an old run that a crash left moved aside (``.NAME.*.old/NAME`` while ``NAME`` is missing). Only
    folders that carry slamkit's :data:`TEMP_MARKER` are touched: the user's ``.NAME.mine.tmp/`` is kept."""
    out = Path(out)
    parent, name = out.parent, out.name
    removed: list[Path] = []
    if not parent.is_dir():
        return removed
    for p in sorted(parent.glob(f".{glob_escape(name)}.*.old")):
        if not is_own_temporary(p):
            continue
        moved = p / name
        if moved.is_dir() and not out.exists():
            with contextlib.suppress(OSError):
                os.replace(moved, out)
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p)
    for p in parent.glob(f".{glob_escape(name)}.*.tmp"):
        if is_own_temporary(p):
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


def glob_escape(name: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", name)
