"""A textured planar 3D scene, and the default room of the synthetic sequences.

The scene is a set of textured rectangles (:class:`Quad`, :mod:`slamkit.sources.surfaces`) rendered
*exactly* for a pinhole camera by :mod:`slamkit.sources.render`: a 3D point on a quad projects with the pose
and intrinsics exactly where its texel appears. The default room's textures are painted procedurally
(:mod:`slamkit.sources.textures`).

Conventions: world frame with z up, metres; poses are (4, 4) camera-to-world with OpenCV camera axes (x right,
y down, z forward); pixel centres are at integer coordinates (as :class:`~slamkit.camera.Intrinsics`).
Texel ``(i, j)`` (column, row) of a quad's texture of size W x H covers the quad fractions
``[i/W, (i+1)/W] x [j/H, (j+1)/H]`` along ``edge_u`` and ``edge_v``.

Lighting is Lambertian with fixed point lights and baked into the textures when the scene is built, so the
appearance of a surface point does not depend on the viewpoint (a brightness-constancy world).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import Intrinsics
from .render import NEAR, Rendering, look_at, project, raycast, render
from .surfaces import Quad, Texture
from .textures import (base_surface, books, handwriting, mix_colours, notes, paste, photo, random_colour, shapes,
                       wood)

__all__ = ["NEAR", "Quad", "Rendering", "Scene", "Texture", "default_room", "look_at", "project", "room_quads",
           "box_quads", "ROOM_X", "ROOM_Y", "ROOM_Z", "BOXES", "WALL_COLOURS", "POSTERS", "BOX_PHOTOS", "LIGHTS",
           "AMBIENT"]


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

    def render(self, pose: np.ndarray, intrinsics: Intrinsics, *, texture: bool = True) -> Rendering:
        """Render the scene seen by a camera with camera-to-world ``pose`` (4, 4) and pinhole ``intrinsics``
        (distortion is not modelled and must be zero). With ``texture=False`` only depth and quad ids.
        See :func:`slamkit.sources.render.render`."""
        return render(self.quads, pose, intrinsics, background=self.background, lod_bias=self.lod_bias,
                      texture=texture)

    def depth(self, pose: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """(H, W) float64 exact z-depth (metres) of every pixel centre; inf where no quad is hit."""
        return self.render(pose, intrinsics, texture=False).depth

    def raycast(self, pose: np.ndarray, intrinsics: Intrinsics, pixels: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast rays through (N, 2) float pixel coordinates (any sub-pixel position, pinhole).

        Returns ((N, 3) world points of the first hit, (N,) z-depth in metres, (N,) quad index); points are
        NaN, depth inf and index -1 for rays that hit nothing.
        """
        return raycast(self.quads, pose, intrinsics, pixels)

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


# ----------------------------------------------------------------------------------------------------------
# the default room


def _bake_lighting(quad: Quad, img: np.ndarray, lights, ambient: float) -> np.ndarray:
    """Texture ``img`` (uint8) of ``quad`` times two-sided Lambertian lighting from point ``lights``
    [(position, power)] plus ``ambient``; returns uint8."""
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
    return lambda rng: mix_colours(random_colour(rng, 0, 256), base, 0.3)


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
              frame=int(0.03 * tpm), frame_colour=random_colour(rng, 10, 90))
    return img


def _floor(h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
    img = wood(h, w, rng, plank=int(0.18 * tpm))
    rug_h, rug_w = int(1.3 * tpm), int(1.9 * tpm)
    rug = base_surface(rug_h, rug_w, rng, (60, 50, 140), contrast=0.25, grain=0.1, largest=32)
    shapes(rug, rng, 500, (int(0.03 * tpm), int(0.15 * tpm)), lambda r: random_colour(r, 20, 240), alpha=(0.8, 1.0))
    grass = cv2.resize(photo("grass"), (rug_w // 2, rug_h // 2), interpolation=cv2.INTER_AREA)
    rug[rug_h // 4:rug_h // 4 + rug_h // 2, rug_w // 4:rug_w // 4 + rug_w // 2] = grass
    paste(img, rug, int(2.0 * tpm), int(2.4 * tpm), rug_w, rug_h, frame=int(0.06 * tpm), frame_colour=(30, 30, 120))
    mat = base_surface(int(0.6 * tpm), int(0.9 * tpm), rng, (70, 110, 60), contrast=0.3, grain=0.2, largest=16)
    shapes(mat, rng, 60, (int(0.02 * tpm), int(0.08 * tpm)), lambda r: random_colour(r, 20, 240))
    paste(img, mat, int(4.3 * tpm), int(0.5 * tpm), mat.shape[1], mat.shape[0], frame=int(0.02 * tpm))
    notes(img, rng, 6, (int(0.15 * tpm), int(0.3 * tpm)))  # papers on the floor
    return img


def _ceiling(h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
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
        cv2.circle(img, (x, y), int(rng.uniform(0.02, 0.08) * tpm), random_colour(rng, 60, 200), -1, cv2.LINE_AA)
    shapes(img, rng, 40, (int(0.05 * tpm), int(0.3 * tpm)), _muted((200, 200, 200)), alpha=(0.3, 0.6))
    return img


def _box_face(name: str, h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
    box, side = name.rsplit("_", 1)
    area = h * w / tpm**2
    if box == "crate":
        img = wood(h, w, rng, int(0.12 * tpm), vertical=side != "top")
        notes(img, rng, max(1, 5 * area), (int(0.08 * tpm), int(0.16 * tpm)))
        shapes(img, rng, 30 * area, (int(0.04 * tpm), int(0.12 * tpm)), lambda r: random_colour(r, 10, 80), (0.7, 0.9))
    elif box == "cabinet":
        img = base_surface(h, w, rng, (150, 140, 90), contrast=0.1, grain=0.08)
        notes(img, rng, max(2, 8 * area), (int(0.08 * tpm), int(0.18 * tpm)))
        shapes(img, rng, 60 * area, (int(0.03 * tpm), int(0.12 * tpm)), lambda r: random_colour(r, 0, 256))
    elif box == "cube":
        img = base_surface(h, w, rng, random_colour(rng, 80, 220), contrast=0.2, grain=0.1)
        shapes(img, rng, 250 * area, (int(0.02 * tpm), int(0.1 * tpm)), lambda r: random_colour(r, 0, 256), (0.8, 1.0))
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
        shapes(img, rng, 50 * area, (int(0.02 * tpm), int(0.1 * tpm)), lambda r: random_colour(r, 0, 256))
    elif box == "shelf" and side == "left":
        img = books(h, w, rng, tpm)
    else:
        img = base_surface(h, w, rng, random_colour(rng, 60, 200), contrast=0.15, grain=0.08)
        shapes(img, rng, 80 * area, (int(0.02 * tpm), int(0.12 * tpm)), lambda r: random_colour(r, 0, 256))
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
