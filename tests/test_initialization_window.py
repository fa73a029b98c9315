"""The initializer at any speed and length: the motion window, the last attempt at the end of a sequence and
the forward check of a candidate pair, on synthetic sequences with exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit import Slam, SlamConfig, ate, open_source
from slamkit.errors import ConfigError
from slamkit.frames import FrameLoader
from slamkit.features import create_extractor
from slamkit.stages.initializer import Initializer, InitializerConfig


def _features(spec: str, n: int, skip: int = 1):
    src = open_source(spec)
    loader = FrameLoader(src)
    loader.configure(np.arange(0, len(src), skip)[:n], create_extractor("orb", num_features=2000), src.camera, False)
    out = []
    for i in range(n):
        frame, ff, *_ = loader.next(i)
        out.append(ff)
    return src, out


@pytest.mark.parametrize("frames", [4, 9])
def test_a_sequence_shorter_than_the_window_is_initialized_and_posed(frames):
    """4 or 9 frames of the default loop, 10 frames apart (a third of a second each, like TUM's short
    sequences): fewer than the 20-frame window, so the initializer tries the pair when the sequence ends and
    every frame is posed."""
    src = open_source("default")
    slam = Slam(src, SlamConfig().with_overrides(frame_skip=10, max_frames=frames))
    results = slam.run()
    assert any(r.status == "initialized" for r in results), results[-1].message
    assert slam.summary()["frames_posed"] == frames
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.01          # metres, on a 5.7 m loop


def test_the_motion_window_closes_early_under_fast_motion():
    """At 1.5 m per frame down the street the window's first frame shares half its matches with the newest
    frame after a few frames: the pair is tried then, not after 20 frames (30 m)."""
    src, ffs = _features("synthetic:street-drive?frames=20&speed=1.5&noise=1&seed=1", 20)
    init = Initializer(src.camera, InitializerConfig(window_overlap=0.3))
    tried = next(i for i, ff in enumerate(ffs) if init.step(ff).status != "collecting")
    assert tried < 10
    fixed = Initializer(src.camera, InitializerConfig(window_overlap=0))
    assert [fixed.step(ff).status for ff in ffs[:19]] == ["collecting"] * 19


def test_initializer_window_config_is_validated():
    for bad in ({"window_overlap": 1.0}, {"verify_frames": -1}, {"min_verify_ratio": 1.5},
                {"min_points_at_end": 200}):
        with pytest.raises(ConfigError):
            InitializerConfig(**bad).validate()
