"""Textured planar surfaces of a scene: a mipmapped :class:`Texture`, the :class:`Quad` that carries it,
and trilinear sampling of the texture (what the renderer of :mod:`slamkit.sources.render` draws).

Texel ``(i, j)`` (column, row) of a quad's texture of size W x H covers the quad fractions
``[i/W, (i+1)/W] x [j/H, (j+1)/H]`` along ``edge_u`` and ``edge_v``; texel centres are at integer texel
coordinates, as pixel centres are at integer pixel coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError


class Texture:
    """A BGR uint8 texture and its mipmap pyramid: ``levels[k]`` (BGRA, alpha 255: four bytes a texel sample
    fast) is level 0 reduced about ``2**k`` times, ``scales[k]`` the exact (x, y) size ratio of level k to 0.

    Levels are made by a Gaussian blur and a 2x2 area average, which keeps the pixel-centre convention
    (texel j of level k+1 is centred on texels 2j, 2j+1 of level k), so sampling a level never shifts the
    texture (``cv2.pyrDown`` would shift it by half a texel).
    """

    def __init__(self, image: np.ndarray):
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

    def camera_plane(self, Rt: np.ndarray, C: np.ndarray):
        """The quad in the frame of a camera at ``C`` (world -> camera rotation ``Rt``): (n, d, Ua, ao, Vb, bo)
        with plane ``n . X = d`` and quad fractions ``a = Ua . X - ao``, ``b = Vb . X - bo`` of a camera
        point X; None when the camera lies in the plane."""
        n = Rt @ self._normal
        o = Rt @ (self.origin - C)
        d = float(n @ o)
        if abs(d) < 1e-12:
            return None
        Ua = Rt @ self._u_dual
        Vb = Rt @ self._v_dual
        return n, d, Ua, float(Ua @ o), Vb, float(Vb @ o)



def sample_trilinear(tex: Texture, s: np.ndarray, t: np.ndarray, lod: np.ndarray) -> np.ndarray:
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
        c = _sample(tex, level, ss, tt)
        if level + 1 < nlev and f.max() > 1e-3:
            c1 = _sample(tex, level + 1, ss, tt)
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


def _sample(tex: Texture, level: int, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(rows, 1024, 4) uint8 bilinear samples of mipmap ``level`` of ``tex`` at level-0 texel coordinates
    (s, t) (N of them, zero-padded to whole rows)."""
    sx, sy = tex.scales[level]
    rows = -(-len(s) // _ROW)
    mx = _pad_rows(s, rows, sx, 0.5 * sx - 0.5)
    my = _pad_rows(t, rows, sy, 0.5 * sy - 0.5)
    return cv2.remap(tex.levels[level], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)
