"""Atomic file and folder writes: readers never see a half-written output.

A file is written to a temporary sibling in the same folder (same file system), flushed and fsynced, then
moved over the target with ``os.replace``, which is atomic on POSIX and Windows. If anything fails before the
rename, the temporary file is removed and the old file (if any) is left untouched. The new file gets the
permissions of the file it replaces, or ``0o666 & ~umask`` when it is new (``mkstemp`` would give ``0o600``).

A folder is written the same way with :func:`atomic_dir`: the caller fills a temporary sibling folder, which
then takes the place of the old one. The temporary folder, and the folder the old one is moved into, hold
slamkit's marker (:data:`slamkit.io.run_dir.TEMP_MARKER`), so a later clean-up removes only folders slamkit
made. Replacing a non-empty folder takes two renames (old -> backup, new -> target), so there is an instant in
which the target does not exist, but never one in which it is partial.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from ..errors import OutputError
from ..interrupt import signals_blocked
from .run_dir import TEMP_MARKER, mark_temporary, not_a_regular_file, replace_refusal

__all__ = ["atomic_write_text", "atomic_write_bytes", "atomic_dir"]


def _prepare_parent(path: Path) -> Path:
    """Create the parent folder of ``path`` if needed; OutputError naming it when that is impossible."""
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{parent}: output folder cannot be created ({e.strerror or e})") from e
    if not parent.is_dir():
        raise OutputError(f"{parent}: output folder is not a folder")
    return parent


def _new_file_mode(path: Path) -> int:
    try:
        return stat.S_IMODE(path.stat().st_mode)
    except OSError:
        mask = os.umask(0)
        os.umask(mask)
        return 0o666 & ~mask


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable; best effort (not every platform can open a folder)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _atomic_write(path: str | os.PathLike, chunks: Iterable[bytes]) -> Path:
    path = Path(path)
    parent = _prepare_parent(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a folder, cannot be replaced by a file")
    kind = not_a_regular_file(path)
    if kind:
        raise OutputError(f"{path}: is {kind}; slamkit replaces only regular files, so it was left as it is")
    mode = _new_file_mode(path)
    try:
        fd, tmp_name = tempfile.mkstemp(dir=parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as e:
        raise OutputError(f"{parent}: output folder is not writable ({e.strerror or e})") from e
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as f:
            for chunk in chunks:
                f.write(chunk)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException as e:
        written = _tree_size(tmp)
        existed = path.exists()
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(e, OSError):
            err = OutputError(write_failure(path, e, written, existed, "file"))
            err.os_error = e  # for an enclosing atomic_dir, which words it for the whole folder
            raise err from None
        raise
    _fsync_dir(parent)
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes | Iterable[bytes]) -> Path:
    """Write ``data`` (bytes, or an iterable of byte chunks) to ``path`` atomically; returns the path.

    Missing parent folders are created. An error while producing the chunks leaves the old file intact.
    Raises OutputError naming the folder or file when it cannot be written.
    """
    chunks = [data] if isinstance(data, (bytes, bytearray, memoryview)) else data
    return _atomic_write(path, (bytes(c) for c in chunks))


def atomic_write_text(path: str | os.PathLike, text: str | Iterable[str], encoding: str = "utf-8") -> Path:
    """Write ``text`` (a string, or an iterable of string chunks such as lines) to ``path`` atomically.

    Chunks are encoded and written as they come, so a generator that raises half-way leaves only a
    temporary file, which is removed: the old ``path`` stays as it was. Newlines are written as given.
    """
    chunks = [text] if isinstance(text, str) else text
    return _atomic_write(path, (c.encode(encoding) for c in chunks))


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, overwrite: bool = False, kind: str = "run") -> Iterator[Path]:
    """Context manager: fill a temporary sibling folder, which replaces ``path`` when the block succeeds.

    ``with atomic_dir("out/run1") as d: (d / "a.txt").write_text(...)`` — inside the block ``d`` is the
    temporary folder (``out/.run1.XXXX.tmp``). On a clean exit it is renamed to ``out/run1``; an old
    ``out/run1`` is moved aside first and deleted afterwards. If the block raises (an error, Ctrl-C, SIGTERM
    under :mod:`slamkit.interrupt`), the temporary folder is deleted and the old folder is untouched; the two
    renames run with those signals blocked, and are undone if anything still comes between them.

    Only slamkit's own folders are replaced: an existing ``path`` must be an empty folder or a slamkit
    ``kind`` output (``run``, ``session``, ``export``, ``report``) holding nothing else, and never the home
    folder, the current folder, one holding either or a file system root
    (:func:`slamkit.io.run_dir.replace_refusal`). This is checked when the block starts and again just before
    the old folder is moved aside; OutputError otherwise, and nothing is moved or deleted. ``overwrite`` is
    accepted for older callers and widens nothing. OutputError too when the parent is not writable or
    ``path`` is a file.
    """
    path = Path(path)
    parent = _prepare_parent(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: exists and is not a folder, will not replace it with one")
    refusal = replace_refusal(path, kind)
    if refusal:
        raise OutputError(f"{path}: {refusal}")
    try:
        tmp = Path(tempfile.mkdtemp(dir=parent, prefix=f".{path.name}.", suffix=".tmp"))
    except OSError as e:
        raise OutputError(f"{parent}: output folder is not writable ({e.strerror or e})") from e
    try:
        mark_temporary(tmp, path)  # only a folder holding this marker is ever removed as a stale temporary
    except OSError as e:
        _remove_tree(tmp)
        raise OutputError(write_failure(path, e, 0, path.exists(), "folder")) from None
    except BaseException:
        _remove_tree(tmp)
        raise
    existed = path.exists()
    try:
        yield tmp
        # mkdtemp creates 0o700; give the result the usual folder permissions
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o777 & ~mask)
        backup = _commit(tmp, path, parent, kind)
    except (OSError, OutputError) as e:  # e.g. a full disk while the block wrote: one line, old folder untouched
        written = _tree_size(tmp)
        _remove_tree(tmp)
        cause = e if isinstance(e, OSError) else getattr(e, "os_error", None)
        if cause is not None:
            raise OutputError(write_failure(path, cause, written, existed, "folder")) from None
        raise OutputError(str(e).replace(str(tmp), str(path))) from None  # never the temporary folder's name
    except BaseException:
        _remove_tree(tmp)
        raise
    if backup is not None:
        _remove_tree(backup)
    _fsync_dir(parent)


def _tree_size(p: Path) -> int:
    """Bytes in file or folder ``p`` (0 when it is gone)."""
    if p.is_file():
        return p.stat().st_size
    total = 0
    for root, _, files in os.walk(p):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, f)).st_size
    return total


def write_failure(path: Path, error: OSError, written: int, existed: bool, what: str) -> str:
    """One line for an OSError while writing ``path`` atomically: for a full disk, where, how much was
    written and is free, and that the previous ``path`` is intact (the write never replaced it)."""
    kept = (f"the previous {what} {path} is intact" if existed else f"nothing was written to {path}")
    if error.errno in (errno.ENOSPC, errno.EDQUOT):
        try:
            free = shutil.disk_usage(path.parent).free
        except OSError:
            free = 0
        return (f"no space left on the disk of {path.parent}: {written / 1e6:.1f} MB written when it ran out, "
                f"{free / 1e6:.1f} MB free in all: more is needed; {kept} — free some space (or choose another "
                "disk) and run the same command again")
    return f"{path}: cannot be written ({error.strerror or error}); {kept}"


def _remove_tree(folder: Path) -> None:
    """``rmtree`` that completes even when an interrupt arrives meanwhile (it is raised again afterwards), so
    no temporary folder survives Ctrl-C or SIGTERM."""
    pending: BaseException | None = None
    for _ in range(5):
        try:
            shutil.rmtree(folder, ignore_errors=True)
            break
        except KeyboardInterrupt as e:
            pending = e
    if pending is not None:
        raise pending


def _commit(tmp: Path, path: Path, parent: Path, kind: str) -> Path | None:
    """Rename ``tmp`` to ``path``, the old ``path`` moved into a backup folder first (returned, to delete),
    only when it is still a folder slamkit may replace (a file put into it since the block began keeps it)."""
    backup: Path | None = None
    try:
        with signals_blocked():
            if path.exists() or path.is_symlink():
                refusal = replace_refusal(path, kind)
                if refusal:
                    raise OutputError(f"{path}: {refusal}")
                backup = Path(tempfile.mkdtemp(dir=parent, prefix=f".{path.name}.", suffix=".old"))
                mark_temporary(backup, path)
                os.replace(path, backup / path.name)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp / TEMP_MARKER)  # the folder becomes the output: no longer a temporary
            os.replace(tmp, path)
    except BaseException as e:
        note = ""
        if backup is not None:
            moved = backup / path.name
            if moved.exists() and not path.exists():
                try:
                    os.replace(moved, path)
                except OSError:
                    note = f"; the old folder is kept at {moved}"
            if not note:
                _remove_tree(backup)
        if isinstance(e, OSError):
            raise OutputError(f"{path}: folder cannot be replaced ({e.strerror or e}){note}") from e
        raise
    return backup
