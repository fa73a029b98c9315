"""The exact renderer of textured quads: z-buffer rasterisation, texturing, and ray casting.

An image is rendered *exactly* for a pinhole camera: every pixel centre casts a ray, the ray's depth on
each quad's plane is ``z = d / (n . r)`` (``r`` the ray with unit z in camera coordinates, ``n . X = d`` the
plane), the nearest quad in front of the near plane wins (a z-buffer), and its texture is sampled at the
exact texture coordinate of the hit point (bilinear, trilinear between mipmap levels when the texture is
minified). So a 3D point on a quad projects with the pose and intrinsics exactly where its texel appears,
up to the 1/32 texel resolution of OpenCV's remap.

Conventions: world frame with z up, metres; poses are (4, 4) camera-to-world with OpenCV camera axes (x right,
y down, z forward); pixel centres are at integer coordinates (as :class:`~slamkit.camera.Intrinsics`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from ..camera import Intrinsics
from ..errors import ConfigError
from .surfaces import Quad, sample_trilinear

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
# clipping


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


# ----------------------------------------------------------------------------------------------------------
# rendering


@dataclass(frozen=True, eq=False)
class Rendering:
    """What :meth:`Scene.render` produced. ``image`` (H, W, 3) uint8 BGR; ``depth`` (H, W) float64 z-depth in
    metres of each pixel centre (inf where no quad is hit); ``quad`` (H, W) int16 index of the visible quad
    in ``Scene.quads`` (-1 where none)."""

    image: np.ndarray | None
    depth: np.ndarray
    quad: np.ndarray


def render(quads: Sequence[Quad], pose: np.ndarray, intrinsics: Intrinsics, *,
           background: tuple[int, int, int] = (0, 0, 0), lod_bias: float = 0.0, texture: bool = True) -> Rendering:
    """Render ``quads`` seen by a camera with camera-to-world ``pose`` (4, 4) and pinhole ``intrinsics``
    (distortion is not modelled and must be zero). With ``texture=False`` only depth and quad ids.

    Two passes. The z-buffer pass rasterises each quad's near-clipped, projected polygon: pixels more
    than a pixel inside it are inside the quad, pixels near its outline get the exact analytic test
    (quad fractions in [0, 1)); depths are analytic everywhere. The texturing pass then samples each
    quad's texture at the exact texture coordinates of the pixels it won (pixels that see no quad get the
    BGR ``background``; ``lod_bias`` is added to the mipmap level).
    """
    if intrinsics.has_distortion:
        raise ConfigError("Scene.render: the renderer is pinhole only; intrinsics.dist must be zero")
    W, H = intrinsics.width, intrinsics.height
    pose = np.asarray(pose, dtype=np.float64)
    Rt = pose[:3, :3].T  # world -> camera rotation
    C = pose[:3, 3]
    rx_all = (np.arange(W) - intrinsics.cx) / intrinsics.fx
    ry_all = (np.arange(H) - intrinsics.cy) / intrinsics.fy
    zbuf = np.full((H, W), np.inf)
    qbuf = np.full((H, W), -1, dtype=np.int16)
    planes, boxes = [], {}
    for qi, quad in enumerate(quads):
        plane = quad.camera_plane(Rt, C)
        planes.append(plane)
        if plane is None:
            continue
        box = _rasterise(qi, quad, plane, Rt, C, intrinsics, rx_all, ry_all, zbuf, qbuf)
        if box is not None:
            boxes[qi] = box
    image = None
    if texture:
        image = _texture_pass(quads, intrinsics, zbuf, qbuf, planes, boxes, background, lod_bias)
    return Rendering(image=image, depth=zbuf, quad=qbuf)


def _rasterise(qi: int, quad: Quad, plane, Rt: np.ndarray, C: np.ndarray, intrinsics: Intrinsics,
               rx_all: np.ndarray, ry_all: np.ndarray, zbuf: np.ndarray, qbuf: np.ndarray):
    """The z-buffer pass of quad ``qi``: write its depth and id into ``zbuf`` and ``qbuf`` (H, W) where it
    is the nearest so far; returns the bounding box (x0, y0, x1, y1) of its projection, or None when it
    is not in view."""
    W, H = intrinsics.width, intrinsics.height
    fx, fy = intrinsics.fx, intrinsics.fy
    poly = _clip_near((quad.corners - C) @ Rt.T, NEAR)
    if len(poly) < 3:
        return None
    uv = np.stack([fx * poly[:, 0] / poly[:, 2] + intrinsics.cx,
                   fy * poly[:, 1] / poly[:, 2] + intrinsics.cy], axis=1)
    uv = _clip_rect(uv, -2.0, -2.0, W + 1.0, H + 1.0)
    if len(uv) < 3:
        return None
    x0, y0 = max(int(math.floor(uv[:, 0].min())) - 2, 0), max(int(math.floor(uv[:, 1].min())) - 2, 0)
    x1, y1 = min(int(math.ceil(uv[:, 0].max())) + 2, W - 1), min(int(math.ceil(uv[:, 1].max())) + 2, H - 1)
    if x0 > x1 or y0 > y1:
        return None
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
    return x0, y0, x1, y1


def _texture_pass(quads: Sequence[Quad], intrinsics: Intrinsics, zbuf: np.ndarray, qbuf: np.ndarray,
                  planes: list, boxes: dict, background: tuple[int, int, int], lod_bias: float) -> np.ndarray:
    """The texturing pass: (H, W, 3) uint8 image from the z-buffer, the quad ids, each quad's camera
    plane and the bounding box (x0, y0, x1, y1) of its projection."""
    W, H = intrinsics.width, intrinsics.height
    f32 = np.float32
    # BGRA pixels as one uint32 each: scattering 4-byte items is far faster than 3-byte rows
    out = np.empty((H * W, 4), dtype=np.uint8)
    out[:] = np.asarray((*background, 255), dtype=np.uint8)
    out = out.view(np.uint32).reshape(H * W)
    q = qbuf.ravel()
    order = np.argsort(q, kind="stable")
    ends = np.cumsum(np.bincount(q.astype(np.int64) + 1, minlength=len(quads) + 1))
    rx_all, ry_all = _pixel_rays(intrinsics)
    z_all = zbuf.ravel().astype(f32)
    lod_img = np.zeros((H, W), dtype=f32)
    for qi, quad in enumerate(quads):
        if ends[qi + 1] > ends[qi] and quad.texture is not None:
            _mip_levels(intrinsics, quad, planes[qi], boxes[qi], qbuf, qi, lod_img, lod_bias)
    lod_all = lod_img.ravel()
    for qi, quad in enumerate(quads):
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
        out[flat] = sample_trilinear(quad.texture, s, t, lod_all[flat])
    return cv2.cvtColor(out.view(np.uint8).reshape(H, W, 4), cv2.COLOR_BGRA2BGR)


def _mip_levels(intrinsics: Intrinsics, quad: Quad, plane, box, qbuf: np.ndarray, qi: int,
                lod_img: np.ndarray, lod_bias: float) -> None:
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
        lod = 0.5 * np.log2(foot2) + lod_bias
    lod = np.where((z > 0) & np.isfinite(lod), lod, nlev - 1)  # grid points beyond the plane's horizon
    lod = np.clip(lod, 0.0, nlev - 1).astype(np.float32)
    if nx > 1 or ny > 1:
        lod = cv2.resize(lod, (8 * nx, 8 * ny), interpolation=cv2.INTER_LINEAR)
    else:
        lod = np.broadcast_to(lod, (8, 8))
    sub = lod_img[y0:y1 + 1, x0:x1 + 1]
    np.copyto(sub, lod[:bh, :bw], where=qbuf[y0:y1 + 1, x0:x1 + 1] == qi)


# ----------------------------------------------------------------------------------------------------------
# ray casting


def raycast(quads: Sequence[Quad], pose: np.ndarray, intrinsics: Intrinsics, pixels: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast rays through (N, 2) float pixel coordinates (any sub-pixel position, pinhole) at ``quads``.

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
    for qi, quad in enumerate(quads):
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


def undistort_radial_exact(camera: Intrinsics, xy: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of a camera with radial distortion ``k1, k2, k3`` -> (N, 2) pixels of its pinhole part,
    exact to rounding (the fixed point of ``x = x_d / (1 + k1 r^2 + k2 r^4 + k3 r^6)``; OpenCV's
    ``undistortPoints`` stops after 5 steps, 1e-3 px off in the corners at k1 = -0.1). Tangential
    coefficients are ignored."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    xd, yd = (xy[:, 0] - camera.cx) / camera.fx, (xy[:, 1] - camera.cy) / camera.fy
    x, y = xd.copy(), yd.copy()
    k1, k2, k3 = camera.dist[0], camera.dist[1], camera.dist[4]
    for _ in range(200):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = xd / radial, yd / radial
    return np.column_stack([camera.fx * x + camera.cx, camera.fy * y + camera.cy])


def distortion_maps(camera: Intrinsics) -> tuple[Intrinsics, np.ndarray, np.ndarray]:
    """(pinhole canvas, map_x, map_y) to render a radially distorted ``camera``: the canvas is the pinhole
    part of the camera grown to cover every pixel's undistorted place (barrel distortion sees wider), and
    ``cv2.remap(render, map_x, map_y)`` samples it at those places."""
    w, h = camera.width, camera.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    und = undistort_radial_exact(camera, np.column_stack([u.ravel(), v.ravel()]))
    x0, y0 = np.floor(und.min(axis=0)) - 2
    x1, y1 = np.ceil(und.max(axis=0)) + 2
    x0, y0 = min(x0, 0.0), min(y0, 0.0)
    canvas = Intrinsics(int(max(x1 + 1, w) - x0), int(max(y1 + 1, h) - y0), camera.fx, camera.fy,
                        camera.cx - x0, camera.cy - y0)
    map_x = (und[:, 0] - x0).reshape(h, w).astype(np.float32)
    map_y = (und[:, 1] - y0).reshape(h, w).astype(np.float32)
    return canvas, map_x, map_y
