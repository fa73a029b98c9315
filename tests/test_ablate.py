"""Ablation sweeps: grid parsing and its errors, failing runs as rows, persistence and resume, the local
process pool, and the same sweep on a real dask LocalCluster (identical rows; a worker killed mid-sweep
loses no finished result).

Runs are tiny (a 24-frame synthetic sequence) so the whole file stays around a minute on 2 cores.
"""

from __future__ import annotations

import json
import math
import re
import threading
import time
from pathlib import Path

import pytest

from slamkit import ConfigError
from slamkit.ablate import Grid, parse_grid, plan, run_one, sweep
from slamkit.cli import main
from conftest import notebook_stream

SOURCE = "synthetic:handheld?frames=24"
BAD_SOURCE = "/nonexistent/sequence"
FIXED = ["init_frames=8"]
GRID = ["flow_threshold=0.05,0.1", *FIXED]
COMPARED = ["ate_rmse_m", "frames_posed", "keyframes", "points3D", "points_per_image", "reprojection_error_px"]


# --------------------------------------------------------------------------------------------- grid

def test_parse_grid_types_and_order():
    g = parse_grid(["flow_threshold=0.02,0.05,0.1", "init_frames=10,20", "frame_skip=2", "features=orb,sift",
                    "tracker.min_inliers=20"])
    assert isinstance(g, Grid) and len(g) == 3 * 2 * 1 * 2 * 1
    d = g.to_dict()
    assert d["flow_threshold"] == [0.02, 0.05, 0.1] and all(isinstance(v, float) for v in d["flow_threshold"])
    assert d["init_frames"] == [10, 20] and all(type(v) is int for v in d["init_frames"])
    assert d["features"] == ["orb", "sift"] and d["tracker.min_inliers"] == [20]
    combos = g.combinations()
    assert combos[0] == {"flow_threshold": 0.02, "init_frames": 10, "frame_skip": 2, "features": "orb",
                         "tracker.min_inliers": 20}
    assert len({json.dumps(c, sort_keys=True) for c in combos}) == len(g)
    assert parse_grid("flow_threshold=0.05 init_frames=10").to_dict() == parse_grid(
        {"flow_threshold": [0.05], "init_frames": 10}).to_dict()
    tasks = plan(["a", "b"], g, repeats=3)
    assert len(tasks) == 2 * len(g) * 3 and [t.seed for t in tasks[:3]] == [0, 1, 2]
    assert len({t.key for t in tasks}) == len(tasks)  # one result file per run


@pytest.mark.parametrize("items, words", [
    (["flow_thresh=0.1"], ["flow_thresh", "unknown", "flow_threshold"]),
    (["init_frames=ten"], ["init_frames", "'ten'", "int"]),
    (["init_frames=10.5"], ["init_frames", "10.5"]),
    (["frame_skip=0"], ["frame_skip", ">= 1"]),
    (["features=orb,surf9"], ["features", "surf9"]),
    (["init_frames"], ["init_frames", "NAME=V1"]),
    (["init_frames="], ["no values"]),
    (["init_frames=10", "init_frames=20"], ["twice"]),
    (["seed=1,2"], ["repeats"]),
])
def test_parse_grid_errors_name_the_parameter(items, words):
    with pytest.raises(ConfigError) as e:
        parse_grid(items)
    for w in words:
        assert w in str(e.value)


