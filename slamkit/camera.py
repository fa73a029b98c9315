"""Camera intrinsics: pinhole + OpenCV distortion (k1, k2, p1, p2, k3).

slamkit works in *undistorted* pixel coordinates: keypoints are undistorted once, after extraction, and the
map uses an ideal pinhole camera with the same (fx, fy, cx, cy). This keeps every pycolmap estimator on the
PINHOLE model and makes distortion a property of the source only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .errors import CalibrationError, ConfigError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with OpenCV radial-tangential distortion.

    All values in pixels for an image of ``width`` x ``height``; ``dist`` is (k1, k2, p1, p2, k3).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        values = dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy)
        for name, v in values.items():
            if not math.isfinite(float(v)):
                raise CalibrationError(f"intrinsics: {name}={v} is not a finite number")
        for i, v in enumerate(self.dist):
            if not math.isfinite(float(v)):
                raise CalibrationError(f"intrinsics: distortion coefficient {i} ({v}) is not a finite number")
        if len(self.dist) != 5:
            raise CalibrationError(f"intrinsics: dist needs 5 values (k1 k2 p1 p2 k3), got {len(self.dist)}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f"intrinsics: image size {self.width}x{self.height} must be positive")
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f"intrinsics: focal lengths must be positive (fx={self.fx}, fy={self.fy})")
        lo, hi = focal_range(int(self.width), int(self.height))
        for name, f in (("fx", self.fx), ("fy", self.fy)):
            if not lo <= f <= hi:
                raise CalibrationError(
                    f"intrinsics: {name}={float(f):g} pixels is not a focal length of a {self.width}x{self.height} "
                    f"camera (sane: {lo:.4g} to {hi:.4g} pixels, fields of view between {MIN_FOV_DEG:g} and "
                    f"{MAX_FOV_DEG:g} degrees); check the calibration's units and image size")
        if not (0 < self.cx < self.width and 0 < self.cy < self.height):
            raise CalibrationError(
                f"intrinsics: principal point ({self.cx}, {self.cy}) lies outside the "
                f"{self.width}x{self.height} image"
            )

    @classmethod
    def from_focal(cls, width: int, height: int, focal: float | None = None) -> "Intrinsics":
        """Pinhole camera with the principal point at the centre; ``focal`` defaults to 1.2 x width
        (a ~45 degree horizontal field of view, COLMAP's default prior)."""
        f = 1.2 * max(width, height) if focal is None else float(focal)
        return cls(int(width), int(height), f, f, width / 2.0, height / 2.0)

    @classmethod
    def parse(cls, text: str, width: int, height: int, where: str = "camera") -> "Intrinsics":
        """Intrinsics of ``width`` x ``height`` images from a short text, as given on a command line:
        ``F`` (focal length in pixels, principal point at the centre), ``FX,FY,CX,CY``, or those followed by
        OpenCV's distortion ``K1,K2,P1,P2[,K3]``. Commas or spaces separate the numbers. A malformed text
        raises :class:`~slamkit.errors.ConfigError` naming ``where``; values that cannot be a camera of that
        size raise :class:`CalibrationError`."""
        values = parse_camera_values(text, where)
        if len(values) == 1:
            return cls.from_focal(width, height, values[0])
        dist = tuple(values[4:]) + (0.0,) * (9 - len(values))
        try:
            camera = cls(int(width), int(height), *values[:4], dist=dist)
            camera.check_distortion()
        except CalibrationError as e:
            raise CalibrationError(f"{where}={text!r}: {e}") from None
        return camera

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def is_guess(self) -> bool:
        """Whether these are the documented guess :meth:`from_focal` gives without a focal length (sources
        without any calibration return it; ``Slam`` then estimates the camera)."""
        return self == Intrinsics.from_focal(self.width, self.height)

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.dist)

    @property
    def pinhole(self) -> "Intrinsics":
        """The same camera without distortion (the camera of undistorted keypoints)."""
        return replace(self, dist=(0.0, 0.0, 0.0, 0.0, 0.0))

    def check_centred(self, where: str = "intrinsics") -> None:
        """Raise :class:`CalibrationError` when the principal point is more than a quarter of the image
        size away from the image centre: intrinsics from a calibration file without an image size (KITTI
        ``calib.txt``, 7-Scenes ``camera-intrinsics.txt``) were then almost surely measured for images of
        another size (about ``2 cx`` x ``2 cy``)."""
        if abs(self.cx - self.width / 2) < self.width / 4 and abs(self.cy - self.height / 2) < self.height / 4:
            return
        raise CalibrationError(
            f"{where}: principal point ({self.cx:.1f}, {self.cy:.1f}) is far from the centre of the "
            f"{self.width}x{self.height} images: the intrinsics are probably for another image size (about "
            f"{2 * self.cx + 1:.0f}x{2 * self.cy + 1:.0f}); pass camera=Intrinsics(...) if they are right")

    def check_distortion(self, where: str = "intrinsics") -> None:
        """Raise :class:`CalibrationError` naming the coefficient when the distortion is not one a lens
        produces over this image: the radial mapping r -> r (1 + k1 r^2 + k2 r^4 + k3 r^6) of undistorted to
        distorted radius must increase from the principal point out to the farthest image corner (where it
        folds back, several directions of view land on one pixel) and stretch the radius there at most
        :data:`MAX_STRETCH` times, the undistortion slamkit applies
        (:meth:`undistort_points`) must be monotonic along every ray from the principal point to the image
        border and be undone by the distortion within :data:`MAX_UNDISTORTION_ERROR_PX`, and the tangential
        coefficients must stay below :data:`MAX_TANGENTIAL`."""
        if not self.has_distortion:
            return
        k1, k2, p1, p2, k3 = self.dist
        for name, p in (("p1", p1), ("p2", p2)):
            if abs(p) > MAX_TANGENTIAL:
                raise CalibrationError(f"{where}: distortion {name}={p:g} is not what a lens produces (tangential "
                                       f"distortion beyond {MAX_TANGENTIAL:g}); check the order k1 k2 p1 p2 k3")
        w, h, f = self.width, self.height, max(self.fx, self.fy)
        t = np.linspace(0.0, 1.0, 65)[1:, None]
        ends = np.array([[0, 0], [w / 2, 0], [w, 0], [w, h / 2], [w, h], [w / 2, h], [0, h], [0, h / 2]], float)
        centre = np.array([self.cx, self.cy])
        rays = centre + t[None] * (ends[:, None] - centre)  # (8, 64, 2) distorted pixels out to the border
        r_image = float(np.hypot(*((ends - centre) / [self.fx, self.fy]).T).max())
        # the lens model: undistorted radii out to where it reaches the farthest corner, or folds back first
        r = np.linspace(0.0, 1.0, 4001)[1:] * max(4.0 * r_image, 4.0)
        r2 = r * r
        rd = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        fold = np.nonzero(1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3)) <= 0)[0]
        reach = np.nonzero(rd >= r_image)[0]
        problem = ""
        if not len(reach) or (len(fold) and fold[0] < reach[0]):
            top = float(rd[fold[0]]) if len(fold) else float(rd.max())
            problem = (f"the distortion mapping reaches at most {top * f:.0f} pixels from the principal point"
                       f"{' and folds back there' if len(fold) else ''}, but the image's farthest corner is "
                       f"{r_image * f:.0f} pixels out")
        elif r_image / np.interp(r_image, rd[: reach[0] + 1], r[: reach[0] + 1]) > MAX_STRETCH:
            stretch = r_image / np.interp(r_image, rd[: reach[0] + 1], r[: reach[0] + 1])
            problem = (f"it stretches the radius {stretch:.3g} times at the image's farthest corner (lenses: "
                       f"well under {MAX_STRETCH:g})")
        else:
            undistorted = self.undistort_points(rays.reshape(-1, 2))
            error = float(np.abs(self.distort_points(undistorted) - rays.reshape(-1, 2)).max())
            radius = np.linalg.norm(undistorted.reshape(rays.shape) - centre, axis=2)
            if not (np.isfinite(radius).all() and (np.diff(radius, axis=1) > 0).all()):
                problem = "the undistortion is not monotonic from the principal point to the image border"
            elif error > MAX_UNDISTORTION_ERROR_PX:
                problem = (f"undistorting the image border with it and distorting again is off by {error:.3g} "
                           f"pixels (more than {MAX_UNDISTORTION_ERROR_PX:g})")
        if not problem:
            return
        at = r[reach[0]] if len(reach) else r_image
        terms = {"k1": abs(k1) * at ** 2, "k2": abs(k2) * at ** 4, "k3": abs(k3) * at ** 6}
        name = max(terms, key=terms.get)
        raise CalibrationError(
            f"{where}: distortion {name}={dict(k1=k1, k2=k2, k3=k3)[name]:g} is not what a lens produces for a "
            f"{w}x{h} image (k1={k1:g}, k2={k2:g}, k3={k3:g}): {problem}; check the coefficients, their order "
            "(k1 k2 p1 p2 k3) and the image size")

    def check_image(self, shape: tuple[int, ...], where: str = "image") -> None:
        """Raise :class:`CalibrationError` when an image of ``shape`` (H, W[, C]) does not fit."""
        h, w = int(shape[0]), int(shape[1])
        if (w, h) != (self.width, self.height):
            raise CalibrationError(
                f"{where}: image is {w}x{h} but the intrinsics are for {self.width}x{self.height}"
            )

    def distort_points(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of the ideal pinhole camera -> (N, 2) float64 distorted pixels (OpenCV's model: the
        inverse of :meth:`undistort_points`)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion or len(xy) == 0:
            return xy.copy()
        k1, k2, p1, p2, k3 = self.dist
        x, y = (xy[:, 0] - self.cx) / self.fx, (xy[:, 1] - self.cy) / self.fy
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.column_stack([self.fx * xd + self.cx, self.fy * yd + self.cy])

    def undistort_points(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) distorted pixels -> (N, 2) float64 pixels of the ideal pinhole camera (OpenCV's iteration run
        to convergence, :data:`UNDISTORT_CRITERIA`: its default 5 steps leave pixels of error at the border of
        a real wide lens, 2.9 px for KITTI's raw cameras)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion or len(xy) == 0:
            return xy.copy()
        out = cv2.undistortPoints(xy.reshape(-1, 1, 2), self.K, np.asarray(self.dist), None, None, self.K,
                                  UNDISTORT_CRITERIA)
        return out.reshape(-1, 2).astype(np.float64)

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the image resized by ``factor`` (pixel-centre convention)."""
        return Intrinsics(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            dist=self.dist,
        )

    def to_dict(self) -> dict:
        return dict(width=self.width, height=self.height, fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy,
                    dist=list(self.dist))

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]), float(d["cx"]),
                   float(d["cy"]), tuple(float(x) for x in d.get("dist", (0, 0, 0, 0, 0))))


UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
"""Termination of OpenCV's undistortion iteration (steps, change in normalised coordinates)."""

MAX_STRETCH = 2.0
"""Largest ratio of distorted to undistorted radius at the image's farthest corner (lenses: about 0.5-1.2)."""

MAX_UNDISTORTION_ERROR_PX = 0.5
"""Largest error (pixels) of undistorting a point of the image border and distorting it again."""

MAX_TANGENTIAL = 0.1
"""Largest tangential distortion coefficient |p1|, |p2| accepted (real lenses: below about 0.01)."""

MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0
"""The fields of view (degrees, across the larger image side) a focal length may give: beyond them a value is
a typo or another unit (``--camera 1e12``, metres for pixels), and SLAM would only fail much later."""


def focal_range(width: int, height: int) -> tuple[float, float]:
    """(smallest, largest) sane focal length in pixels for ``width`` x ``height`` images (see
    :data:`MIN_FOV_DEG`)."""
    half = max(width, height) / 2.0
    return half / math.tan(math.radians(MAX_FOV_DEG / 2)), half / math.tan(math.radians(MIN_FOV_DEG / 2))


def parse_camera_values(text: str, where: str = "camera") -> list[float]:
    """The numbers of a camera text (see :meth:`Intrinsics.parse`): 1, 4, 8 or 9 finite floats, the focal
    lengths positive; :class:`~slamkit.errors.ConfigError` naming ``where`` otherwise."""
    fields = str(text).translate(str.maketrans(",()[]", "     ")).split()
    if not fields:
        raise ConfigError(f"{where}: {text!r} is empty; give F (focal length, pixels) or FX,FY,CX,CY[,distortion], "
                          "or leave the option out to use the source's intrinsics")
    usage = (f"{where}: expected F (focal length, pixels), FX,FY,CX,CY, or FX,FY,CX,CY,K1,K2,P1,P2[,K3] "
             f"(OpenCV distortion), got {text!r}")
    if len(fields) not in (1, 4, 8, 9):
        raise ConfigError(f"{usage}: {len(fields)} numbers")
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise ConfigError(f"{usage}: not a number") from None
    if not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{usage}: not finite")
    if values[0] <= 0 or (len(values) > 1 and values[1] <= 0):
        raise ConfigError(f"{usage}: focal lengths must be positive")
    return values
