"""A textured planar 3D scene and its exact renderer: the geometry behind the synthetic sequences.

The scene is a set of textured rectangles (:class:`Quad`). An image is rendered *exactly* for a pinhole
camera: every pixel centre casts a ray, the ray's depth on each quad's plane is ``z = d / (n . r)`` (``r`` the
ray with unit z in camera coordinates, ``n . X = d`` the plane), the nearest quad in front of the near plane
wins (a z-buffer), and its texture is sampled at the exact texture coordinate of the hit point (bilinear,
trilinear between mipmap levels when the texture is minified). So a 3D point on a quad projects with the
pose and intrinsics exactly where its texel appears, up to the 1/32 texel resolution of OpenCV's remap.

Conventions: world frame with z up, metres; poses are (4, 4) camera-to-world with OpenCV camera axes (x right,
y down, z forward); pixel centres are at integer coordinates (as :class:`~slamkit.camera.Intrinsics`).
Texel ``(i, j)`` (column, row) of a quad's texture of size W x H covers the quad fractions
``[i/W, (i+1)/W] x [j/H, (j+1)/H]`` along ``edge_u`` and ``edge_v``.

Lighting is Lambertian with fixed point lights and baked into the textures when the scene is built, so the
appearance of a surface point does not depend on the viewpoint (a brightness-constancy world).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from ..camera import Intrinsics
from ..errors import ConfigError

#: Near plane of the renderer, metres: geometry closer to the camera centre is clipped.
NEAR = 0.02


# ----------------------------------------------------------------------------------------------------------
# poses


def look_at(center, target, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """(4, 4) camera-to-world pose of a camera at ``center`` looking at ``target`` (metres, world frame).

    The camera's y axis (image down) is aligned with ``-up`` as far as possible, then rotated by ``roll``
    radians about the optical axis.
    """
    c = np.asarray(center, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - c
    f /= np.linalg.norm(f)
    x = np.cross(f, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ConfigError("look_at: the viewing direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    if roll:
        cr, sr = math.cos(roll), math.sin(roll)
        x, y = cr * x + sr * y, -sr * x + cr * y
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, f, c
    return pose


def project(pose: np.ndarray, intrinsics: Intrinsics, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project (N, 3) world points with a camera-to-world ``pose`` -> ((N, 2) float64 pixels, (N,) z-depth).

    Points behind the camera get a negative depth (their pixels are meaningless).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    R = pose[:3, :3]
    xc = (pts - pose[:3, 3]) @ R  # = R^T (X - C)
    z = xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics.fx * xc[:, 0] / z + intrinsics.cx
        v = intrinsics.fy * xc[:, 1] / z + intrinsics.cy
    return np.stack([u, v], axis=1), z


# ----------------------------------------------------------------------------------------------------------
# textures


class Texture:
    """A BGR uint8 texture and its mipmap pyramid: ``levels[k]`` (BGRA, alpha 255: four bytes a texel sample
    fast) is level 0 reduced about ``2**k`` times, ``scales[k]`` the exact (x, y) size ratio of level k to 0.

    Levels are made by a Gaussian blur and a 2x2 area average, which keeps the pixel-centre convention
    (texel j of level k+1 is centred on texels 2j, 2j+1 of level k), so sampling a level never shifts the
    texture (``cv2.pyrDown`` would shift it by half a texel).
    """

    def __init__(self, image: np.ndarray):
        import cv2

        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ConfigError(f"texture: need an (H, W, 3) uint8 BGR image, got {image.shape} {image.dtype}")
        h0, w0 = image.shape[:2]
        levels = [cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)]
        scales = [(1.0, 1.0)]
        while min(levels[-1].shape[:2]) >= 16:
            prev = levels[-1]
            h, w = prev.shape[0] // 2, prev.shape[1] // 2
            levels.append(cv2.resize(cv2.GaussianBlur(prev, (0, 0), 0.8), (w, h), interpolation=cv2.INTER_AREA))
            scales.append((w / w0, h / h0))
        for level in levels:
            level.setflags(write=False)
        self.levels: list[np.ndarray] = levels
        self.scales: list[tuple[float, float]] = scales

    @property
    def image(self) -> np.ndarray:
        """(H, W, 3) uint8 BGR level 0 (a read-only view)."""
        return self.levels[0][..., :3]

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in texels."""
        return self.levels[0].shape[1], self.levels[0].shape[0]


@dataclass(eq=False)
class Quad:
    """A textured rectangle: corners ``origin``, ``origin + edge_u``, ``origin + edge_u + edge_v``,
    ``origin + edge_v`` (world, metres). The texture's columns run along ``edge_u``, its rows along ``edge_v``
    (so ``origin`` is the texture's top-left corner). Quads are two-sided."""

    name: str
    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    texture: Texture | None = None

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.edge_u = np.asarray(self.edge_u, dtype=np.float64).reshape(3)
        self.edge_v = np.asarray(self.edge_v, dtype=np.float64).reshape(3)
        lu, lv = np.linalg.norm(self.edge_u), np.linalg.norm(self.edge_v)
        if not (lu > 0 and lv > 0):
            raise ConfigError(f"quad {self.name!r}: edges must have a positive length")
        if abs(self.edge_u @ self.edge_v) > 1e-9 * lu * lv:
            raise ConfigError(f"quad {self.name!r}: edge_u and edge_v must be orthogonal")
        # derived geometry (the geometry fields are not meant to change after construction)
        n = np.cross(self.edge_u, self.edge_v)
        self._normal = n / np.linalg.norm(n)
        o, u, v = self.origin, self.edge_u, self.edge_v
        self._corners = np.stack([o, o + u, o + u + v, o + v])
        self._u_dual = u / (u @ u)  # a = (X - origin) . u_dual
        self._v_dual = v / (v @ v)

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal ``edge_u x edge_v``."""
        return self._normal.copy()

    @property
    def corners(self) -> np.ndarray:
        """(4, 3) world corners in order origin, +u, +u+v, +v."""
        return self._corners.copy()

    def point(self, a, b) -> np.ndarray:
        """World point(s) at quad fractions ``a`` along ``edge_u`` and ``b`` along ``edge_v`` -> (..., 3)."""
        a = np.asarray(a, dtype=np.float64)[..., None]
        b = np.asarray(b, dtype=np.float64)[..., None]
        return self.origin + a * self.edge_u + b * self.edge_v

    def texel_point(self, s, t) -> np.ndarray:
        """World point(s) at continuous texel coordinates (``s`` column, ``t`` row; texel centres at
        integers, as pixels) -> (..., 3)."""
        w, h = self.texture.size if self.texture is not None else (1, 1)
        return self.point((np.asarray(s, dtype=np.float64) + 0.5) / w, (np.asarray(t, dtype=np.float64) + 0.5) / h)


@functools.lru_cache(maxsize=8)
def _pixel_rays(intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Read-only (H*W,) float32 x and y components of the ray (unit z) of every pixel, row-major."""
    W, H = intrinsics.width, intrinsics.height
    rx = np.tile(((np.arange(W) - intrinsics.cx) / intrinsics.fx).astype(np.float32), H)
    ry = np.repeat(((np.arange(H) - intrinsics.cy) / intrinsics.fy).astype(np.float32), W)
    rx.setflags(write=False)
    ry.setflags(write=False)
    return rx, ry


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a (K, 3) camera-frame polygon to ``z >= near``."""
    out = []
    k = len(poly)
    for i in range(k):
        p, q = poly[i], poly[(i + 1) % k]
        pin, qin = p[2] >= near, q[2] >= near
        if pin:
            out.append(p)
        if pin != qin:
            s = (near - p[2]) / (q[2] - p[2])
            out.append(p + s * (q - p))
    return np.array(out).reshape(-1, 3)


def _clip_rect(poly: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a (K, 2) image polygon to the rectangle [x0, x1] x [y0, y1]."""
    for axis, bound, keep_above in ((0, x0, True), (0, x1, False), (1, y0, True), (1, y1, False)):
        if len(poly) == 0:
            break
        out = []
        k = len(poly)
        for i in range(k):
            p, q = poly[i], poly[(i + 1) % k]
            pin = p[axis] >= bound if keep_above else p[axis] <= bound
            qin = q[axis] >= bound if keep_above else q[axis] <= bound
            if pin:
                out.append(p)
            if pin != qin:
                s = (bound - p[axis]) / (q[axis] - p[axis])
                out.append(p + s * (q - p))
        poly = np.array(out).reshape(-1, 2)
    return poly


