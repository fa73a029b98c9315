"""The app's Save keeps what the student put into the run folder since the last save.

``Slam.save`` replaces its run folder atomically (:func:`slamkit.io.save_run`): everything in the old folder
goes, including files a run folder may hold that the save itself does not write — the app's **Export HTML**
(``map.html``), ``slamkit eval``'s report. :func:`keeping_unsaved_files` copies those aside (a sibling
folder ``.NAME.kept-XXXX.files``) before the save and puts them back into the new folder after it, so an
export made before a Save survives it. A folder with files that are not a run's at all is still refused by
the save (``OutputError``: nothing is deleted).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from ..io.run_dir import RUN_ENTRIES, RUN_MARKER, read_manifest

WRITTEN_LATER = frozenset({"map.html", "report.md", "report.html", "evaluation.json", "plots"})
"""Entries of a run folder written after the save (Export HTML, ``slamkit eval``), when no manifest says."""


def unsaved_entries(run_dir: str | os.PathLike) -> list[str]:
    """Top-level names in the run folder ``run_dir`` that its save did not write (its manifest does not list
    them), which the next save would delete; empty when ``run_dir`` is missing or not a slamkit run."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir() or not (run_dir / RUN_MARKER).is_file():
        return []
    try:
        listed = set((read_manifest(run_dir) or {}).get("files", {}))
    except (OSError, ValueError):
        listed = set()
    written = {name.split("/", 1)[0] for name in listed} | {RUN_MARKER}
    if not listed:  # no readable manifest: what a run folder holds beside the save's own files
        written |= RUN_ENTRIES - WRITTEN_LATER
    return sorted(n for n in os.listdir(run_dir) if n not in written and n in RUN_ENTRIES)


@contextlib.contextmanager
def keeping_unsaved_files(run_dir: str | os.PathLike) -> Iterator[list[str]]:
    """Around a save into ``run_dir``: the names of :func:`unsaved_entries` are copied aside first and put
    back into the folder afterwards (when the save failed, the old folder still holds them and the copies
    are dropped). Yields those names."""
    run_dir = Path(run_dir)
    names = unsaved_entries(run_dir)
    if not names:
        yield []
        return
    aside = Path(tempfile.mkdtemp(dir=run_dir.parent, prefix=f".{run_dir.name}.kept-", suffix=".files"))
    for n in names:
        src = run_dir / n
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, aside / n)
    try:
        yield names
    finally:
        for n in names:
            if run_dir.is_dir() and not (run_dir / n).exists():
                os.replace(aside / n, run_dir / n)
        shutil.rmtree(aside, ignore_errors=True)


__all__ = ["unsaved_entries", "keeping_unsaved_files", "is_slamkit_map", "WRITTEN_LATER"]


def is_slamkit_map(path: Path) -> bool:
    """``path`` is a regular file holding the title of a map slamkit exported ("slamkit map")."""
    try:
        if path.is_symlink() or not path.is_file():
            return False
        with open(path, "rb") as f:
            return b"slamkit map" in f.read(1 << 20)
    except OSError:
        return False
