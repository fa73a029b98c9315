"""Every configuration value is validated where it is declared (issue 40, rule 6).

The test walks every field of :class:`SlamConfig`, recursively through the stage configs and their nested
configs (generated from the dataclasses, not a list), and sets each to hostile values: NaN, infinities, -1,
1e20, 10**20, 2**31 and a garbage string. Each must be refused with a ConfigError naming the dotted field, or
be in :data:`ACCEPTED` with the reason it is accepted on purpose. A new field is covered without touching
this file; a new accepted value must be added to :data:`ACCEPTED` with its reason.
"""

from __future__ import annotations

import dataclasses
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slamkit import Slam, SlamConfig
from slamkit.errors import C_INT_MAX, ArgumentTypeError, ConfigError, check_number, native_seed
from slamkit.sources.synthetic import synthetic_source

PROBES: dict[str, object] = {
    "nan": float("nan"), "inf": float("inf"), "-inf": float("-inf"), "-1": -1, "1e20": 1e20, "10**20": 10**20,
    "2**31": 2**31, "text": "garbage",
}
"""Hostile values, by name. The same values given as strings (as ``--set KEY=VALUE`` does) are probed too."""

ACCEPTED: dict[tuple[str, str], str] = {
    **{(seed, p): "a seed is any non-negative integer (slamkit.errors.native_seed maps it for pycolmap)"
       for seed in ("seed", "initializer.random_seed", "tracker.random_seed", "motion_model.random_seed")
       for p in ("1e20", "10**20", "2**31")},
    **{(f"loop_closing.{v}.random_seed", p): "-1: random (documented); any non-negative integer is a seed"
       for v in ("verification", "merge_verification") for p in ("-1", "1e20", "10**20", "2**31")},
    ("ba.num_threads", "-1"): "-1: all cores (documented)",
    **{("weights_dir", p): "a folder name (any text); checked when a learned extractor or matcher is created"
       for p in PROBES},
    **{("camera", p): "a focal length in pixels; checked against the image size when the source is opened "
                      "(Intrinsics' sane range: fields of view from 1 to 170 degrees)"
       for p in ("1e20", "10**20", "2**31")},
}
"""(dotted field, probe name) -> why that value is accepted on purpose."""


def _leaves(obj, prefix: str = ""):
    """(dotted name, value) of every field that is not itself a config dataclass, recursively."""
    for f in dataclasses.fields(obj):
        value, name = getattr(obj, f.name), f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            yield from _leaves(value, name + ".")
        else:
            yield name, value


FIELDS = list(_leaves(SlamConfig()))


def test_the_walk_reaches_every_stage_and_nested_config():
    names = {n for n, _ in FIELDS}
    assert len(FIELDS) > 150
    for expected in ("seed", "ba.num_threads", "initializer.matching.ratio", "mapper.guided_matching.max_hamming",
                     "loop_closing.verification.scale_range", "local_mapping.fuse_matching.max_l2",
                     "self_calibration.window_frames", "keyframes.flow_threshold"):
        assert expected in names


def _probes(value):
    """The probes that apply to a field holding ``value`` (a tuple: each element in turn)."""
    if isinstance(value, bool):
        return [(p, v) for p, v in PROBES.items() if p in ("text", "nan", "-1", "1e20")]
    if isinstance(value, tuple):
        return [(f"{p}@{k}", tuple(v if j == k else value[j] for j in range(len(value))))
                for p, v in PROBES.items() for k in range(len(value))] + [("text", "garbage")]
    return list(PROBES.items())


def _names_field(message: str, dotted: str) -> bool:
    return re.search(rf"(?<![\w.]){re.escape(dotted)}(?![\w])", message) is not None


@pytest.mark.parametrize("as_text", [False, True], ids=["python", "text"])
def test_every_field_refuses_hostile_values_or_accepts_them_on_purpose(as_text):
    accepted, wrong = set(), []
    for dotted, value in FIELDS:
        for probe, bad in _probes(value):
            given = (",".join(map(str, bad)) if isinstance(bad, tuple) else str(bad)) if as_text else bad
            try:
                cfg = SlamConfig().with_overrides(**{dotted: given})
            except (ConfigError, ArgumentTypeError) as e:
                if not _names_field(str(e), dotted):
                    wrong.append(f"{dotted}={given!r}: the message does not name the field: {e}")
                continue
            except Exception as e:  # noqa: BLE001 - anything else is the defect this test is for
                wrong.append(f"{dotted}={given!r}: {type(e).__name__}: {e}")
                continue
            key = (dotted, probe.split("@")[0])
            if key not in ACCEPTED:
                obj = cfg
                for part in dotted.split("."):
                    obj = getattr(obj, part)
                wrong.append(f"{dotted}={given!r} accepted (now {obj!r}) without a reason in ACCEPTED")
            accepted.add(key)
    assert not wrong, "\n".join(wrong)
    if not as_text:  # every documented exception is still needed (as text, "1e20" is refused for an int)
        assert accepted == set(ACCEPTED), set(ACCEPTED) ^ accepted


