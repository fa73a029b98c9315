"""The rendered-sequence cache is checked at every open (issue 40): ``meta.json`` holds every file's size and
SHA-256, written with the files; a cache that does not match is rendered again with a one-line note. The
default sequence's cache goes through the same :func:`ensure_cached_sequence`, here with a 4-frame sequence."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from slamkit.sources.synthetic import DEFAULT_CAMERA, cache_problem, ensure_cached_sequence, synthetic_source

META = {"version": "test-v1", "frames": 4}


def _ensure(folder: Path) -> Path:
    return ensure_cached_sequence(folder, lambda: synthetic_source("sideways", frames=4, noise=1.0), META,
                                  DEFAULT_CAMERA, "the test sequence")


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_changed_cache_is_noticed_and_rendered_again(tmp_path, caplog):
    folder = _ensure(tmp_path / "seq")
    meta = json.loads((folder / "meta.json").read_text())
    assert len([f for f in meta["files"] if f.startswith("rgb/")]) == 4 and "rgb.txt" in meta["files"]
    assert cache_problem(folder, META) == ""
    good = _files(folder)
    mtimes = {p: p.stat().st_mtime_ns for p in folder.rglob("*")}
    with caplog.at_level(logging.WARNING, logger="slamkit.sources.synthetic"):
        assert _ensure(folder) == folder
    assert not caplog.records and {p: p.stat().st_mtime_ns for p in folder.rglob("*")} == mtimes  # reused

    image = sorted((folder / "rgb").iterdir())[2]
    name = f"rgb/{image.name}"
    damaged = bytearray(image.read_bytes())
    damaged[len(damaged) // 2] ^= 0x10  # one bit: same size, another checksum
    image.write_bytes(bytes(damaged))
    assert cache_problem(folder, META) == f"{name} does not match its checksum"
    image.write_bytes(bytes(damaged[:-100]))
    assert cache_problem(folder, META) == f"{name} has {len(damaged) - 100} bytes, not {len(damaged)}"
    with caplog.at_level(logging.WARNING, logger="slamkit.sources.synthetic"):
        _ensure(folder)
    notes = [r.getMessage() for r in caplog.records]
    assert len(notes) == 1 and "\n" not in notes[0] and name in notes[0] and "rendering it again" in notes[0]
    assert _files(folder) == {**good, "meta.json": _files(folder)["meta.json"]}  # the same frames, rendered again
    assert cache_problem(folder, META) == ""
    assert not [p for p in tmp_path.iterdir() if p.name != "seq"]  # no temporary or stale folder left


def test_every_kind_of_mismatch_is_named(tmp_path):
    folder = _ensure(tmp_path / "seq")
    assert cache_problem(tmp_path / "none", META) == "it does not exist"
    assert "other settings (frames=4)" in cache_problem(folder, {**META, "frames": 5})
    assert "camera.json is not the sequence's camera" in cache_problem(folder, META, DEFAULT_CAMERA.scaled(0.5))
    image = sorted((folder / "rgb").iterdir())[0]
    image.unlink()
    assert cache_problem(folder, META).startswith(f"rgb/{image.name} cannot be read")
    meta = json.loads((folder / "meta.json").read_text())
    del meta["files"]  # as the caches of slamkit before the checksums
    (folder / "meta.json").write_text(json.dumps(meta))
    assert cache_problem(folder, META) == "its meta.json lists no checksums (an older slamkit wrote it)"
    (folder / "meta.json").write_text("{not json")
    assert "meta.json or camera.json is unreadable" in cache_problem(folder, META)
    (folder / "meta.json").unlink()
    assert cache_problem(folder, META) == "meta.json is missing"
    _ensure(folder)
    assert cache_problem(folder, META) == ""
