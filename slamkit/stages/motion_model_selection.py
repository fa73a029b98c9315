"""Motion model selection between two views: a rotation only, or a general motion (issue 42).

With known intrinsics K a camera that only turns maps image points through the infinite homography
``K R K^-1`` (Hartley & Zisserman, 8.4.5): the pure-rotation model has 3 parameters and explains every match
whatever its depth. A general motion is an essential matrix (5 parameters). When the translation is too
small for its parallax to stand out of the keypoint noise, both models explain the matches and the essential
matrix's translation is noise; Torr's Geometric Robust Information Criterion (GRIC, Torr 1998, "Geometric
motion segmentation and model selection") chooses between them:

    GRIC = sum_i min(e_i^2 / sigma^2, 2 (r - d)) + d n ln(r) + k ln(r n)

with r = 4 (two image points per match), n matches, d the dimension of the model's manifold (2 for a
homography, 3 for an essential matrix), k its parameters (3 for a rotation, 5 for an essential matrix) and
e_i a match's distance to the manifold (pixels): for the rotation half the symmetric transfer error's squared
length, for the essential matrix the Sampson distance. The lower GRIC wins. ORB-SLAM's initializer scores a
homography against a fundamental matrix in the same spirit; PTAM and DT-SLAM switch to rotation-only tracking
on such a test. No COLMAP equivalent decides per frame (its two-view geometry labels a pair PANORAMIC from
inlier ratios, without the noise model).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pycolmap

from ..errors import check_fields, native_seed
from ..state import GENERAL, ROTATION  # the models chosen between (MotionModelChoice.model; "" = undecided)


@dataclass(frozen=True)
class MotionModelSelectionConfig:
    enabled: bool = True
    """Choose a motion model per frame, and pose frames that only turn by their rotation (issue 42); False:
    as before (no choice made, a pure rotation never posed)."""
    sigma_px: float = 1.0
    """Standard deviation of a keypoint's position, pixels (GRIC's noise model)."""
    min_matches: int = 20
    """Fewer matches: no choice ("" model)."""
    max_error_px: float = 3.0
    """RANSAC inlier threshold of both models, pixels."""
    ransac_iterations: int = 128
    """Hypotheses tried per model: for the rotation (two matches each), and at most this many for the
    essential matrix (five matches each; pycolmap's default of 1,000 at least costs ~0.3 s per frame)."""
    random_seed: int = 0
    min_rotation_only_deg: float = 5.0
    """A run without a map is posed as "rotation only" when its longest rotation chain turns at least this far
    from its first frame: a still camera has no rotation to show, and a small sideways step looks like a
    turn of a few degrees (0.17 m across a wall 3.2 m away: 3 degrees), so both stay unposed, their reason
    said."""

    def validate(self) -> "MotionModelSelectionConfig":
        check_fields(self, "motion_model", {"sigma_px": "(0, 100]", "min_matches": "[5, inf)",
                                            "min_rotation_only_deg": "[0, 180]",
                                            "max_error_px": "(0, 1e9]", "ransac_iterations": ("[1, 10000]", "scored at once: iterations x matches values in memory"),
                                            "random_seed": "[0, inf)"})
        return self


@dataclass(frozen=True, eq=False)
class MotionModelChoice:
    """What :meth:`MotionModelSelector.step` chose and why. ``rotation``: (3, 3) cam2_from_cam1 rotation of
    the pure-rotation model (None when undecided); ``inliers``: (N,) bool matches the chosen model explains."""

    model: str
    """"rotation", "general", or "" (too few matches to say)."""
    reason: str
    gric_rotation: float = math.nan
    gric_general: float = math.nan
    rotation: np.ndarray | None = None
    inliers: np.ndarray | None = None
    num_matches: int = 0
    rms_rotation_px: float = math.nan
    """RMS symmetric transfer error of the rotation model over its inliers, pixels."""

    @property
    def is_rotation(self) -> bool:
        return self.model == ROTATION


def rotation_from_bearings(b1: np.ndarray, b2: np.ndarray) -> np.ndarray:
    """(3, 3) rotation R minimising sum |b2 - R b1|^2 (Kabsch) over (N, 3) unit bearing vectors; (..., N, 3)
    batches give (..., 3, 3)."""
    H = np.swapaxes(b2, -1, -2) @ b1
    U, _, Vt = np.linalg.svd(H)
    D = np.ones(H.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def _bearings(xy: np.ndarray, K_inv: np.ndarray) -> np.ndarray:
    b = np.c_[xy, np.ones(len(xy))] @ K_inv.T
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _transfer_sq(R: np.ndarray, b1: np.ndarray, xy2: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., N) squared pixel distance between ``xy2`` and the bearings ``b1`` rotated by R (..., 3, 3) and
    projected by K; behind the camera: inf."""
    p = (K @ R) @ b1.T  # (..., 3, N)
    z = p[..., 2, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = (p[..., 0, :] / z - xy2[:, 0]) ** 2 + (p[..., 1, :] / z - xy2[:, 1]) ** 2
    return np.where(z > 1e-9, d, np.inf)


def gric(errors_sq: np.ndarray, sigma: float, d: int, k: int, r: int = 4) -> float:
    """Torr's GRIC of a model: ``errors_sq`` (N,) squared distances to its manifold (pixels^2), manifold
    dimension ``d``, ``k`` parameters, data dimension ``r``."""
    n = len(errors_sq)
    rho = np.minimum(np.asarray(errors_sq) / sigma**2, 2.0 * (r - d))
    return float(rho.sum() + d * n * math.log(r) + k * math.log(r * n))


def sampson_sq(F: np.ndarray, xy1: np.ndarray, xy2: np.ndarray) -> np.ndarray:
    """(N,) squared Sampson distances (pixels^2) of matches ``xy1`` <-> ``xy2`` (N, 2) to fundamental matrix F."""
    x1, x2 = np.c_[xy1, np.ones(len(xy1))], np.c_[xy2, np.ones(len(xy2))]
    Fx1, Ftx2 = x1 @ F.T, x2 @ F
    num = np.einsum("ij,ij->i", x2, Fx1) ** 2
    return num / np.maximum(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2, 1e-300)


class MotionModelSelector:
    """Chooses rotation-only or general motion for a frame's matches to a reference view (GRIC)."""

    def __init__(self, config: MotionModelSelectionConfig = MotionModelSelectionConfig()):
        self.config = config.validate()
        ransac = pycolmap.RANSACOptions()
        ransac.max_error = config.max_error_px
        ransac.random_seed = native_seed(config.random_seed)
        ransac.min_num_trials = min(ransac.min_num_trials, config.ransac_iterations)
        ransac.max_num_trials = config.ransac_iterations
        ransac.confidence = 0.999
        self._ransac = ransac

    def estimate_rotation(self, xy1: np.ndarray, xy2: np.ndarray, K: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pure-rotation model of matches ``xy1`` -> ``xy2`` ((N, 2) pixels, N >= 2): RANSAC over pairs
        of matches, then Kabsch on the inliers. Returns (R (3, 3) cam2_from_cam1, squared symmetric transfer
        errors (N,) pixels^2 (mean of both directions), inliers (N,) bool)."""
        c = self.config
        K_inv = np.linalg.inv(K)
        b1, b2 = _bearings(xy1, K_inv), _bearings(xy2, K_inv)
        rng = np.random.default_rng(c.random_seed)
        n = len(b1)
        i = rng.integers(0, n, (c.ransac_iterations, 2))
        i[:, 1] = np.where(i[:, 0] == i[:, 1], (i[:, 1] + 1) % n, i[:, 1])
        Rs = rotation_from_bearings(b1[i], b2[i])  # (H, 3, 3)
        err = _transfer_sq(Rs, b1, xy2, K)
        best = int(np.argmax((err < c.max_error_px**2).sum(axis=1)))
        inliers = err[best] < c.max_error_px**2
        R = Rs[best]
        for _ in range(2):  # re-estimate on the inliers, then re-classify
            if inliers.sum() >= 2:
                R = rotation_from_bearings(b1[inliers], b2[inliers])
            sym = 0.5 * (_transfer_sq(R, b1, xy2, K) + _transfer_sq(R.T, b2, xy1, K))
            inliers = sym < c.max_error_px**2
        return R, sym, inliers

    def step(self, xy_ref: np.ndarray, xy_cur: np.ndarray, K: np.ndarray) -> MotionModelChoice:
        """Choose the motion model of matches ``xy_ref`` (reference view) <-> ``xy_cur`` (this frame), both
        (N, 2) float64 undistorted pixels of one pinhole camera ``K`` (3, 3)."""
        c = self.config
        xy_ref, xy_cur = np.asarray(xy_ref, np.float64).reshape(-1, 2), np.asarray(xy_cur, np.float64).reshape(-1, 2)
        n = len(xy_ref)
        if n < c.min_matches:
            return MotionModelChoice("", f"{n} matches < {c.min_matches}: no motion model chosen", num_matches=n)
        R, sym, inl_rot = self.estimate_rotation(xy_ref, xy_cur, K)
        g_rot = gric(0.5 * sym, c.sigma_px, d=2, k=3)  # half the transfer error: noise in both images
        rms = float(np.sqrt(sym[inl_rot].mean())) if inl_rot.any() else math.nan
        cam = pycolmap.Camera(model="PINHOLE", width=int(2 * K[0, 2] + 1), height=int(2 * K[1, 2] + 1),
                              params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        est = pycolmap.estimate_essential_matrix(xy_ref, xy_cur, cam, cam, self._ransac)
        if est is None:
            g_gen, inl_gen = math.inf, np.zeros(n, bool)
        else:
            K_inv = np.linalg.inv(K)
            F = K_inv.T @ np.asarray(est["E"]) @ K_inv
            e = sampson_sq(F, xy_ref, xy_cur)
            g_gen, inl_gen = gric(e, c.sigma_px, d=3, k=5), e < c.max_error_px**2
        angle = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(R) - 1) / 2))))
        if g_rot <= g_gen:
            return MotionModelChoice(ROTATION, f"rotation only ({angle:.1f} deg): GRIC {g_rot:.0f} <= {g_gen:.0f} "
                                     f"of an essential matrix ({int(inl_rot.sum())}/{n} inliers, transfer "
                                     f"{rms:.2f} px)", g_rot, g_gen, R, inl_rot, n, rms)
        return MotionModelChoice(GENERAL, f"general motion: essential-matrix GRIC {g_gen:.0f} < {g_rot:.0f} of a "
                                 f"rotation ({int(inl_gen.sum())}/{n} inliers; rotation transfer {rms:.2f} px)",
                                 g_rot, g_gen, R, inl_gen, n, rms)


__all__ = ["GENERAL", "ROTATION", "MotionModelChoice", "MotionModelSelectionConfig", "MotionModelSelector", "gric",
           "rotation_from_bearings", "sampson_sq"]