def test_stage_configs_check_themselves_with_the_dotted_name():
    """A stage built from the Python API refuses the same values (its validate() runs in the constructor)."""
    cfg = SlamConfig()
    stages = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)
              if dataclasses.is_dataclass(getattr(cfg, f.name))}
    checked = 0
    for stage_name, stage in stages.items():
        for f in dataclasses.fields(stage):
            value = getattr(stage, f.name)
            if isinstance(value, float):
                with pytest.raises(ConfigError, match=re.escape(f"{stage_name}.{f.name}")):
                    dataclasses.replace(stage, **{f.name: math.nan}).validate()
                checked += 1
            elif isinstance(value, int) and not isinstance(value, bool) and not f.name.endswith("seed"):
                with pytest.raises(ConfigError, match=re.escape(f"{stage_name}.{f.name}")):
                    dataclasses.replace(stage, **{f.name: 10**20}).validate()
                checked += 1
    assert checked > 80


def test_check_number_intervals():
    check_number(0.0, "x", "[0, 1)")
    check_number(5, "n", "[1, inf)", integer=True)
    for value, interval in ((1.0, "[0, 1)"), (0.0, "(0, 1]"), (math.nan, None), (-math.inf, None), (2**31, None)):
        with pytest.raises(ConfigError, match=r"^x "):
            check_number(value, "x", interval, integer=isinstance(value, int))
    with pytest.raises(ConfigError, match=r"n must be an integer >= 1 and <= 2147483647 \(got 2147483648\)"):
        check_number(2**31, "n", "[1, inf)", integer=True)
    with pytest.raises(ConfigError, match=r"an integer"):
        check_number(1.5, "n", "[1, inf)", integer=True)
    check_number(2**80, "a.seed", "[0, inf)", integer=True)  # a seed: any size


def test_native_seed_is_the_seed_when_it_fits_and_a_fixed_32_bit_value_otherwise():
    for seed in (0, 1, 12345, C_INT_MAX, -1):
        assert native_seed(seed) == seed
    big = [2**31, 2**32, 2**64 + 7, 10**30]
    mapped = [native_seed(s) for s in big]
    assert all(0 <= m < C_INT_MAX for m in mapped)
    assert mapped == [native_seed(s) for s in big]  # deterministic
    assert len(set(mapped)) == len(mapped)
    assert native_seed(np.int64(2**40)) == native_seed(2**40)


def test_a_seed_beyond_32_bits_runs_and_repeats():
    """Any non-negative seed runs (pycolmap takes a C int): the same big seed twice, the same trajectory."""
    def run(seed):
        slam = Slam(synthetic_source("sideways", frames=24), SlamConfig(seed=seed, loop_closing=dataclasses.replace(
            SlamConfig().loop_closing, enabled=False)))
        slam.run()
        return slam.trajectory()

    a, b = run(2**64 + 3), run(2**64 + 3)
    assert len(a) >= 20
    np.testing.assert_array_equal(a.poses, b.poses)


def test_the_cli_refuses_a_bad_value_in_one_line(tmp_path: Path):
    """A ``--set`` value that used to fail inside pycolmap, and a huge ``--frame-skip``: one line naming the
    parameter, exit 2, no run (the other values: the generated test above, through the same ``with_overrides``)."""
    for setting, name in (("initializer.max_error_px=nan", "initializer.max_error_px"),):
        r = subprocess.run([sys.executable, "-m", "slamkit.cli", "run", "synthetic:sideways?frames=10", "--out",
                            str(tmp_path / "out"), "-q", "--set", setting], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and name in lines[0] and "Traceback" not in r.stderr, r.stderr
        assert not (tmp_path / "out").exists()
    r = subprocess.run([sys.executable, "-m", "slamkit.cli", "run", "synthetic:sideways?frames=10", "--out",
                        str(tmp_path / "out"), "-q", "--frame-skip", str(10**20)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "frame_skip" in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("spec, words", [
    ("synthetic:sideways?frames=1e11", "frames must be an integer >= 2 and <= 100000"),
    ("synthetic:sideways?frames=100001", "frames must be an integer >= 2 and <= 100000"),
    ("synthetic:block-loop?laps=1000000", "frames must be an integer >= 2 and <= 100000"),  # before allocating
    ("synthetic:sideways?noise=nan", "noise='nan' must be a finite number"),
    ("synthetic:sideways?speed=inf", "speed='inf' must be a finite number"),
    ("synthetic:handheld?seed=-1", "seed='-1' must be >= 0"),
])
def test_synthetic_specs_are_finite_and_bounded_before_allocating(spec, words):
    from slamkit.sources.synthetic import open_synthetic

    with pytest.raises(ConfigError, match=re.escape(words)):
        open_synthetic(spec)


def test_a_synthetic_seed_of_any_size_is_exact_and_deterministic():
    from slamkit.sources.synthetic import open_synthetic, parse_spec

    assert parse_spec(f"synthetic:handheld?seed={2**70 + 1}")[1]["seed"] == 2**70 + 1  # not rounded by a float
    a, b = (open_synthetic(f"synthetic:handheld?frames=5&noise=1&seed={2**70 + 1}") for _ in range(2))
    np.testing.assert_array_equal(a.gt_poses, b.gt_poses)
    np.testing.assert_array_equal(a.image(3), b.image(3))


def test_open_source_bounds_frame_skip_and_max_frames_too():
    """The Python API's ``open_source(..., frame_skip=)`` without a SlamConfig: the same one line."""
    from slamkit.sources import open_source

    for kw, name in ((dict(frame_skip=10**20), "frame_skip"), (dict(max_frames=10**20), "max_frames"),
                     (dict(frame_skip=0), "frame_skip")):
        with pytest.raises(ConfigError, match=f"^{name} must be >= 1 and <= 2147483647"):
            open_source("synthetic:sideways?frames=10", **kw)
