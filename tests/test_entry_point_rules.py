"""Issue 50, item 5: one rule for every entry point.

What ``slamkit run`` refuses (a camera given for the rendered ``default`` sequence, whose camera is part of its
spec), ``slamkit ablate`` (in this process, on the local pool and on a real dask LocalCluster), the Python API
(``Slam``, ``run_to_folder``) and the notebook app refuse in the same words; an ablation run that posed no frame
is a failed row with the reason, and the sweep exits non-zero (1, as for any failed run of an ablation).
"""

from __future__ import annotations

import json
import math

import pytest

from slamkit import ConfigError, SlamConfig
from slamkit.ablate import NOTHING_POSED, run_one, sweep
from slamkit.cli import main
from slamkit.pipeline import Slam
from slamkit.runner import EXIT_FAILED, EXIT_USAGE, run_to_folder
from slamkit.sources import open_source
from slamkit.sources.base import CAMERA_IN_SPEC

SOURCE = "synthetic:handheld?frames=24"
NOTHING = {"max_frames": 3}  # three frames of a slow hand-held walk: no initial pair, so nothing is posed


def _run_message(tmp_path, capsys, source: str) -> str:
    """The one line ``slamkit run SOURCE --camera 585`` refuses with (exit 2, nothing written)."""
    out = tmp_path / "run"
    assert main(["run", source, "--camera", "585", "--max-frames", "20", "-q", "--out", str(out)]) == EXIT_USAGE
    assert not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("slamkit: error: ")
    return err[0].removeprefix("slamkit: error: ")


@pytest.mark.parametrize("source", ["default", SOURCE])
def test_python_api_refuses_a_camera_for_a_rendered_source_in_runs_words(tmp_path, capsys, source):
    message = _run_message(tmp_path, capsys, source)
    assert message == CAMERA_IN_SPEC
    cfg = SlamConfig().with_overrides(camera="585", max_frames=20)
    with pytest.raises(ConfigError) as by_spec:
        Slam(source, cfg)
    with pytest.raises(ConfigError) as opened_first:  # the source opened without the camera, as ablate did
        Slam(open_source(source), cfg)
    with pytest.raises(ConfigError) as to_folder:
        run_to_folder(source, tmp_path / "api", cfg)
    assert str(by_spec.value) == str(opened_first.value) == str(to_folder.value) == message
    slam = Slam(open_source(source), SlamConfig().with_overrides(max_frames=20))
    with pytest.raises(ConfigError, match=r"^camera= cannot be given for synthetic sources"):
        slam.reset(cfg)  # a new config on a running pipeline: the same rule
    # "auto" (self-calibration) and another run's camera stay allowed, as `run` allows them
    assert Slam(open_source(source), SlamConfig().with_overrides(camera="auto")).calibrator is not None


def test_the_app_refuses_it_in_the_same_words():
    pytest.importorskip("ipywidgets")
    from slamkit.viz.app import SlamApp

    with pytest.raises(ConfigError) as e:
        SlamApp("default", SlamConfig().with_overrides(camera="585", max_frames=20))
    assert str(e.value) == CAMERA_IN_SPEC


def test_ablate_fails_the_row_with_runs_words_and_exits_non_zero(tmp_path, capsys):
    message = _run_message(tmp_path, capsys, "default")
    row = run_one("default", {"camera": "585", "max_frames": 20})
    assert row["status"] == "failed" and row["error"] == f"ConfigError: {message}"
    out = tmp_path / "sweep"
    rc = main(["ablate", "default", "--grid", "camera=585", "max_frames=20", "--workers", "0", "-q",
               "--out", str(out)])
    captured = capsys.readouterr()
    assert rc == EXIT_FAILED and message in captured.err and "0/1 runs ok" in captured.err
    saved = [json.loads(p.read_text()) for p in (out / "runs").glob("*.json")]
    assert [r["status"] for r in saved] == ["failed"] and saved[0]["error"] == f"ConfigError: {message}"


def test_a_run_that_posed_nothing_is_a_failed_row_and_a_non_zero_exit(tmp_path, capsys):
    row = run_one(SOURCE, NOTHING)
    assert row["status"] == "failed" and row["frames_posed"] == 0 and row["frames"] == 3
    assert row["error"].startswith(NOTHING_POSED + ": no initial pair found") and math.isnan(row["ate_rmse_m"])
    # `run` on the same source and settings: exit 3 and the same reason
    assert main(["run", SOURCE, "--max-frames", "3", "-q", "--out", str(tmp_path / "run")]) == 3
    err = capsys.readouterr().err
    assert "no frame was posed, so no map was made" in err and "no map: no initial pair found" in err
    rc = main(["ablate", SOURCE, "--grid", "max_frames=3", "--workers", "0", "-q", "--out", str(tmp_path / "sw")])
    captured = capsys.readouterr()
    assert rc == EXIT_FAILED and NOTHING_POSED in captured.err and "0/1 runs ok" in captured.err


def test_dask_cluster_gives_the_same_failed_rows(tmp_path):
    """The same two failing runs (a refused camera; nothing posed) on a real dask LocalCluster and in this
    process: failed rows with the same errors."""
    distributed = pytest.importorskip("distributed")
    grid = {"camera": ["", "585"], "max_frames": [3]}  # "": the source's own camera
    local = sweep([SOURCE], grid, tmp_path / "serial", "serial", write_outputs=False)
    with distributed.LocalCluster(n_workers=1, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        remote = sweep([SOURCE], grid, tmp_path / "dask", client, write_outputs=False)
    for df in (local, remote):
        assert (df["status"] == "failed").all(), df[["status", "error"]]
        errors = dict(zip(df["camera"], df["error"]))
        assert errors["585"] == f"ConfigError: {CAMERA_IN_SPEC}"
        assert errors[""].startswith(NOTHING_POSED + ": no initial pair found")
    assert local["error"].tolist() == remote["error"].tolist()
