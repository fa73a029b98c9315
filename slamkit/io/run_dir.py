"""Run folders: how slamkit recognises its own output folders, decides whether ``--out`` may be written, and
keeps two processes from writing one folder at once.

- **Marker and manifest** (:mod:`slamkit.io.ownership`, re-exported here): ``.slamkit-run`` lists the size
  and SHA-256 of every file a save wrote; readers check a saved run against it (:mod:`slamkit.io.saved`), and
  it says "slamkit wrote this folder": only such a folder (of the output's kind, holding nothing else) or an
  empty one is ever replaced, ``overwrite`` or not (:func:`~slamkit.io.ownership.replace_refusal`).
- **``check_out_dir``** runs before any frame is processed: a missing or empty folder, or a slamkit run
  folder, is fine; a file, a folder of other files, a folder equal to, inside or containing the source, the
  home or current folder or one holding either are refused; the parent is created and a test file written,
  so an unwritable ``--out`` fails in a second, not after the whole run.
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
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from ..errors import OutputError, shown
from .ownership import (EXPORT_MARKER, LISTING_HEADER, MANIFEST_FORMATS, MANIFEST_VERSION, OUTPUT_KINDS,  # noqa: F401
                        PLOT_FILES, REPORT_FILES, REPORT_MARKER, REPORT_MARKS, REPORT_OWN_CONTENT, RUN_ENTRIES,
                        RUN_MARKER, SESSION_ENTRY, SESSION_MARKER, SWEEP_ENTRIES, SWEEP_FILE, TEMP_MARKER, TUM_HEADER,
                        _OWN_MARKERS, _even_with_overwrite, _is_session_dir, _resolved, file_sha256, foreign_entries,
                        found_text, is_own_report_file, is_replaceable, is_run_folder, protected_reason,
                        read_manifest, replace_refusal, save_id, write_listing, write_manifest)

__all__ = ["EXPORT_MARKER", "OUTPUT_KINDS", "REPORT_MARKER", "RUN_MARKER", "SESSION_MARKER", "TEMP_MARKER",
           "check_out_dir", "check_output", "foreign_entries", "is_replaceable", "is_run_folder", "mark_temporary",
           "out_dir_lock", "protected_reason", "read_manifest", "remove_stale_temporaries", "replace_refusal",
           "source_paths", "write_manifest"]

_PREFIX = re.compile(r"^(tum|kitti|7scenes|sevenscenes|euroc|video|folder):(.*)$", re.S)


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


def _overlap(out: Path, src: Path) -> str | None:
    o, s = _resolved(out), _resolved(src)
    if o == s:
        return "is the source"
    if o in s.parents:
        return "contains the source"
    if s.is_dir() and s in o.parents:
        return "is inside the source"
    return None


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