def test_cli_reports_bad_grid(capsys, tmp_path):
    assert main(["ablate", SOURCE, "--grid", "init_frames=ten", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "init_frames" in err and "'ten'" in err and "Traceback" not in err
    assert not (tmp_path / "runs").exists()
    assert main(["ablate", SOURCE, "--features", "orb,surf9", "--out", str(tmp_path)]) == 2
    assert "surf9" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------- runs

def test_run_one_never_raises():
    bad = run_one(BAD_SOURCE, {"flow_threshold": 0.05}, seed=0)
    assert bad["status"] == "failed" and "SourceError" in bad["error"] and BAD_SOURCE in bad["error"]
    assert math.isnan(bad["ate_rmse_m"]) and bad["flow_threshold"] == 0.05
    conflicting = run_one(SOURCE, {"tracker.min_inliers": 1000}, seed=0)  # contradicts min_tracked_matches
    assert conflicting["status"] == "failed" and "ConfigError" in conflicting["error"]
    json.dumps(bad), json.dumps(conflicting)


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory):
    """The reference sweep: 2 combinations on the synthetic sequence + a source that does not open, on the
    local process pool (2 processes)."""
    out = tmp_path_factory.mktemp("local")
    t = time.perf_counter()
    df = sweep([SOURCE, BAD_SOURCE], GRID, out, "local", workers=2)
    return out, df, time.perf_counter() - t


def test_local_sweep_rows_files_and_ground_truth(local_sweep):
    out, df, _ = local_sweep
    assert len(df) == 4 and list(df.columns[:5]) == ["source", "flow_threshold", "init_frames", "seed", "repeat"]
    good = df[df["source"] == SOURCE]
    assert (good["status"] == "ok").all(), good["error"].tolist()
    # synthetic ground truth is exact: the trajectory is within centimetres, every frame posed
    assert (good["ate_rmse_m"] < 0.05).all(), good["ate_rmse_m"].tolist()
    assert (good["fraction_posed"] > 0.9).all() and (good["keyframes"] >= 2).all()
    assert (good["points_per_image"] > 50).all() and (good["reprojection_error_px"] < 2).all()
    assert {"t_features_s", "t_track_s", "wall_time_s"} <= set(df.columns)
    bad = df[df["source"] == BAD_SOURCE]
    assert (bad["status"] == "failed").all() and bad["error"].str.contains("does not exist").all()
    assert len(list((out / "runs").glob("*.json"))) == 4
    for name in ("results.csv", "results.md", "effects.png", "sweep.json"):
        assert (out / name).stat().st_size > 0, name
    md = (out / "results.md").read_text()
    assert "## Failed runs" in md and "does not exist" in md and "effects.png" in md
    pytest.importorskip("pyarrow")  # the dask extra; without it only CSV is written
    import pandas as pd

    back = pd.read_parquet(out / "results.parquet")
    assert back["ate_rmse_m"].tolist()[:2] == pytest.approx(df["ate_rmse_m"].tolist()[:2])


def test_resume_reuses_finished_runs(local_sweep, tmp_path, monkeypatch):
    import shutil

    import slamkit.ablate as ablate

    src, df, _ = local_sweep
    out = shutil.copytree(src, tmp_path / "copy")

    def must_not_run(task):
        raise AssertionError(f"{task} was run again")

    monkeypatch.setattr(ablate, "_run_task", must_not_run)
    again = sweep([SOURCE, BAD_SOURCE], GRID, out, "serial", write_outputs=False)
    assert again["cached"].all()
    assert again["ate_rmse_m"].tolist()[:2] == df["ate_rmse_m"].tolist()[:2]
    # a run file that is corrupt (not written by slamkit) is run again; retry_failed redoes failed ones
    calls = []
    monkeypatch.setattr(ablate, "_run_task", lambda t: calls.append(t) or {**ablate._lost_row(t, OSError("x")),
                                                                          "status": "ok", "error": ""})
    victim = next(p for p in sorted((out / "runs").glob("*.json")) if json.loads(p.read_text())["status"] == "ok")
    victim.write_text("{ truncated")
    sweep([SOURCE, BAD_SOURCE], GRID, out, "serial", retry_failed=True, write_outputs=False)
    assert len(calls) == 3  # the corrupt one and the two failed ones


def test_cli_ablate_reuses_and_prints_table(local_sweep, capsys):
    out, df, _ = local_sweep
    rc = main(["ablate", SOURCE, BAD_SOURCE, "--grid", *GRID, "--out", str(out), "-q"])
    cap = capsys.readouterr()
    assert rc == 1  # some runs failed
    assert "2/4 runs ok (4 reused" in cap.err
    assert "| source | flow_threshold | init_frames |" in cap.out and "failed" in cap.out


# --------------------------------------------------------------------------------------------- dask

def test_dask_cluster_same_rows_and_worker_killed(local_sweep, tmp_path, capsys):
    distributed = pytest.importorskip("distributed")
    psutil = pytest.importorskip("psutil")
    _, local_df, _ = local_sweep
    grid = ["flow_threshold=0.05,0.1,0.2", *FIXED]  # 3 runs; 2 of them are the local sweep's
    out = tmp_path / "dask"
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        result: dict = {}

        def run():
            try:
                result["df"] = sweep([SOURCE], grid, out, client)
            except BaseException as e:  # noqa: BLE001
                result["error"] = e

        th = threading.Thread(target=run)
        th.start()
        deadline = time.monotonic() + 240
        while not list((out / "runs").glob("*.json")) and time.monotonic() < deadline:
            time.sleep(0.2)
        finished = {p.name: p.read_bytes() for p in (out / "runs").glob("*.json")}
        assert finished, "no run finished in time"
        pids = client.run(lambda: __import__("os").getpid())
        busy = [w for w, keys in client.processing().items() if keys]
        victim = psutil.Process(pids[busy[0]] if busy else next(iter(pids.values())))
        victim.kill()  # a worker process dies mid-sweep, running a task (its nanny starts a new one)
        th.join(timeout=300)
        assert not th.is_alive()
        assert "error" not in result, result.get("error")
        # finished results survived the killed worker, unchanged
        for name, data in finished.items():
            assert (out / "runs" / name).read_bytes() == data
        # resume: whatever was lost with the worker is redone, nothing finished is
        df = sweep([SOURCE], grid, out, client)
        # the CLI on the same cluster (everything is finished: nothing runs again)
        assert main(["ablate", SOURCE, "--grid", *grid, "--scheduler", cluster.scheduler_address, "--out", str(out),
                     "-q"]) == 0
    assert len(df) == 3 and (df["status"] == "ok").all(), df[["status", "error"]]
    assert df["cached"].sum() >= len(finished)
    assert f"on {cluster.scheduler_address}" in capsys.readouterr().err
    # the same runs give the same rows on the cluster as on the local pool (same seeds)
    same = df[df["flow_threshold"] < 0.15].sort_values("flow_threshold")
    ref = local_df[local_df["source"] == SOURCE].sort_values("flow_threshold")
    for col in COMPARED:
        assert same[col].tolist() == pytest.approx(ref[col].tolist(), rel=1e-9, abs=1e-12), col


# --------------------------------------------------------------------------------------------- notebook

def test_ablation_notebook_runs_tiny(tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    path = Path(__file__).resolve().parents[1] / "notebooks" / "03_ablation.ipynb"
    nb = nbformat.read(path, as_version=4)
    idx = next(i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", []))
    values = {"sources": [SOURCE], "grid": {"flow_threshold": [0.1]}, "init_frames": 8, "workers": 0,
              "out_dir": str(tmp_path / "best")}
    cell = nbformat.v4.new_code_cell("\n".join(f"{k} = {v!r}" for k, v in values.items()))
    cell.metadata["tags"] = ["injected-parameters"]
    nb.cells.insert(idx + 1, cell)
    nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.output_type == "error"]
    text = notebook_stream(nb, "stdout") + "\n" + notebook_stream(nb, "stderr")
    assert "1 runs:" in text and "1 of 1 runs ok" in text
    html = "\n".join(o.get("data", {}).get("text/html", "") for o in outputs)
    assert "ATE (cm)" in html and "<table" in html and "ATE sd" not in html  # in cm; one repeat: no spread column
    assert "1/1 runs" in text  # the progress bar is plain text: a saved notebook keeps it
    assert not any("application/vnd.jupyter.widget-view+json" in o.get("data", {}) for o in outputs)
    assert sum("image/png" in o.get("data", {}) for o in outputs) >= 2  # effects + best trajectory
    sweep_dir = tmp_path / "best-sweep"
    assert len(list((sweep_dir / "runs").glob("*.json"))) == 1 and (sweep_dir / "effects.png").exists()
    assert (tmp_path / "best" / "report.md").exists() and (tmp_path / "best" / "map.html").exists()
    # one repeat: no summary table that would repeat the run table, no speed compared without a spread
    assert "one run per setting: no summary table" in text and "frames/s" not in html
    assert re.search(r"lowest mean ATE: flow_threshold=0.1, init_frames=8, [0-9.]+ cm; no other setting is tied", text)
    best_cm = float(re.search(r"the sweep measured ATE ([0-9.]+) cm for it", text).group(1))
    saved_cm = float(text.split("ATE RMSE of the saved run: ")[1].split(" cm")[0])
    assert saved_cm == pytest.approx(best_cm, abs=0.01)  # same seed, same run: what the reading says
