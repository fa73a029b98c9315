"""Issue 50: ``--overwrite`` (and every writer that replaces a folder) never deletes what slamkit did not make.

Only an empty folder or slamkit's own output of that kind (its marker, nothing else in it) is replaced; the
home folder, the current folder, a folder holding either, and a source are refused by name, even when they
hold slamkit's marker. Each case checks the exit code or error, the one-line message, and that every byte of
what was there is still there.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import slamkit
from slamkit.cli import main
from slamkit.config import SlamConfig
from slamkit.errors import OutputError
from slamkit.eval.report import evaluate_run
from slamkit.exporter import export
from slamkit.io.atomic import atomic_dir
from slamkit.io.run import save_run
from slamkit.io.run_dir import (EXPORT_MARKER, REPORT_MARKER, RUN_MARKER, check_output, foreign_entries,
                                is_replaceable, save_id)
from slamkit.io.saved import check_run
from slamkit.runner import EXIT_USAGE
from slamkit.sources.synthetic import cache_root

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 10
"""Frames of the default sequence in the runs here: all 10 are posed (a map to export and evaluate)."""


def _digest(folder: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file below ``folder`` (equal before and after: nothing was lost)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _cli(*args: str, cwd: Path, home: Path) -> subprocess.CompletedProcess:
    """``python -m slamkit ARGS`` in ``cwd`` with ``HOME=home`` (the caches stay where they are)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "HOME": str(home)}
    env.setdefault("SLAMKIT_CACHE", str(cache_root()))
    return subprocess.run([sys.executable, "-m", "slamkit", *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd, env=env)


def _home(tmp_path: Path) -> Path:
    """A throwaway folder standing in for a home folder, with a file in it."""
    home = tmp_path / "home"
    (home / "thesis").mkdir(parents=True)
    (home / "thesis" / "thesis.tex").write_text("\\chapter{Results}\n")
    (home / "notes.txt").write_text("do not lose\n")
    return home


@pytest.fixture(scope="module")
def slam():
    """A finished 10-frame run of the default sequence, every frame posed."""
    s = slamkit.Slam(slamkit.open_source("default", max_frames=FRAMES), SlamConfig())
    for _ in s:
        pass
    s.finish()
    assert s.summary()["frames_posed"] == FRAMES
    return s


@pytest.fixture(scope="module")
def saved_run(slam, tmp_path_factory) -> Path:
    return slam.save(tmp_path_factory.mktemp("saved") / "run")


@pytest.fixture
def run(saved_run, tmp_path) -> Path:
    """A copy of the saved run, to change."""
    return Path(shutil.copytree(saved_run, tmp_path / "run"))


# ----------------------------------------------------------------------------------------------- the home folder
def test_run_overwrite_on_the_home_folder_is_refused_from_the_shell(tmp_path):
    home = _home(tmp_path)
    (tmp_path / "work").mkdir()
    before = _digest(home)
    for out in (str(home), "~"):  # "~" as the shell passes it when quoted: expanded by slamkit itself
        r = _cli("run", "default", "--out", out, "--overwrite", "--max-frames", "3", "-q", cwd=tmp_path / "work",
                 home=home)
        line = _one_line(r.stderr)
        assert r.returncode == EXIT_USAGE and f"{home}: is the home folder" in line and "even with --overwrite" in line
        assert _digest(home) == before and sorted(p.name for p in home.iterdir()) == ["notes.txt", "thesis"]
    assert not list(tmp_path.glob(".home*"))  # no temporary or moved-aside folder beside it


def test_the_home_folder_is_refused_even_when_it_holds_a_slamkit_run(slam, tmp_path, monkeypatch):
    home = _home(tmp_path)
    monkeypatch.setenv("HOME", str(home))
    (home / RUN_MARKER).write_text("{}")  # a marker does not make a home folder replaceable
    before = _digest(home)
    for write in (lambda: slam.save(home), lambda: save_run(slam, home, overwrite=True),
                  lambda: save_run(slam, "~", overwrite=True), lambda: slam.save_session(home)):
        with pytest.raises(OutputError, match="is the home folder"):
            write()
    with pytest.raises(OutputError, match="holds the home folder"):
        save_run(slam, tmp_path, overwrite=True)
    with pytest.raises(OutputError, match="is the home folder"), atomic_dir(home, overwrite=True) as d:
        (d / "x").write_text("never")
    assert _digest(home) == before


def test_the_current_folder_and_its_parents_are_refused(slam, tmp_path, monkeypatch):
    here = tmp_path / "a" / "b"
    here.mkdir(parents=True)
    (here / "data.csv").write_text("1,2\n")
    monkeypatch.chdir(here)
    before = _digest(tmp_path)
    for out, why in ((".", "is the current folder"), ("..", "holds the current folder"),
                     (str(tmp_path), "holds the current folder")):
        with pytest.raises(OutputError, match=why):
            save_run(slam, out, overwrite=True)
        for kind in ("export", "report", "sweep", "session"):
            with pytest.raises(OutputError, match=why):
                check_output(out, kind, overwrite=True)
    with pytest.raises(OutputError, match="is the current folder"), atomic_dir(here, overwrite=True):
        pass
    r = _cli("run", "default", "--out", "..", "--overwrite", "--max-frames", "3", "-q", cwd=here, home=tmp_path / "h")
    assert r.returncode == EXIT_USAGE and "--out ..: holds the current folder" in _one_line(r.stderr)
    assert _digest(tmp_path) == before


def test_a_file_system_root_is_refused():
    with pytest.raises(OutputError, match="file system root"):
        check_output("/", "run", overwrite=True)
    assert not is_replaceable("/")


# ----------------------------------------------------------------------------------------------- a user's folder
def test_overwrite_never_replaces_a_folder_of_other_files(slam, tmp_path, capsys):
    mine = _home(tmp_path)  # any folder of the user's: a thesis, a dataset, a results folder
    before = _digest(mine)
    code = main(["run", "default", "--out", str(mine), "--overwrite", "--max-frames", "3", "-q"])
    line = _one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "folder is not empty and is not a slamkit run (2 entries: notes.txt, thesis/)" in line
    assert "even with --overwrite" in line and "another folder" in line
    with pytest.raises(OutputError, match=r"not a slamkit run \(2 entries: notes.txt, thesis/\)"):
        save_run(slam, mine, overwrite=True)
    with pytest.raises(OutputError, match="not a slamkit run"), atomic_dir(mine, overwrite=True) as d:
        (d / "x").write_text("never")
    with pytest.raises(OutputError, match="not a slamkit session"):
        slam.save_session(mine)
    assert _digest(mine) == before and not list(tmp_path.glob(".home.*"))


def test_an_empty_folder_is_used_and_a_slamkit_run_replaced_with_or_without_overwrite(slam, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    assert main(["run", "default", "--out", str(out), "--max-frames", "3", "-q"]) in (0, 3)
    first = save_id(out)
    assert main(["run", "default", "--out", str(out), "--overwrite", "--max-frames", "4", "-q"]) in (0, 3)
    assert save_id(out) not in (None, first)
    save_run(slam, out, overwrite=True)
    check_run(out)
    assert len(slamkit.read_tum(out / "trajectory_tum.txt")) == FRAMES


@pytest.mark.parametrize("where", ["notes.txt", "sparse/mine.txt", "session/mine.npz", "old/", "plots/mine.png",
                                   "report.md"])
def test_a_run_folder_holding_a_file_slamkit_did_not_write_is_refused(slam, run, capsys, where):
    """The run's manifest lists what its save wrote; anything else (even named like a report slamkit writes,
    without slamkit's mark) is the user's, and the folder is not replaced, --overwrite or not."""
    path = run / where
    if where.endswith("/"):
        path.mkdir()
        (path / "a.txt").write_text("mine")
    else:
        path.parent.mkdir(exist_ok=True)
        path.write_text("mine")
    before = _digest(run)
    assert foreign_entries(run) == [where]
    for extra in ([], ["--overwrite"]):
        code = main(["run", "default", "--out", str(run), *extra, "--max-frames", "3", "-q"])
        line = _one_line(capsys.readouterr().err)
        assert code == EXIT_USAGE and f"is a slamkit run folder but also holds what slamkit did not write ({where})" in line
    with pytest.raises(OutputError, match="never deletes a file it did not write"):
        save_run(slam, run, overwrite=True)
    with pytest.raises(OutputError, match="also holds"), atomic_dir(run, overwrite=True):
        pass
    assert _digest(run) == before


def test_a_file_put_into_the_run_folder_while_it_is_written_keeps_it(run):
    """atomic_dir checks again just before it moves the old folder aside."""
    with pytest.raises(OutputError, match=r"also holds what slamkit did not write \(late.txt\)"):
        with atomic_dir(run, overwrite=True) as d:
            (d / "x.txt").write_text("new")
            (run / "late.txt").write_text("mine")
    assert (run / "late.txt").read_text() == "mine" and (run / RUN_MARKER).is_file()
    assert not list(run.parent.glob(".run.*"))


def test_what_eval_and_the_app_wrote_into_a_run_folder_is_slamkit_s(slam, run):
    """A report slamkit eval wrote there (with its mark) and the app's map.html are replaced with the run."""
    result = evaluate_run(run, plots=True, map_view=False)
    assert Path(result["report_md"]).parent == run and (run / "plots").is_dir()
    (run / "map.html").write_text("<html><title>slamkit map: run</title></html>")
    assert foreign_entries(run) == []
    slam.save(run)
    assert not (run / "report.md").exists()  # slamkit's own, replaced with the run


# ----------------------------------------------------------------------------------------------- export, eval, ablate, gt
def test_export_never_replaces_a_folder_slamkit_did_not_write(saved_run, tmp_path, capsys):
    home = _home(tmp_path)
    before = _digest(home)
    assert main(["export", str(saved_run), "--format", "colmap", "--out", str(home), "-q"]) == EXIT_USAGE
    assert "not a slamkit export (2 entries: notes.txt, thesis/)" in _one_line(capsys.readouterr().err)
    with pytest.raises(SystemExit) as e:  # export has no such flag: argparse's usage error
        main(["export", str(saved_run), "--format", "colmap", "--out", str(home), "--overwrite"])
    assert e.value.code == EXIT_USAGE and "unrecognized arguments: --overwrite" in capsys.readouterr().err
    assert _digest(home) == before
    # an earlier export is replaced; one the user added a file to is not
    out = tmp_path / "ds"
    export(saved_run, out)
    assert (out / EXPORT_MARKER).is_file() and foreign_entries(out, "export") == []
    export(saved_run, out, format="nerfstudio")
    assert (out / "transforms.json").is_file() and not (out / "sparse").exists()
    (out / "images" / "mine.jpg").write_bytes(b"mine")
    before = _digest(out)
    with pytest.raises(OutputError, match=r"is a slamkit export folder but also holds .*\(images/mine.jpg\)"):
        export(saved_run, out)
    assert _digest(out) == before


def test_eval_out_never_replaces_a_folder_slamkit_did_not_write(saved_run, tmp_path, capsys):
    home = _home(tmp_path)
    before = _digest(home)
    assert main(["eval", str(saved_run), "--out", str(home), "--no-map-view"]) == EXIT_USAGE
    assert "not a slamkit report (2 entries: notes.txt, thesis/)" in _one_line(capsys.readouterr().err)
    assert _digest(home) == before
    out = tmp_path / "report"
    assert main(["eval", str(saved_run), "--out", str(out), "--no-map-view"]) == 0
    assert (out / REPORT_MARKER).is_file() and foreign_entries(out, "report") == []
    assert main(["eval", str(saved_run), "--out", str(out), "--no-map-view"]) == 0  # its own report: replaced
    (out / "plots" / "mine.png").write_bytes(b"mine")
    capsys.readouterr()
    assert main(["eval", str(saved_run), "--out", str(out), "--no-map-view"]) == EXIT_USAGE
    assert "(plots/mine.png)" in _one_line(capsys.readouterr().err) and (out / "plots" / "mine.png").is_file()


def test_ablate_never_writes_into_the_home_folder_or_a_folder_of_other_files(tmp_path, capsys, monkeypatch):
    home = _home(tmp_path)
    monkeypatch.setenv("HOME", str(home))
    before = _digest(home)
    results = tmp_path / "results"  # the user's own results.csv, named as a sweep's: not written over
    results.mkdir()
    (results / "results.csv").write_text("mine\n")
    before_results = _digest(results)
    for out, why in ((home, "is the home folder"), (home / "thesis", "not a slamkit sweep (thesis.tex)"),
                     (results, "not a slamkit sweep (results.csv)")):
        assert main(["ablate", "default", "--grid", "max_frames=3", "--out", str(out), "--workers", "0", "-q"]) == 2
        assert why in _one_line(capsys.readouterr().err)
    assert _digest(home) == before and _digest(results) == before_results


def test_gt_overwrite_replaces_only_a_trajectory_slamkit_wrote(tmp_path, capsys):
    src = "synthetic:sideways?frames=5"
    mine = tmp_path / "thesis.tex"
    mine.write_text("\\chapter{Results}\n")
    assert main(["gt", src, str(mine), "--overwrite"]) == EXIT_USAGE
    line = _one_line(capsys.readouterr().err)
    assert "is not a trajectory file slamkit wrote" in line and "even with --overwrite" in line
    assert mine.read_text() == "\\chapter{Results}\n"
    out = tmp_path / "gt.txt"
    assert main(["gt", src, str(out)]) == 0
    first = out.read_bytes()
    assert main(["gt", src, str(out), "--overwrite"]) == 0 and out.read_bytes() == first


def test_the_app_s_save_keeps_its_map_html_and_refuses_a_user_s_file(slam, run):
    """The app's Save (``keeping_unsaved_files`` around ``slam.save``, :meth:`SlamApp.save`) replaces the run
    folder but keeps what the last save did not write there (Export HTML's map.html, eval's report); a file of
    the user's makes it refuse, and nothing is lost."""
    from slamkit.viz.kept_files import keeping_unsaved_files

    evaluate_run(run, plots=False, map_view=False)
    (run / "map.html").write_text("<html><title>slamkit map: default</title></html>")
    later = {n: (run / n).read_bytes() for n in ("map.html", "report.md", "report.html", "evaluation.json")}
    first = save_id(run)
    with keeping_unsaved_files(run) as kept:
        slam.save(run)
    assert kept == sorted(later) and save_id(run) not in (None, first)
    assert {n: (run / n).read_bytes() for n in later} == later
    (run / "notes.txt").write_text("mine")
    before = _digest(run)
    with pytest.raises(OutputError, match=r"also holds what slamkit did not write \(notes.txt\)"):
        with keeping_unsaved_files(run):
            slam.save(run)
    assert _digest(run) == before and not list(run.parent.glob(".run.*"))


def test_the_app_s_export_html_replaces_only_a_map_slamkit_wrote(tmp_path):
    """:meth:`SlamApp.export_html` asks this before it writes over an existing file."""
    from slamkit.viz.kept_files import is_slamkit_map as _is_slamkit_map

    mine, ours = tmp_path / "map.html", tmp_path / "ours.html"
    mine.write_text("<html><title>my thesis figure</title></html>")
    ours.write_text("<html><title>slamkit map: default</title></html>")
    assert not _is_slamkit_map(mine) and _is_slamkit_map(ours) and not _is_slamkit_map(tmp_path)
