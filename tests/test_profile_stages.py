"""benchmarks/profile_stages.py on a short rendered sequence, in a real child process: its stage rows add up
to the process's wall time with little left unaccounted, and agree with the pipeline's own clock."""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import profile_stages  # noqa: E402
from profile_stages import PREFETCH_STAGES, REPO, TOLERANCE, profile_tree  # noqa: E402


def _own_cpu() -> float:
    used = resource.getrusage(resource.RUSAGE_SELF)
    return used.ru_utime + used.ru_stime


@pytest.fixture(scope="module")
def profile():
    t, cpu = time.perf_counter(), _own_cpu()
    out = profile_tree(REPO, "synthetic:handheld?frames=30&seed=1", 30, {})
    out["parent_cpu_s"] = _own_cpu() - cpu  # this process only waited meanwhile
    return out, time.perf_counter() - t


def test_rows_add_up_to_the_wall_time_with_little_unaccounted(profile):
    out, outside = profile
    rows, wall = out["rows"], out["wall_s"]
    assert out["frames"] == 30 and out["posed"] > 20
    assert wall <= outside and wall > 0.9 * outside  # the child's spawn-to-exit, as timed from here
    assert all(v >= 0 for v in rows.values()), rows
    assert sum(rows.values()) == pytest.approx(wall, rel=1e-9)
    assert rows["unaccounted"] < TOLERANCE * wall, rows
    for stage in ("startup and exit", "open", "read + features (wait)", "initialize", "track", "final BA", "save"):
        assert rows[stage] > 0, stage
    assert not set(PREFETCH_STAGES) & set(rows)  # the prefetch thread's stages overlap: listed apart
    assert out["prefetch"]["features"] > 0


def test_cpu_time_is_the_childs_own_and_bounded_by_its_cores(profile):
    """Only what the machine's load cannot change: the child's CPU time is its own (more than this waiting
    process used meanwhile; imports and 30 frames take seconds of CPU) and at most all cores for its wall
    time (a busy machine lowers the share of a core the child gets, never raises it past that bound)."""
    out, _ = profile
    assert out["cpu_s"] > 0 and out["cpu_s"] > out["parent_cpu_s"]
    assert out["cpu_s"] <= profile_stages.CORES * out["wall_s"] * 1.05 + 0.05


def test_rows_of_the_steps_and_finish_match_the_pipelines_own_clock(profile):
    out, _ = profile
    rows = out["rows"]
    slam_rows = sum(v for k, v in rows.items() if k not in ("startup and exit", "open", "save"))
    assert slam_rows == pytest.approx(out["slam_wall_s"], rel=TOLERANCE)


def test_table_names_every_stage_and_the_throughput_ratio(profile):
    out, _ = profile
    table = profile_stages._table("synthetic", ["a", "b"], {"a": [out], "b": [out]})
    for stage in out["rows"]:
        assert f"| {stage} |" in table
    assert "throughput vs a: b 1.00x" in table
    assert f"| CPU time, all threads | {1e3 * out['cpu_s'] / out['frames']:.1f} ({out['cpu_s']:.1f} s) |" in table
    bound = out["cpu_s"] / profile_stages.CORES
    assert f"b {bound:.1f} s = {out['wall_s'] / bound:.2f}x" in table
    assert f"{out['frames'] / out['wall_s']:.1f} fps" in table


def test_summary_and_final_line_report_each_stages_ms_per_frame():
    from slamkit import Slam, SlamConfig
    from slamkit.runner import summary_line

    slam = Slam("synthetic:sideways?frames=12", SlamConfig().with_overrides(init_frames=6))
    slam.run()
    s = slam.summary()
    ms = s["stage_ms_per_frame"]
    assert set(ms) == set(s["timings_s"]) and list(ms.values()) == sorted(ms.values(), reverse=True)
    for k, v in s["timings_s"].items():
        assert ms[k] == pytest.approx(1e3 * v / s["frames"])
    top = next(iter(ms))
    assert f"frames/s ({top} {ms[top]:.0f}, " in summary_line(s)
