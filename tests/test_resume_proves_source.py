"""Issue 50, items 2 and 3: each frame is fingerprinted when it is READ (its file's name, bytes, pixels and
SHA-256), and a resume proves its source against those fingerprints before one frame is processed.

Two rendered image folders with the same file names (the same motion, other image noise) stand in for "a KITTI
folder in place of a 7-Scenes one"; files swapped on disk stand in for images renamed into each other's place."""

from __future__ import annotations

import csv
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from slamkit import Slam, SlamConfig
from slamkit.cli import main
from slamkit.errors import SessionError
from slamkit.exporter import export
from slamkit.io.run_dir import RUN_MARKER, SESSION_MARKER, write_manifest
from slamkit.runner import run_to_folder
from slamkit.session import save_session
from slamkit.sources.synthetic import synthetic_source, write_tum_sequence

FRAMES = 16
CUT = 10
"""The interrupted run processes the first CUT of FRAMES frames."""


def _image_folder(root: Path, noise: float, seed: int) -> tuple[Path, str]:
    """The rendered ``sideways`` motion as a plain image folder ``root/images`` (PNG files named by their times,
    the same names for every noise/seed) and the ``--camera`` text of its exact camera."""
    src = synthetic_source("sideways", frames=FRAMES, noise=noise, seed=seed)
    tum = write_tum_sequence(src, root / "tum")
    folder = root / "images"
    folder.mkdir(parents=True)
    for p in sorted((tum / "rgb").glob("*.png")):
        shutil.copy(p, folder / p.name)
    shutil.rmtree(tum)
    cam = src.camera
    return folder, f"{cam.fx},{cam.fy},{cam.cx},{cam.cy}"


def _config(camera: str, **kw) -> SlamConfig:
    return SlamConfig().with_overrides(init_frames=8, camera=camera, **kw)


def _digest(folder: Path) -> dict:
    """Every file below ``folder`` (and the lock file beside it) by relative name: its SHA-256."""
    files = {p.relative_to(folder.parent).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
             for p in folder.rglob("*") if p.is_file()}
    return {**files, "siblings": sorted(p.name for p in folder.parent.iterdir())}


def _rows(run: Path) -> dict[int, dict]:
    with open(run / "frames.csv", newline="") as f:
        return {int(r["index"]): r for r in csv.DictReader(f)}


def _swap(a: Path, b: Path) -> None:
    da, db = a.read_bytes(), b.read_bytes()
    a.write_bytes(db)
    b.write_bytes(da)


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """(folder A, folder B with the same file names and other pixels, camera text, a run folder of the first CUT
    frames of A, interrupted: resumable)."""
    root = tmp_path_factory.mktemp("proves")
    a, camera = _image_folder(root / "a", noise=0.0, seed=0)
    b, _ = _image_folder(root / "b", noise=2.0, seed=1)
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
    run = root / "runs" / "run"
    outcome = run_to_folder(str(a), run, _config(camera, max_frames=CUT), evaluate_ate=False)
    assert outcome.saved and outcome.summary["frames"] == CUT  # still initializing: no map yet (exit code 3)
    return a, b, camera, run