def _camera_plane(quad: Quad, Rt: np.ndarray, C: np.ndarray):
    """The quad in camera coordinates: (n, d, Ua, ao, Vb, bo) with plane ``n . X = d`` and quad fractions
    ``a = Ua . X - ao``, ``b = Vb . X - bo`` of a camera point X; None when the camera lies in the plane."""
    n = Rt @ quad._normal
    o = Rt @ (quad.origin - C)
    d = float(n @ o)
    if abs(d) < 1e-12:
        return None
    Ua = Rt @ quad._u_dual
    Vb = Rt @ quad._v_dual
    return n, d, Ua, float(Ua @ o), Vb, float(Vb @ o)


@dataclass(frozen=True, eq=False)
class Rendering:
    """What :meth:`Scene.render` produced. ``image`` (H, W, 3) uint8 BGR; ``depth`` (H, W) float64 z-depth in
    metres of each pixel centre (inf where no quad is hit); ``quad`` (H, W) int16 index of the visible quad
    in ``Scene.quads`` (-1 where none)."""

    image: np.ndarray | None
    depth: np.ndarray
    quad: np.ndarray


@dataclass(eq=False)
class Scene:
    """A set of textured quads rendered with a z-buffer.

    ``background`` is the BGR colour of pixels that see no quad; ``lod_bias`` shifts the mipmap level;
    ``bounds`` is an optional (2, 3) box (min corner, max corner; metres) holding the scene, e.g. a room.
    """

    quads: list[Quad]
    name: str = "scene"
    background: tuple[int, int, int] = (0, 0, 0)
    #: Added to the mipmap level (log2 of the texel footprint of a pixel): < 0 sharper, > 0 blurrier.
    lod_bias: float = 0.0
    bounds: np.ndarray | None = field(default=None)

    # ---- rendering

    def render(self, pose: np.ndarray, intrinsics: Intrinsics, *, texture: bool = True) -> Rendering:
        """Render the scene seen by a camera with camera-to-world ``pose`` (4, 4) and pinhole ``intrinsics``
        (distortion is not modelled and must be zero). With ``texture=False`` only depth and quad ids.

        Two passes. The z-buffer pass rasterises each quad's near-clipped, projected polygon: pixels more
        than a pixel inside it are inside the quad, pixels near its outline get the exact analytic test
        (quad fractions in [0, 1)); depths are analytic everywhere. The texturing pass then samples each
        quad's texture at the exact texture coordinates of the pixels it won.
        """
        import cv2

        if intrinsics.has_distortion:
            raise ConfigError("Scene.render: the renderer is pinhole only; intrinsics.dist must be zero")
        W, H = intrinsics.width, intrinsics.height
        fx, fy = intrinsics.fx, intrinsics.fy
        pose = np.asarray(pose, dtype=np.float64)
        Rt = pose[:3, :3].T  # world -> camera rotation
        C = pose[:3, 3]
        rx_all = (np.arange(W) - intrinsics.cx) / fx
        ry_all = (np.arange(H) - intrinsics.cy) / fy
        zbuf = np.full((H, W), np.inf)
        qbuf = np.full((H, W), -1, dtype=np.int16)
        planes, boxes = [], {}
        for qi, quad in enumerate(self.quads):
            plane = _camera_plane(quad, Rt, C)
            planes.append(plane)
            if plane is None:
                continue
            poly = _clip_near((quad._corners - C) @ Rt.T, NEAR)
            if len(poly) < 3:
                continue
            uv = np.stack([fx * poly[:, 0] / poly[:, 2] + intrinsics.cx,
                           fy * poly[:, 1] / poly[:, 2] + intrinsics.cy], axis=1)
            uv = _clip_rect(uv, -2.0, -2.0, W + 1.0, H + 1.0)
            if len(uv) < 3:
                continue
            x0, y0 = max(int(math.floor(uv[:, 0].min())) - 2, 0), max(int(math.floor(uv[:, 1].min())) - 2, 0)
            x1, y1 = min(int(math.ceil(uv[:, 0].max())) + 2, W - 1), min(int(math.ceil(uv[:, 1].max())) + 2, H - 1)
            if x0 > x1 or y0 > y1:
                continue
            boxes[qi] = (x0, y0, x1, y1)
            # 1 = surely inside the quad, 2 = within about 1.5 px of its outline (tested exactly)
            mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), dtype=np.uint8)
            pts = np.round((uv - (x0, y0)) * 16).astype(np.int32).reshape(-1, 1, 2)
            cv2.fillConvexPoly(mask, pts, 1, cv2.LINE_8, 4)
            cv2.polylines(mask, [pts], True, 2, 5, cv2.LINE_8, 4)
            n, d, Ua, ao, Vb, bo = plane
            zsub, qsub = zbuf[y0:y1 + 1, x0:x1 + 1], qbuf[y0:y1 + 1, x0:x1 + 1]
            rx, ry = rx_all[x0:x1 + 1], ry_all[y0:y1 + 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                z = d / ((n[0] * rx + n[2])[None, :] + (n[1] * ry)[:, None])
                win = (mask == 1) & (z < zsub)
                np.copyto(zsub, z, where=win)
                qsub[win] = qi
                yy, xx = np.nonzero(mask == 2)
                rxe, rye, ze = rx[xx], ry[yy], z[yy, xx]
                a = ze * (Ua[0] * rxe + Ua[1] * rye + Ua[2]) - ao
                b = ze * (Vb[0] * rxe + Vb[1] * rye + Vb[2]) - bo
                ok = (ze > NEAR) & (ze < zsub[yy, xx]) & (a >= 0) & (a < 1) & (b >= 0) & (b < 1)
            yy, xx = yy[ok], xx[ok]
            zsub[yy, xx] = ze[ok]
            qsub[yy, xx] = qi
        image = None
        if texture:
            image = self._texture(intrinsics, zbuf, qbuf, planes, boxes, cv2)
        return Rendering(image=image, depth=zbuf, quad=qbuf)

    def _texture(self, intrinsics: Intrinsics, zbuf: np.ndarray, qbuf: np.ndarray, planes: list, boxes: dict,
                 cv2) -> np.ndarray:
        """The texturing pass: (H, W, 3) uint8 image from the z-buffer, the quad ids, each quad's camera
        plane and the bounding box (x0, y0, x1, y1) of its projection."""
        W, H = intrinsics.width, intrinsics.height
        f32 = np.float32
        # BGRA pixels as one uint32 each: scattering 4-byte items is far faster than 3-byte rows
        out = np.empty((H * W, 4), dtype=np.uint8)
        out[:] = np.asarray((*self.background, 255), dtype=np.uint8)
        out = out.view(np.uint32).reshape(H * W)
        q = qbuf.ravel()
        order = np.argsort(q, kind="stable")
        ends = np.cumsum(np.bincount(q.astype(np.int64) + 1, minlength=len(self.quads) + 1))
        rx_all, ry_all = _pixel_rays(intrinsics)
        z_all = zbuf.ravel().astype(f32)
        lod_img = np.zeros((H, W), dtype=f32)
        for qi, quad in enumerate(self.quads):
            if ends[qi + 1] > ends[qi] and quad.texture is not None:
                self._mip_levels(intrinsics, quad, planes[qi], boxes[qi], qbuf, qi, lod_img, cv2)
        lod_all = lod_img.ravel()
        for qi, quad in enumerate(self.quads):
            flat = order[ends[qi]:ends[qi + 1]]  # pixels won by quad qi (qbuf == qi)
            if len(flat) == 0 or quad.texture is None:
                continue
            n, d, Ua, ao, Vb, bo = planes[qi]
            rx, ry, z = rx_all[flat], ry_all[flat], z_all[flat]
            tw, th = quad.texture.size
            # texel coordinates s = a * tw - 0.5, t = b * th - 0.5 of the quad fractions a, b of the
            # pixel's point z * (rx, ry, 1)
            s = z * (f32(Ua[0] * tw) * rx + f32(Ua[1] * tw) * ry + f32(Ua[2] * tw))
            s -= f32(ao * tw + 0.5)
            t = z * (f32(Vb[0] * th) * rx + f32(Vb[1] * th) * ry + f32(Vb[2] * th))
            t -= f32(bo * th + 0.5)
            out[flat] = _sample_trilinear(quad.texture, s, t, lod_all[flat], cv2)
        return cv2.cvtColor(out.view(np.uint8).reshape(H, W, 4), cv2.COLOR_BGRA2BGR)

    def _mip_levels(self, intrinsics: Intrinsics, quad: Quad, plane, box, qbuf: np.ndarray, qi: int,
                    lod_img: np.ndarray, cv2) -> None:
        """Write the mipmap level (log2 of the texel footprint of a pixel, plus ``lod_bias``) of the pixels of
        quad ``qi`` into ``lod_img``. The footprint is the longer column of the Jacobian of the texel
        coordinates w.r.t. the pixel, analytic for a plane (da/dx = z/fx (Ua_x - (a + ao) n_x / d), etc.);
        it is evaluated every 8 pixels and interpolated, as it varies slowly."""
        n, d, Ua, ao, Vb, bo = plane
        x0, y0, x1, y1 = box
        bw, bh = x1 - x0 + 1, y1 - y0 + 1
        nx, ny = -(-bw // 8), -(-bh // 8)
        # grid point k sits at pixel x0 + 3.5 + 8k: where cv2.resize by 8 puts it (pixel-centre convention)
        rx = ((x0 + 3.5 + 8 * np.arange(nx) - intrinsics.cx) / intrinsics.fx)[None, :]
        ry = ((y0 + 3.5 + 8 * np.arange(ny) - intrinsics.cy) / intrinsics.fy)[:, None]
        tw, th = quad.texture.size
        nlev = len(quad.texture.levels)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            z = d / (n[0] * rx + n[1] * ry + n[2])
            ua = z * (Ua[0] * rx + Ua[1] * ry + Ua[2])  # = a + ao
            vb = z * (Vb[0] * rx + Vb[1] * ry + Vb[2])  # = b + bo
            kx, ky = z / intrinsics.fx, z / intrinsics.fy
            dsdx = tw * kx * (Ua[0] - ua * n[0] / d)
            dsdy = tw * ky * (Ua[1] - ua * n[1] / d)
            dtdx = th * kx * (Vb[0] - vb * n[0] / d)
            dtdy = th * ky * (Vb[1] - vb * n[1] / d)
            foot2 = np.maximum(dsdx ** 2 + dtdx ** 2, dsdy ** 2 + dtdy ** 2)
            lod = 0.5 * np.log2(foot2) + self.lod_bias
        lod = np.where((z > 0) & np.isfinite(lod), lod, nlev - 1)  # grid points beyond the plane's horizon
        lod = np.clip(lod, 0.0, nlev - 1).astype(np.float32)
        if nx > 1 or ny > 1:
            lod = cv2.resize(lod, (8 * nx, 8 * ny), interpolation=cv2.INTER_LINEAR)
        else:
            lod = np.broadcast_to(lod, (8, 8))
        sub = lod_img[y0:y1 + 1, x0:x1 + 1]
        np.copyto(sub, lod[:bh, :bw], where=qbuf[y0:y1 + 1, x0:x1 + 1] == qi)

    def depth(self, pose: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """(H, W) float64 exact z-depth (metres) of every pixel centre; inf where no quad is hit."""
        return self.render(pose, intrinsics, texture=False).depth

    # ---- ray casting

    def raycast(self, pose: np.ndarray, intrinsics: Intrinsics, pixels: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast rays through (N, 2) float pixel coordinates (any sub-pixel position, pinhole).

        Returns ((N, 3) world points of the first hit, (N,) z-depth in metres, (N,) quad index); points are
        NaN, depth inf and index -1 for rays that hit nothing.
        """
        xy = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        pose = np.asarray(pose, dtype=np.float64)
        R, C = pose[:3, :3], pose[:3, 3]
        rays_c = np.stack([(xy[:, 0] - intrinsics.cx) / intrinsics.fx,
                           (xy[:, 1] - intrinsics.cy) / intrinsics.fy, np.ones(len(xy))], axis=1)
        rays_w = rays_c @ R.T  # world direction with unit camera z
        best = np.full(len(xy), np.inf)
        idx = np.full(len(xy), -1, dtype=np.int64)
        for qi, quad in enumerate(self.quads):
            n = quad.normal
            with np.errstate(divide="ignore", invalid="ignore"):
                z = (n @ (quad.origin - C)) / (rays_w @ n)
                p = C + z[:, None] * rays_w - quad.origin
                a = p @ quad.edge_u / (quad.edge_u @ quad.edge_u)
                b = p @ quad.edge_v / (quad.edge_v @ quad.edge_v)
                hit = (z > NEAR) & (z < best) & (a >= 0) & (a < 1) & (b >= 0) & (b < 1)
            best[hit] = z[hit]
            idx[hit] = qi
        pts = C + best[:, None] * rays_w
        pts[idx < 0] = np.nan
        return pts, best, idx

    def points(self, pose: np.ndarray, intrinsics: Intrinsics, pixels: np.ndarray) -> np.ndarray:
        """(N, 3) exact world points seen at (N, 2) pixel coordinates (NaN where nothing is hit)."""
        return self.raycast(pose, intrinsics, pixels)[0]

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: the points lie inside the scene's bounding box ``bounds`` shrunk by ``margin`` metres."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.bounds is None:
            return np.ones(len(pts), dtype=bool)
        lo, hi = self.bounds[0] + margin, self.bounds[1] - margin
        return np.all((pts >= lo) & (pts <= hi), axis=1)


def _sample_trilinear(tex: Texture, s: np.ndarray, t: np.ndarray, lod: np.ndarray, cv2) -> np.ndarray:
    """(N,) uint32 BGRA colours of texture ``tex`` at float32 texel coordinates (s, t) of level 0, blending
    the two mipmap levels around ``lod`` (bilinear at level 0 where ``lod <= 0``)."""
    nlev = len(tex.levels)
    l0 = lod.astype(np.int8)  # floor, as 0 <= lod <= nlev - 1
    lo, hi = int(l0.min()), int(l0.max())
    out = None if lo == hi else np.empty(len(s), dtype=np.uint32)
    for level in range(lo, hi + 1):
        if lo == hi:
            sel, ss, tt, f = slice(None), s, t, lod
        else:
            sel = np.flatnonzero(l0 == level)
            if len(sel) == 0:
                continue
            ss, tt, f = s[sel], t[sel], lod[sel]
        f = f - np.float32(level)  # weight of the next level
        c = _sample(tex, level, ss, tt, cv2)
        if level + 1 < nlev and f.max() > 1e-3:
            c1 = _sample(tex, level + 1, ss, tt, cv2)
            w1 = _pad_rows(f, c.shape[0])
            c = cv2.blendLinear(c, c1, 1.0 - w1, w1)
        c = c.view(np.uint32).reshape(-1)[:len(ss)]
        if out is None:
            return c
        out[sel] = c
    return out


_ROW = 1024  # remap's maps must be narrower than SHRT_MAX: sample N points as a (N/1024, 1024) image


def _pad_rows(v: np.ndarray, rows: int, scale: float = 1.0, offset: float = 0.0) -> np.ndarray:
    """(N,) float32 -> (rows, 1024) float32 holding ``v * scale + offset``, zero-padded."""
    out = np.zeros(rows * _ROW, dtype=np.float32)
    if scale == 1.0 and offset == 0.0:
        out[:len(v)] = v
    else:
        np.multiply(v, np.float32(scale), out=out[:len(v)])
        out[:len(v)] += np.float32(offset)
    return out.reshape(rows, _ROW)


def _sample(tex: Texture, level: int, s: np.ndarray, t: np.ndarray, cv2) -> np.ndarray:
    """(rows, 1024, 4) uint8 bilinear samples of mipmap ``level`` of ``tex`` at level-0 texel coordinates
    (s, t) (N of them, zero-padded to whole rows)."""
    sx, sy = tex.scales[level]
    rows = -(-len(s) // _ROW)
    mx = _pad_rows(s, rows, sx, 0.5 * sx - 0.5)
    my = _pad_rows(t, rows, sy, 0.5 * sy - 0.5)
    return cv2.remap(tex.levels[level], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)


# ----------------------------------------------------------------------------------------------------------
# texture synthesis (deterministic: every texture draws from its own seeded numpy Generator)

_PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry", "retina",
           "motorcycle", "logo", "camera", "brick", "grass", "gravel", "text", "coins", "moon", "page", "clock",
           "cell")
"""scikit-image sample photographs that ship inside its wheel (no download needed)."""

_WORDS = ("SLAM", "COLMAP", "ORB", "keyframe", "bundle", "loop", "pose", "map", "track", "Zurich", "room 42",
          "EXIT", "notes", "2025", "x=3.14", "parallax", "depth", "motion", "A4", "lab", "frame", "camera",
          "vision", "north", "sift", "view", "point", "cloud", "graph", "match", "todo", "call Bob", "Mon 9:00",
          "meeting", "budget", "v2.1", "#17", "OK", "fix bug", "room B", "tel 4471", "lunch", "RANSAC", "P3P",
          "Ceres", "g2o", "Sim(3)", "BA", "epipole", "homography", "KLT", "FAST", "BRIEF")


@functools.lru_cache(maxsize=None)
def photo(name: str) -> np.ndarray:
    """A scikit-image sample photograph as (H, W, 3) uint8 BGR (read-only). Only photographs bundled in the
    scikit-image wheel are offered, so this never touches the network."""
    import warnings

    import cv2

    if name not in _PHOTOS:
        raise ConfigError(f"photo: unknown sample photograph {name!r}; choose from {', '.join(_PHOTOS)}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import skimage.data as data

        img = data.stereo_motorcycle()[0] if name == "motorcycle" else getattr(data, name)()
    img = np.asarray(img)
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:  # composite on white
        alpha = img[..., 3:4].astype(np.float32) / 255.0
        img = (img[..., :3].astype(np.float32) * alpha + 255.0 * (1 - alpha)).astype(np.uint8)
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    img.setflags(write=False)
    return img


def value_noise(h: int, w: int, rng: np.random.Generator, cell: int) -> np.ndarray:
    """(h, w) float32 smooth noise in about [0, 1] with features of about ``cell`` texels."""
    import cv2

    cell = max(int(cell), 1)
    gh, gw = h // cell + 3, w // cell + 3
    grid = rng.random((gh, gw), dtype=np.float32)
    if cell == 1:
        return grid[1:h + 1, 1:w + 1]
    big = cv2.resize(grid, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)
    return big[cell:cell + h, cell:cell + w]


def fractal_noise(h: int, w: int, rng: np.random.Generator, largest: int = 256, smallest: int = 2,
                  roughness: float = 0.6) -> np.ndarray:
    """(h, w) float32 multi-octave noise normalised to [0, 1]: structure at every scale from ``largest`` to
    ``smallest`` texels, octave amplitudes falling as ``roughness ** octave``. Built coarse to fine (each
    octave's random grid is added to the upsampled sum of the coarser ones), so it costs about one
    full-size interpolation."""
    import cv2

    cell, amp = max(int(largest), 1), 1.0
    acc = rng.random((-(-h // cell) + 1, -(-w // cell) + 1), dtype=np.float32)
    while cell // 2 >= max(int(smallest), 1):
        cell //= 2
        amp *= roughness
        shape = (-(-h // cell) + 1, -(-w // cell) + 1)
        acc = cv2.resize(acc, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
        acc += np.float32(amp) * rng.random(shape, dtype=np.float32)
    acc = cv2.resize(acc, (acc.shape[1] * cell, acc.shape[0] * cell), interpolation=cv2.INTER_CUBIC)[:h, :w]
    lo, hi = float(acc.min()), float(acc.max())
    return (acc - lo) * np.float32(1.0 / max(hi - lo, 1e-6))


def _colour(rng: np.random.Generator, lo: int = 20, hi: int = 235) -> tuple[int, int, int]:
    return tuple(int(v) for v in rng.integers(lo, hi, 3))


def _mix(c0, c1, f: float) -> tuple[int, int, int]:
    return tuple(int(round(a * (1 - f) + b * f)) for a, b in zip(c0, c1))


def base_surface(h: int, w: int, rng: np.random.Generator, colour, contrast: float = 0.12,
                 grain: float = 0.06, largest: int = 128) -> np.ndarray:
    """(h, w, 3) uint8 BGR painted/plastered surface: ``colour`` modulated by multi-scale noise (relative
    ``contrast``) and a fine grain."""
    import cv2

    f = fractal_noise(h, w, rng, largest=largest, smallest=4, roughness=0.6)
    f *= np.float32(2 * contrast)
    g = value_noise(h, w, rng, 1)
    g *= np.float32(2 * grain)
    f += g
    f += np.float32(1.0 - contrast - grain)  # mean 1
    return cv2.merge([cv2.convertScaleAbs(f, alpha=float(c)) for c in colour])  # rounded, saturated


def _patch_draw(canvas: np.ndarray, box: tuple[int, int, int, int], alpha: float, draw) -> None:
    """Call ``draw(layer, (ox, oy))`` on a copy of the canvas region ``box`` = (x0, y0, x1, y1) and blend it
    back with opacity ``alpha`` (in place; the canvas is uint8 BGR)."""
    import cv2

    h, w = canvas.shape[:2]
    x0, y0, x1, y1 = max(box[0], 0), max(box[1], 0), min(box[2], w), min(box[3], h)
    if x1 <= x0 or y1 <= y0:
        return
    patch = canvas[y0:y1, x0:x1]
    if alpha >= 1.0:
        draw(patch, (x0, y0))
        return
    layer = patch.copy()
    draw(layer, (x0, y0))
    cv2.addWeighted(layer, alpha, patch, 1.0 - alpha, 0.0, dst=patch)


def shapes(canvas: np.ndarray, rng: np.random.Generator, count: int, size: tuple[int, int], palette=None,
           alpha: tuple[float, float] = (0.6, 1.0)) -> None:
    """Draw ``count`` random shapes (rectangles, frames, discs, rings, triangles, strokes, words) of
    ``size`` (min, max texels) into the uint8 canvas, colours from ``palette`` (a function of rng)."""
    import cv2

    h, w = canvas.shape[:2]
    palette = palette or (lambda r: _colour(r, 0, 256))
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX, cv2.FONT_HERSHEY_TRIPLEX)
    for _ in range(int(count)):
        kind = int(rng.integers(0, 7))
        sz = int(rng.integers(size[0], size[1] + 1))
        x, y = int(rng.integers(-sz // 2, w)), int(rng.integers(-sz // 2, h))
        col = palette(rng)
        a = float(rng.uniform(*alpha))
        aspect = float(rng.uniform(0.3, 1.0))
        thick = int(rng.integers(1, max(2, sz // 8)))
        pts = rng.integers(0, sz + 1, (3, 2))
        word = _WORDS[int(rng.integers(0, len(_WORDS)))]
        font = fonts[int(rng.integers(0, len(fonts)))]

        def draw(layer, off, kind=kind, sz=sz, x=x, y=y, col=col, aspect=aspect, thick=thick, pts=pts, word=word,
                 font=font):
            px, py = x - off[0], y - off[1]
            if kind == 0:
                cv2.rectangle(layer, (px, py), (px + sz, py + int(sz * aspect)), col, -1)
            elif kind == 1:
                cv2.rectangle(layer, (px, py), (px + sz, py + int(sz * aspect)), col, thick)
            elif kind == 2:
                cv2.circle(layer, (px + sz // 2, py + sz // 2), sz // 2, col, -1, cv2.LINE_AA)
            elif kind == 3:
                cv2.circle(layer, (px + sz // 2, py + sz // 2), sz // 2, col, thick, cv2.LINE_AA)
            elif kind == 4:
                cv2.fillPoly(layer, [(pts + (px, py)).astype(np.int32)], col, cv2.LINE_AA)
            elif kind == 5:
                cv2.line(layer, (px + int(pts[0, 0]), py + int(pts[0, 1])), (px + int(pts[1, 0]), py + int(pts[1, 1])),
                         col, max(1, thick // 2), cv2.LINE_AA)
            else:
                scale = sz / 50.0
                cv2.putText(layer, word, (px, py + sz // 2), font, scale, col, max(1, int(scale * 2)), cv2.LINE_AA)

        pad = 4 * sz if kind == 6 else sz + 4
        _patch_draw(canvas, (x - 4, y - 4, x + pad, y + sz + 4), a, draw)


def notes(canvas: np.ndarray, rng: np.random.Generator, count: int, size: tuple[int, int]) -> None:
    """Paper notes (white, yellow, pastel) of ``size`` texels with lines of dark text, in place."""
    import cv2

    h, w = canvas.shape[:2]
    papers = ((245, 245, 245), (150, 245, 250), (235, 225, 200), (210, 240, 215), (215, 215, 250))
    inks = ((30, 30, 30), (140, 40, 20), (30, 30, 160), (20, 90, 20))
    for _ in range(int(count)):
        nw = int(rng.integers(size[0], size[1] + 1))
        nh = int(nw * rng.uniform(0.7, 1.4))
        x, y = int(rng.integers(0, max(w - nw, 1))), int(rng.integers(0, max(h - nh, 1)))
        paper = papers[int(rng.integers(0, len(papers)))]
        ink = inks[int(rng.integers(0, len(inks)))]
        canvas[y + 2:y + nh + 2, x + 2:x + nw + 2] = (canvas[y + 2:y + nh + 2, x + 2:x + nw + 2] * 0.6).astype(np.uint8)
        canvas[y:y + nh, x:x + nw] = paper
        line_h = max(int(nw * rng.uniform(0.12, 0.2)), 6)
        scale = line_h / 30.0
        yy = y + line_h + 2
        while yy < y + nh - 3:
            words = " ".join(_WORDS[int(k)] for k in rng.integers(0, len(_WORDS), 3))
            sub = canvas[y:y + nh, x:x + nw]
            cv2.putText(sub, words, (3, yy - y), cv2.FONT_HERSHEY_SIMPLEX, scale, ink, max(1, int(scale * 2.2)),
                        cv2.LINE_AA)
            yy += line_h


def handwriting(canvas: np.ndarray, rng: np.random.Generator, count: int, size: int) -> None:
    """Marker strokes and scribbled words on a whiteboard, in place."""
    import cv2

    h, w = canvas.shape[:2]
    inks = ((160, 60, 20), (30, 30, 30), (40, 40, 190), (40, 130, 30))
    for _ in range(int(count)):
        ink = inks[int(rng.integers(0, len(inks)))]
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            word = " ".join(_WORDS[int(k)] for k in rng.integers(0, len(_WORDS), 2))
            cv2.putText(canvas, word, (x, y), cv2.FONT_HERSHEY_SCRIPT_SIMPLEX, size / 40.0, ink,
                        max(2, size // 14), cv2.LINE_AA)
        else:
            steps = rng.normal(0, size / 3.0, (int(rng.integers(4, 12)), 2)).cumsum(0)
            pts = (steps + (x, y)).astype(np.int32)
            cv2.polylines(canvas, [pts], False, ink, max(2, size // 14), cv2.LINE_AA)


def paste(canvas: np.ndarray, src: np.ndarray, x: int, y: int, w: int, h: int, frame: int = 0,
          frame_colour=(40, 40, 40)) -> None:
    """Paste ``src`` resized to ``w`` x ``h`` texels at (x, y) of the uint8 canvas (in place), with an
    optional frame of ``frame`` texels around it."""
    import cv2

    H, W = canvas.shape[:2]
    if frame > 0:
        canvas[max(y - frame, 0):y + h + frame, max(x - frame, 0):x + w + frame] = frame_colour
    interp = cv2.INTER_AREA if src.shape[1] > w else cv2.INTER_CUBIC
    res = cv2.resize(src, (w, h), interpolation=interp)
    hh, ww = min(h, H - y), min(w, W - x)
    canvas[y:y + hh, x:x + ww] = res[:hh, :ww]


def wood(h: int, w: int, rng: np.random.Generator, plank: int, vertical: bool = False) -> np.ndarray:
    """(h, w, 3) uint8 BGR wooden planks ``plank`` texels wide (along the rows, or the columns when
    ``vertical``), staggered joints, per-plank tint, grain and knots."""
    import cv2

    if vertical:
        return np.ascontiguousarray(wood(w, h, rng, plank).transpose(1, 0, 2))
    img = np.empty((h, w, 3), dtype=np.float32)
    grain = cv2.resize(fractal_noise(h, w // 8 + 2, rng, largest=32, smallest=1, roughness=0.75), (w, h),
                       interpolation=cv2.INTER_LINEAR)
    knots = fractal_noise(h, w, rng, largest=64, smallest=4, roughness=0.6)
    for r0 in range(0, h, plank):
        r1 = min(r0 + plank, h)
        x = -int(rng.integers(0, 6 * plank))
        while x < w:
            length = int(rng.integers(4 * plank, 12 * plank))
            c0, c1 = max(x, 0), min(x + length, w)
            tint = np.array([40, 90, 140], np.float32) * rng.uniform(0.6, 1.3) + rng.uniform(-15, 15, 3)
            g = grain[r0:r1, c0:c1, None] * 0.6 + knots[r0:r1, c0:c1, None] * 0.4
            img[r0:r1, c0:c1] = tint * (0.55 + 0.9 * g)
            img[r0:r1, c0:c0 + 2] *= 0.35  # joint
            x += length
        img[r0:r0 + 2] *= 0.3  # seam between planks
    return cv2.convertScaleAbs(img)  # rounded, saturated (values are >= 0)


def books(h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
    """(h, w, 3) uint8 BGR front of a bookshelf: shelves 0.32 m apart with books of random width, height
    and colour, with bands and short titles on their spines."""
    import cv2

    canvas = wood(h, w, rng, int(0.12 * tpm))
    shelf = int(0.32 * tpm)
    board = max(int(0.025 * tpm), 3)
    for top in range(board, h - board, shelf):
        bottom = min(top + shelf - board, h)
        canvas[bottom:bottom + board] = (35, 60, 90)
        x = int(rng.integers(0, int(0.03 * tpm) + 1))
        while x < w - 4:
            bw = int(rng.uniform(0.02, 0.06) * tpm)
            bh = int((bottom - top) * rng.uniform(0.6, 0.95))
            col = _colour(rng, 20, 220)
            x1 = min(x + bw, w)
            canvas[bottom - bh:bottom, x:x1] = col
            for _ in range(int(rng.integers(0, 3))):
                yb = bottom - int(bh * rng.uniform(0.1, 0.9))
                canvas[yb:yb + max(bw // 6, 2), x:x1] = _mix(col, (230, 220, 190), 0.7)
            label = "".join(chr(int(c)) for c in rng.integers(65, 91, 2))
            cv2.putText(canvas, label, (x + 1, bottom - bh // 2), cv2.FONT_HERSHEY_SIMPLEX, bw / 45.0,
                        _mix(col, (255, 255, 255), 0.8), 1, cv2.LINE_AA)
            canvas[bottom - bh:bottom, x:x + 1] = (20, 20, 20)
            x = x1 + int(rng.integers(0, 3))
            if rng.random() < 0.06:
                x += int(rng.uniform(0.05, 0.15) * tpm)  # a gap
    return canvas


def _bake_lighting(quad: Quad, img: np.ndarray, lights, ambient: float) -> np.ndarray:
    """Texture ``img`` (uint8) of ``quad`` times two-sided Lambertian lighting from point ``lights``
    [(position, power)] plus ``ambient``; returns uint8."""
    import cv2

    g = 33
    a, b = np.meshgrid((np.arange(g) + 0.5) / g, (np.arange(g) + 0.5) / g)
    pts = quad.point(a, b)
    n = quad.normal
    shade = np.full((g, g), ambient, dtype=np.float64)
    for pos, power in lights:
        d = pos - pts
        r = np.linalg.norm(d, axis=-1)
        cos = np.abs(d @ n) / r
        shade += power * cos / (1.0 + (r / 2.5) ** 2)
    h, w = img.shape[:2]
    shade = cv2.resize(np.clip(shade, 0.3, 1.3).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    return cv2.multiply(img, cv2.merge([shade, shade, shade]), dtype=cv2.CV_8U)  # rounded, saturated


# ----------------------------------------------------------------------------------------------------------
# the default room


#: Room extent (metres): x in [-ROOM_X, ROOM_X], y in [-ROOM_Y, ROOM_Y], z in [0, ROOM_Z] (floor at z = 0).
ROOM_X, ROOM_Y, ROOM_Z = 3.0, 2.25, 2.8

#: Boxes standing in the room: name -> (centre x, centre y, size x, size y, height), metres.
BOXES = {
    "crate": (0.6, 1.25, 1.0, 0.7, 0.75),
    "cabinet": (-2.3, 1.5, 0.9, 0.6, 1.9),
    "cube": (-0.3, 0.2, 0.5, 0.5, 0.5),
    "board": (-1.3, 1.35, 1.0, 0.05, 1.55),
    "locker": (2.45, -0.9, 0.6, 0.9, 1.0),
    "shelf": (2.5, 1.45, 0.5, 0.8, 1.3),
}

#: Wall paint colours (BGR).
WALL_COLOURS = {"wall_front": (165, 198, 218), "wall_right": (222, 204, 182), "wall_back": (182, 214, 192),
                "wall_left": (196, 192, 222)}

#: Posters: wall -> [(photo, left, top, width) in metres from the wall's top-left corner seen from inside].
POSTERS = {
    "wall_front": [("astronaut", 0.35, 0.45, 0.95), ("rocket", 1.6, 0.35, 1.25), ("text", 3.2, 0.55, 1.1),
                   ("hubble_deep_field", 2.1, 1.45, 0.8), ("page", 4.6, 0.45, 1.0)],
    "wall_right": [("retina", 0.35, 0.4, 0.9), ("immunohistochemistry", 1.6, 0.5, 0.8),
                   ("moon", 2.7, 0.45, 0.75), ("clock", 3.2, 1.45, 0.8)],
    "wall_back": [("cell", 0.6, 0.4, 0.7), ("logo", 2.0, 0.5, 0.75), ("coins", 3.3, 0.6, 0.9)],
    "wall_left": [("motorcycle", 0.4, 0.4, 1.1), ("camera", 1.9, 0.45, 0.8), ("brick", 3.0, 0.5, 0.8)],
}

#: Photographs on box faces: quad name -> photo (each photograph appears once in the room).
BOX_PHOTOS = {"board_front": "coffee", "crate_front": "chelsea", "cabinet_front": "gravel"}

LIGHTS = [(np.array([-1.5, 0.0, 2.65]), 0.55), (np.array([1.5, 0.0, 2.65]), 0.55),
          (np.array([0.0, -1.5, 2.0]), 0.2)]
AMBIENT = 0.5


def box_quads(name: str, cx: float, cy: float, sx: float, sy: float, height: float, z0: float = 0.0
              ) -> list[Quad]:
    """The five visible faces (four sides seen upright from outside, and the top) of a box on the floor."""
    x0, x1, y0, y1, z1 = cx - sx / 2, cx + sx / 2, cy - sy / 2, cy + sy / 2, z0 + height
    down = (0.0, 0.0, -height)
    return [
        Quad(f"{name}_front", (x0, y0, z1), (sx, 0, 0), down),   # faces -y
        Quad(f"{name}_right", (x1, y0, z1), (0, sy, 0), down),   # faces +x
        Quad(f"{name}_back", (x1, y1, z1), (-sx, 0, 0), down),   # faces +y
        Quad(f"{name}_left", (x0, y1, z1), (0, -sy, 0), down),   # faces -x
        Quad(f"{name}_top", (x0, y1, z1), (sx, 0, 0), (0, -sy, 0)),
    ]


def room_quads() -> list[Quad]:
    """Untextured geometry of the default room: walls, floor, ceiling and the boxes of :data:`BOXES`."""
    X, Y, Z = ROOM_X, ROOM_Y, ROOM_Z
    quads = [
        Quad("wall_front", (-X, Y, Z), (2 * X, 0, 0), (0, 0, -Z)),
        Quad("wall_right", (X, Y, Z), (0, -2 * Y, 0), (0, 0, -Z)),
        Quad("wall_back", (X, -Y, Z), (-2 * X, 0, 0), (0, 0, -Z)),
        Quad("wall_left", (-X, -Y, Z), (0, 2 * Y, 0), (0, 0, -Z)),
        Quad("floor", (-X, Y, 0), (2 * X, 0, 0), (0, -2 * Y, 0)),
        Quad("ceiling", (-X, -Y, Z), (2 * X, 0, 0), (0, 2 * Y, 0)),
    ]
    for name, (cx, cy, sx, sy, h) in BOXES.items():
        quads += box_quads(name, cx, cy, sx, sy, h)
    return quads


def _muted(base):
    return lambda rng: _mix(_colour(rng, 0, 256), base, 0.3)


def _wall(name: str, h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
    colour = WALL_COLOURS[name]
    img = base_surface(h, w, rng, colour, contrast=0.08, grain=0.04)
    area = h * w / tpm**2
    shapes(img, rng, 14 * area, (int(0.04 * tpm), int(0.3 * tpm)), _muted(colour), alpha=(0.7, 1.0))
    notes(img, rng, 3 * area, (int(0.1 * tpm), int(0.22 * tpm)))
    shapes(img, rng, 12 * area, (int(0.02 * tpm), int(0.08 * tpm)), _muted((60, 60, 60)), alpha=(0.8, 1.0))
    skirting, rail = int(0.1 * tpm), int(0.32 * tpm)
    img[h - skirting:] = (np.float32(0.35) * img[h - skirting:] + 40).astype(np.uint8)
    img[h - skirting:h - skirting + 3] = 30
    img[rail:rail + 6] = (img[rail:rail + 6] * 0.5).astype(np.uint8)
    for photo_name, left, top, width in POSTERS.get(name, []):
        ph = photo(photo_name)
        pw = int(width * tpm)
        paste(img, ph, int(left * tpm), int(top * tpm), pw, int(pw * ph.shape[0] / ph.shape[1]),
              frame=int(0.03 * tpm), frame_colour=_colour(rng, 10, 90))
    return img


def _floor(h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
    import cv2

    img = wood(h, w, rng, plank=int(0.18 * tpm))
    rug_h, rug_w = int(1.3 * tpm), int(1.9 * tpm)
    rug = base_surface(rug_h, rug_w, rng, (60, 50, 140), contrast=0.25, grain=0.1, largest=32)
    shapes(rug, rng, 500, (int(0.03 * tpm), int(0.15 * tpm)), lambda r: _colour(r, 20, 240), alpha=(0.8, 1.0))
    grass = cv2.resize(photo("grass"), (rug_w // 2, rug_h // 2), interpolation=cv2.INTER_AREA)
    rug[rug_h // 4:rug_h // 4 + rug_h // 2, rug_w // 4:rug_w // 4 + rug_w // 2] = grass
    paste(img, rug, int(2.0 * tpm), int(2.4 * tpm), rug_w, rug_h, frame=int(0.06 * tpm), frame_colour=(30, 30, 120))
    mat = base_surface(int(0.6 * tpm), int(0.9 * tpm), rng, (70, 110, 60), contrast=0.3, grain=0.2, largest=16)
    shapes(mat, rng, 60, (int(0.02 * tpm), int(0.08 * tpm)), lambda r: _colour(r, 20, 240))
    paste(img, mat, int(4.3 * tpm), int(0.5 * tpm), mat.shape[1], mat.shape[0], frame=int(0.02 * tpm))
    notes(img, rng, 6, (int(0.15 * tpm), int(0.3 * tpm)))  # papers on the floor
    return img


def _ceiling(h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
    import cv2

    img = base_surface(h, w, rng, (228, 232, 235), contrast=0.06, grain=0.05)
    tile = int(0.6 * tpm)  # suspended-ceiling grid, jittered so that it does not repeat exactly
    for k in range(1, w // tile + 1):
        x = k * tile + int(rng.integers(-3, 4))
        img[:, x:x + 3] = 150
    for k in range(1, h // tile + 1):
        y = k * tile + int(rng.integers(-3, 4))
        img[y:y + 3] = 150
    for lx in (-1.5, 1.5):
        x0, y0 = int((lx + ROOM_X - 0.4) * tpm), int((ROOM_Y - 0.25) * tpm)
        img[y0:y0 + int(0.5 * tpm), x0:x0 + int(0.8 * tpm)] = 252
    for _ in range(12):  # sprinklers, detectors, stains
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        cv2.circle(img, (x, y), int(rng.uniform(0.02, 0.08) * tpm), _colour(rng, 60, 200), -1, cv2.LINE_AA)
    shapes(img, rng, 40, (int(0.05 * tpm), int(0.3 * tpm)), _muted((200, 200, 200)), alpha=(0.3, 0.6))
    return img


def _box_face(name: str, h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
    box, side = name.rsplit("_", 1)
    area = h * w / tpm**2
    if box == "crate":
        img = wood(h, w, rng, int(0.12 * tpm), vertical=side != "top")
        notes(img, rng, max(1, 5 * area), (int(0.08 * tpm), int(0.16 * tpm)))
        shapes(img, rng, 30 * area, (int(0.04 * tpm), int(0.12 * tpm)), lambda r: _colour(r, 10, 80), (0.7, 0.9))
    elif box == "cabinet":
        img = base_surface(h, w, rng, (150, 140, 90), contrast=0.1, grain=0.08)
        notes(img, rng, max(2, 8 * area), (int(0.08 * tpm), int(0.18 * tpm)))
        shapes(img, rng, 60 * area, (int(0.03 * tpm), int(0.12 * tpm)), lambda r: _colour(r, 0, 256))
    elif box == "cube":
        img = base_surface(h, w, rng, _colour(rng, 80, 220), contrast=0.2, grain=0.1)
        shapes(img, rng, 250 * area, (int(0.02 * tpm), int(0.1 * tpm)), lambda r: _colour(r, 0, 256), (0.8, 1.0))
    elif box == "board" and side in ("front", "back"):
        img = base_surface(h, w, rng, (242, 244, 244), contrast=0.03, grain=0.03)
        handwriting(img, rng, 45 * area, int(0.05 * tpm))
        notes(img, rng, 6 * area, (int(0.08 * tpm), int(0.14 * tpm)))
    elif box == "locker":
        img = base_surface(h, w, rng, (140, 120, 105), contrast=0.12, grain=0.1)
        for _ in range(int(rng.integers(2, 4))):  # vent groups of different sizes
            vx, vy = int(rng.uniform(0.05, 0.6) * w), int(rng.uniform(0.05, 0.7) * h)
            slot = int(rng.uniform(0.008, 0.02) * tpm) + 2
            for k in range(int(rng.integers(4, 9))):
                y = vy + k * 3 * slot
                img[y:y + slot, vx:vx + int(rng.uniform(0.1, 0.25) * tpm)] = 40
        notes(img, rng, max(1, 6 * area), (int(0.06 * tpm), int(0.14 * tpm)))
        shapes(img, rng, 50 * area, (int(0.02 * tpm), int(0.1 * tpm)), lambda r: _colour(r, 0, 256))
    elif box == "shelf" and side == "left":
        img = books(h, w, rng, tpm)
    else:
        img = base_surface(h, w, rng, _colour(rng, 60, 200), contrast=0.15, grain=0.08)
        shapes(img, rng, 80 * area, (int(0.02 * tpm), int(0.12 * tpm)), lambda r: _colour(r, 0, 256))
        notes(img, rng, max(1, 4 * area), (int(0.06 * tpm), int(0.12 * tpm)))
    if name in BOX_PHOTOS:
        ph = photo(BOX_PHOTOS[name])
        pw = int(w * 0.55)
        ph_h = min(int(pw * ph.shape[0] / ph.shape[1]), int(h * 0.5))
        paste(img, ph, int(w * 0.22), int(h * 0.12), pw, ph_h, frame=max(int(0.02 * tpm), 2))
    return img


def _texture_for(quad: Quad, rng: np.random.Generator, tpm: float) -> np.ndarray:
    """Synthesize the uint8 BGR texture of one quad of the default room (about ``tpm`` texels per metre on
    walls, floor and ceiling, 1.5 times that on the boxes, which are seen from closer)."""
    name = quad.name
    if not (name.startswith("wall") or name in ("floor", "ceiling")):
        tpm = 1.5 * tpm
    w = max(int(round(np.linalg.norm(quad.edge_u) * tpm)), 16)
    h = max(int(round(np.linalg.norm(quad.edge_v) * tpm)), 16)
    if name.startswith("wall"):
        return _wall(name, h, w, rng, tpm)
    if name == "floor":
        return _floor(h, w, rng, tpm)
    if name == "ceiling":
        return _ceiling(h, w, rng, tpm)
    return _box_face(name, h, w, rng, tpm)


@functools.lru_cache(maxsize=4)
def default_room(seed: int = 0, texels_per_metre: float = 320.0) -> Scene:
    """The textured room of the synthetic sequences (built once per process and cached; treat as read-only).

    A 6 x 4.5 x 2.8 m room (:data:`ROOM_X` ...): painted walls with framed photographs, paper notes and
    drawings, a wooden floor with rugs, a tiled ceiling with light panels, and six pieces of furniture for
    depth variation and occlusion (:data:`BOXES`: a crate, a cabinet, a toy cube, a whiteboard, a locker and
    a bookshelf). Textures are synthesized from ``seed`` at about ``texels_per_metre``; lighting
    (:data:`LIGHTS`) is baked into them.
    """
    quads = room_quads()
    root = np.random.SeedSequence(int(seed))
    for quad, child in zip(quads, root.spawn(len(quads))):
        img = _texture_for(quad, np.random.default_rng(child), texels_per_metre)
        quad.texture = Texture(_bake_lighting(quad, img, LIGHTS, AMBIENT))
    bounds = np.array([[-ROOM_X, -ROOM_Y, 0.0], [ROOM_X, ROOM_Y, ROOM_Z]])
    return Scene(quads, name=f"room(seed={seed})", bounds=bounds)
