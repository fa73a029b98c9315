"""Saved runs are checked before they are read (issue 22): a truncated, emptied or altered file of a run folder
is a one-line SlamkitError naming it, from ``slamkit eval``, ``slamkit run --resume`` and ``Slam.resume``
alike — never a hang inside pycolmap's reader (an empty ``points3D.bin`` made it loop forever), a traceback
or a changed input. Runs saved before manifests existed still load (their formats are checked).
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import random
import shutil
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from slamkit.cli import main
from slamkit.errors import SessionError, SlamkitError
from slamkit.io.run_dir import RUN_MARKER, SESSION_MARKER
from slamkit.io.saved import check_colmap_model, check_run, check_session
from slamkit.pipeline import Slam

REPO = Path(__file__).parents[1]
RUN = ["run", "default", "--max-frames", "30", "-q"]


@pytest.fixture(scope="module")
def saved_run(tmp_path_factory) -> Path:
    """``slamkit run default --max-frames 30``, made once for the module (about 5 s)."""
    out = tmp_path_factory.mktemp("saved") / "run"
    assert main([*RUN, "--out", str(out)]) == 0
    return out


def _copy(saved_run: Path, tmp_path: Path, legacy: bool = False) -> Path:
    run = tmp_path / "run"
    shutil.copytree(saved_run, run)
    if legacy:  # as saved before run folders carried a manifest
        (run / RUN_MARKER).unlink()
        (run / "session" / SESSION_MARKER).unlink()
    return run


def _digest(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _cli(args: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
    """``python -m slamkit.cli ARGS`` in a process of its own: a hang fails the test instead of stalling it."""
    return subprocess.run([sys.executable, "-m", "slamkit.cli", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=timeout)


def test_a_saved_run_records_every_file_and_passes_its_checks(saved_run):
    meta = json.loads((saved_run / RUN_MARKER).read_text())
    assert meta["format"] == "slamkit-run" and meta["version"] == 1
    files = {p.relative_to(saved_run).as_posix() for p in saved_run.rglob("*") if p.is_file()} - {RUN_MARKER}
    assert set(meta["files"]) == files
    for rel, info in meta["files"].items():
        data = (saved_run / rel).read_bytes()
        assert info == {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    check_run(saved_run)
    check_session(saved_run / "session")


@pytest.mark.parametrize("legacy", [False, True], ids=["manifest", "legacy"])
@pytest.mark.parametrize("model", ["sparse", "session/segment_00/model"])
def test_an_empty_points3D_bin_is_an_error_not_a_hang(saved_run, tmp_path, model, legacy):
    run = _copy(saved_run, tmp_path, legacy)
    bad = run / model / "points3D.bin"
    bad.write_bytes(b"")
    before = _digest(run)
    with pytest.raises(SessionError, match=rf"{bad}: "):
        check_colmap_model(run / model) if legacy else check_run(run) if model == "sparse" else check_session(
            run / "session")
    args = ["eval", str(run)] if model == "sparse" else [*RUN, "--out", str(run), "--resume"]
    r = _cli(args)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(f"slamkit: error: {bad}: ") and "Traceback" not in r.stderr
    assert _digest(run) == before


@pytest.mark.parametrize("legacy", [False, True], ids=["manifest", "legacy"])
def test_eval_on_a_truncated_summary_json_names_it(saved_run, tmp_path, capsys, legacy):
    run = _copy(saved_run, tmp_path, legacy)
    summary = run / "summary.json"
    summary.write_bytes(summary.read_bytes()[:100])
    assert main(["eval", str(run), "--no-map-view"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"slamkit: error: {summary}: ") and len(err.strip().splitlines()) == 1, err
    assert "JSONDecodeError" in err if legacy else "bytes, but" in err


@pytest.mark.parametrize("legacy", [False, True], ids=["manifest", "legacy"])
def test_resume_with_a_truncated_arrays_npz_names_it(saved_run, tmp_path, capsys, legacy):
    run = _copy(saved_run, tmp_path, legacy)
    npz = run / "session" / "segment_00" / "arrays.npz"
    npz.write_bytes(npz.read_bytes()[:5000])
    before = _digest(run)
    assert main([*RUN, "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"slamkit: error: {npz}: ") and len(err.strip().splitlines()) == 1, err
    with pytest.raises(SessionError, match=str(npz)):
        Slam.resume(run)
    assert _digest(run) == before


def test_eval_on_a_folder_that_does_not_exist_says_so(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "nothere")]) == 2
    assert f"{tmp_path / 'nothere'}: does not exist" in capsys.readouterr().err


def test_a_run_saved_before_manifests_still_loads_and_evaluates(saved_run, tmp_path, capsys):
    run = _copy(saved_run, tmp_path, legacy=True)
    slam = Slam.resume(run)
    assert len(slam.records) == 30 and slam.done
    assert main(["eval", str(run), "--json-only"]) == 0
    assert json.loads(capsys.readouterr().out)["ate"]["rmse"] < 0.01


def test_an_edited_file_is_named(saved_run, tmp_path):
    run = _copy(saved_run, tmp_path)
    traj = run / "trajectory_tum.txt"
    text = traj.read_text()
    traj.write_text(text.replace("0", "1", 1))  # same size, other content
    with pytest.raises(SessionError, match=rf"{traj}: content differs from what was saved"):
        check_run(run)
    (run / RUN_MARKER).write_text('{"format": "slamkit-run", "ver')
    with pytest.raises(SessionError, match=rf"{run / RUN_MARKER}: the list of saved files cannot be read"):
        check_run(run)


# ----------------------------------------------------------------------------------------------- property
WORKER = textwrap.dedent('''
    """Damage one file of a copy of a saved run, run eval or --resume on it, report one JSON line per case."""
    import contextlib, hashlib, io, json, shutil, sys, time
    from pathlib import Path
    from slamkit.cli import main

    base, work = Path(sys.argv[1]), Path(sys.argv[2])
    cases = json.loads(Path(sys.argv[3]).read_text())

    def digest(folder):
        return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(folder.rglob("*")) if p.is_file()}

    for k, case in enumerate(cases):
        run = work / f"case{k}"
        shutil.copytree(base, run)
        if case["legacy"]:
            (run / ".slamkit-run").unlink()
            (run / "session" / ".slamkit-session.json").unlink()
        path = run / case["file"]
        data = bytearray(path.read_bytes())
        cut = min(case["cut"], max(len(data) - 1, 0))
        if case["kind"] == "truncate":
            data = data[:cut]
        elif case["kind"] == "zero":
            data[cut:cut + 64] = bytes(len(data[cut:cut + 64]))
        elif data:
            data[cut] ^= 1 << case["bit"]
        path.write_bytes(bytes(data))
        before = digest(run)
        args = [a.replace("RUN", str(run)) for a in case["args"]]
        err, t0 = io.StringIO(), time.monotonic()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                rc = main(args)
            except BaseException as e:  # noqa: BLE001 - reported, the test fails on it
                rc = f"raised {type(e).__name__}: {e}"
        changed = rc != 0 and digest(run) != before
        print(json.dumps({"case": k, **case, "rc": rc, "changed": changed, "seconds": time.monotonic() - t0,
                          "err": err.getvalue()[-1500:]}), flush=True)
        shutil.rmtree(run)
    print("done", flush=True)
''')


def _cases(saved_run: Path, seed: int) -> list[dict]:
    rng = random.Random(seed)
    files = sorted(p.relative_to(saved_run).as_posix() for p in saved_run.rglob("*") if p.is_file())
    cases = []
    for rel in files:
        size = (saved_run / rel).stat().st_size
        for command in ("eval", "resume"):
            if command == "eval" and rel.startswith("session/"):
                args = ["eval", "RUN", "--json-only"]    # eval reads none of the session: it should work
            elif command == "eval":
                args = ["eval", "RUN"] if rel.startswith("sparse/") else ["eval", "RUN", "--no-map-view"]
            else:
                args = [*RUN, "--out", "RUN", "--resume"]
            cases.append({"file": rel, "kind": rng.choice(["truncate", "zero", "flip"]),
                          "cut": rng.randrange(max(size, 1)), "bit": rng.randrange(8), "legacy": False, "args": args})
            if rel.endswith((".bin", ".npz", ".json")) and RUN_MARKER not in rel and SESSION_MARKER not in rel:
                # saved before manifests: truncation is caught by the format checks alone
                cases.append({**cases[-1], "kind": "truncate", "legacy": True})
    return cases


def test_damaged_files_give_a_slamkit_error_or_work_never_a_hang_or_traceback(saved_run, tmp_path):
    cases = _cases(saved_run, seed=22)
    (tmp_path / "cases.json").write_text(json.dumps(cases))
    (tmp_path / "worker.py").write_text(WORKER)
    (tmp_path / "work").mkdir()
    proc = subprocess.Popen([sys.executable, str(tmp_path / "worker.py"), str(saved_run), str(tmp_path / "work"),
                             str(tmp_path / "cases.json")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True).start()
    results = []
    try:
        while True:
            try:  # a case that takes this long is a hang (they take well under a second, a successful resume ~2 s)
                line = lines.get(timeout=60)
            except queue.Empty:
                pytest.fail(f"no answer within 60 s after case {len(results)}: {cases[len(results)]}")
            if line.strip() == "done":
                break
            results.append(json.loads(line))
    finally:
        proc.kill()
        err = proc.stderr.read()
    assert len(results) == len(cases), err[-3000:]
    read_by_eval = ("trajectory_tum.txt", "keyframes_tum.txt", "groundtruth_tum.txt", "summary.json", RUN_MARKER)
    caught = 0
    for r in results:
        assert r["rc"] in (0, 2), r                    # worked, or a SlamkitError (exit code 2); nothing raised
        assert "Traceback" not in r["err"], r
        assert not r["changed"], r                     # a refused input is left as it was
        if r["rc"] == 2:
            assert r["err"].startswith("slamkit: error: ") and len(r["err"].strip().splitlines()) == 1, r
        if r["legacy"] or r["kind"] == "zero":         # zeroing bytes that were zero changes nothing
            continue
        reads = (r["file"].startswith("session/") if r["args"][0] == "run" else
                 r["file"] in read_by_eval or (r["file"].startswith("sparse/") and "--no-map-view" not in r["args"]))
        if reads:                                      # damage to a file the command reads is always caught,
            assert r["rc"] == 2, r                     # and the message names the file
            assert Path(r["file"]).name in r["err"] or RUN_MARKER in r["err"] or SESSION_MARKER in r["err"], r
            caught += 1
    assert caught >= 10, caught                    # the seed gives 17 such cases


def test_damaged_session_cases_are_caught_by_resume_in_process(saved_run, tmp_path):
    """Slam.resume (Python API) raises SessionError for the same damage the CLI reports."""
    for rel in ("session/session.json", "session/state.npz", "session/segment_00/model/images.bin"):
        run = _copy(saved_run, tmp_path / rel.replace("/", "_"), legacy=True)
        path = run / rel
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        with pytest.raises(SlamkitError, match=str(path)):
            Slam.resume(run)