# ----------------------------------------------------------------------------------------------- item 3
def test_fingerprints_are_those_of_what_was_read_not_of_the_files_at_saving(folders, tmp_path, capsys):
    """Two files swapped on disk after the run read them and before it is saved: frames.csv holds the hashes of
    the bytes that were read (not of the files as they are at saving), and export refuses in one line naming
    both frames and files instead of exporting each image under the other's pose."""
    a, _, camera, _ = folders
    folder = tmp_path / "images"
    shutil.copytree(a, folder)
    files = sorted(folder.glob("*.png"))
    read = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in files}
    slam = Slam(str(folder), _config(camera))
    slam.run()
    posed = [r.index for r in slam.records if r.rel_pose is not None]
    i, j = posed[2], posed[5]
    _swap(files[i], files[j])  # read already; not yet saved
    run = slam.save(tmp_path / "run")
    rows = _rows(run)
    for k, p in enumerate(files):  # every row: what was read, with its size and pixels
        assert rows[k]["file"] == p.name and rows[k]["sha256"] == read[p.name], k
        assert rows[k]["bytes"] == str(len(p.read_bytes()) if k not in (i, j) else
                                       len((files[j] if k == i else files[i]).read_bytes()))
        assert (rows[k]["width"], rows[k]["height"]) == ("640", "480")
    assert rows[i]["sha256"] != hashlib.sha256(files[i].read_bytes()).hexdigest()  # the file now is the other
    meta = json.loads((run / "session" / "session.json").read_text())
    assert meta["records"]["columns"]["sha256"][i] == read[files[i].name]  # the session holds them too
    assert main(["export", str(run), "--format", "colmap", "--frames", "all", "--out", str(tmp_path / "ds"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and not (tmp_path / "ds").exists()
    assert f"frame {i} (dataset frame {i}) is not the image the run posed: {files[i]} has other content" in err
    assert f"so are frame {j} ({files[j].name})" in err and "nothing was exported" in err
    _swap(files[i], files[j])  # put back: the same export now works
    assert export(run, tmp_path / "ds2", frames="all").num_images == len(posed)


def test_a_rendered_source_records_no_fingerprint():
    slam = Slam("synthetic:sideways?frames=3", SlamConfig())
    slam.run()
    assert all(r.sha256 == "" and r.fingerprint is None for r in slam.records)


# ----------------------------------------------------------------------------------------------- item 2
def test_resume_on_another_folder_of_the_same_names_is_refused_and_writes_nothing(folders, tmp_path, capsys):
    """The session of folder A resumed on folder B (same names, same count, same camera and times, other
    pixels): refused through the library, Slam.resume and the CLI, one line naming the first frame and file that
    differ, the run folder byte for byte as it was."""
    a, b, camera, run = folders
    before = _digest(run)
    first = sorted(b.glob("*.png"))[0].name
    with pytest.raises(SessionError, match=rf"frame 0 \({first}\) is not the image the run read: .*{first} has "
                                           r"other content than the run read \(SHA-256 differs.*so are frames 1 "
                                           rf".*and {CUT - 6} more; {CUT} of the {CUT} frames processed differ") as e:
        run_to_folder(str(b), run, _config(camera, max_frames=FRAMES), resume=True, evaluate_ate=False)
    assert "\n" not in str(e.value)
    with pytest.raises(SessionError, match="is not the image the run read"):
        Slam.resume(run, source=str(b), config={"max_frames": FRAMES})
    assert main(["run", str(b), "--out", str(run), "--resume", "--max-frames", str(FRAMES), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "is not the image the run read" in err
    assert _digest(run) == before


def test_files_swapped_between_a_run_and_its_resume_are_named(folders, tmp_path):
    a, _, camera, run = folders
    src = tmp_path / "images"
    shutil.copytree(a, src)
    files = sorted(src.glob("*.png"))
    _swap(files[3], files[7])
    meta_run = tmp_path / "run"
    shutil.copytree(run, meta_run)
    before = _digest(meta_run)
    with pytest.raises(SessionError, match=rf"frame 3 \({files[3].name}\) is not the image the run read: .*SHA-256 "
                                           rf"differs.*; so are frame 7 \({files[7].name}\); 2 of the {CUT} frames"):
        Slam.resume(meta_run, source=str(src), config={"max_frames": FRAMES})
    assert _digest(meta_run) == before
    _swap(files[3], files[7])
    assert Slam.resume(meta_run, source=str(src), config={"max_frames": FRAMES})._cursor == CUT


def test_resume_on_the_same_folder_continues(folders, tmp_path):
    a, _, camera, run = folders
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    outcome = run_to_folder(str(a), copy, _config(camera, max_frames=FRAMES), resume=True,
                            resume_overrides={"max_frames": FRAMES}, evaluate_ate=False)
    assert outcome.exit_code == 0 and outcome.resumed_after == CUT and outcome.complete
    assert outcome.summary["frames_posed"] == FRAMES
    rows = _rows(copy)
    files = sorted(a.glob("*.png"))
    assert len(rows) == FRAMES and all(rows[k]["sha256"] == hashlib.sha256(p.read_bytes()).hexdigest()
                                       for k, p in enumerate(files))


def test_resume_on_another_kind_of_source_is_refused(folders, tmp_path):
    """The session of a plain image folder resumed on a TUM-layout folder of the same name and frames: refused,
    saying which kind each is."""
    _, _, camera, run = folders
    tum = write_tum_sequence(synthetic_source("sideways", frames=FRAMES), tmp_path / "images")
    before = _digest(run)
    with pytest.raises(SessionError, match=r"recorded on a folder source \('folder/images'\), this is a tum "
                                           r"source \('tum/images'\)"):
        run_to_folder(str(tum), run, _config(camera, max_frames=FRAMES), resume=True, evaluate_ate=False)
    assert _digest(run) == before


def _as_before_issue_50(folder: Path) -> None:
    """Rewrite a session as slamkit wrote it before issue 50: no fingerprint columns in its records, no source
    kind (the manifests written again, as that slamkit would have)."""
    meta_path = folder / "session.json"
    meta = json.loads(meta_path.read_text())
    for name in ("file", "file_bytes", "width", "height", "sha256"):
        del meta["records"]["columns"][name]
    del meta["source"]["kind"]
    meta_path.write_text(json.dumps(meta, indent=1))
    write_manifest(folder, SESSION_MARKER)


def test_a_session_of_an_older_slamkit_is_proven_by_frames_csv_or_refused(folders, tmp_path):
    """Before issue 50 a session held no fingerprint: a run folder's frames.csv (measured when it was saved)
    proves its source instead, and the resumed run records them again; a session folder alone is refused."""
    a, _, camera, run = folders
    old = tmp_path / "old"
    shutil.copytree(run, old)
    _as_before_issue_50(old / "session")
    write_manifest(old, RUN_MARKER)
    src = tmp_path / "images"
    shutil.copytree(a, src)
    files = sorted(src.glob("*.png"))
    _swap(files[1], files[2])
    with pytest.raises(SessionError, match=rf"frame 1 \({files[1].name}\) is not the image the run read"):
        Slam.resume(old, source=str(src), config={"max_frames": FRAMES})
    _swap(files[1], files[2])
    slam = Slam.resume(old, source=str(src), config={"max_frames": FRAMES})
    assert [(r.sha256, r.file_bytes) for r in slam.records] == [(hashlib.sha256(p.read_bytes()).hexdigest(),
                                                                  p.stat().st_size) for p in files[:CUT]]
    bare = tmp_path / "bare"
    save_session(slam, bare)
    _as_before_issue_50(bare)
    with pytest.raises(SessionError, match=r"saved by an older slamkit without the fingerprints of the 10 frames it "
                                           r"read, and no frames.csv beside it"):
        Slam.resume(bare, source=str(src), config={"max_frames": FRAMES})


def test_fingerprints_survive_a_resume_bit_for_bit(folders, tmp_path):
    """The records restored from a session hold the fingerprints they were saved with (and save them again)."""
    a, _, camera, run = folders
    slam = Slam.resume(run, source=str(a))
    rows = _rows(run)
    assert [(r.file, str(r.file_bytes), r.sha256) for r in slam.records] == \
           [(rows[k]["file"], rows[k]["bytes"], rows[k]["sha256"]) for k in range(CUT)]
    assert np.all([r.width == 640 and r.height == 480 for r in slam.records])


def _video(path: Path, noise: float, seed: int) -> Path:
    """The rendered ``sideways`` motion (8 frames, 320x240) as an MJPG video."""
    import cv2

    src = synthetic_source("sideways", frames=8, noise=noise, seed=seed, scale=0.5)
    path.parent.mkdir(parents=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    assert writer.isOpened()
    for i in range(len(src)):
        writer.write(cv2.cvtColor(src[i].color, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def test_a_video_frame_is_fingerprinted_by_its_decoded_pixels_and_proven_on_resume(tmp_path):
    """A video's frames: the file's name and size, and each decoded frame's own SHA-256 (of the BGR pixels as
    decoded); resumed on another video of the same name, length and size, refused naming the frame."""
    a = _video(tmp_path / "a" / "clip.avi", noise=0.0, seed=0)
    b = _video(tmp_path / "b" / "clip.avi", noise=3.0, seed=1)
    slam = Slam(str(a), SlamConfig().with_overrides(camera="300"))
    slam.run(max_steps=5)
    recs = slam.records
    assert [r.file for r in recs] == ["clip.avi"] * 5 and {r.file_bytes for r in recs} == {a.stat().st_size}
    assert [(r.width, r.height) for r in recs] == [(320, 240)] * 5
    decoded = [np.ascontiguousarray(slam.source[k].color[..., ::-1]) for k in range(5)]  # RGB back to BGR
    assert [r.sha256 for r in recs] == [hashlib.sha256(d).hexdigest() for d in decoded]
    assert len({r.sha256 for r in recs}) == 5  # every frame its own
    session = save_session(slam, tmp_path / "session")
    assert Slam.resume(session, source=str(a))._cursor == 5
    with pytest.raises(SessionError, match=rf"frame 0 \(clip.avi\) is not the image the run read: frame 0 of {b} has "
                                           r"other content than the run read \(SHA-256 differs; \d+ bytes, the run "
                                           r"read \d+\); so are frames 1 .*5 of the 5 frames processed differ"):
        Slam.resume(session, source=str(b))
