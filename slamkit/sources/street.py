"""A street scene for driving sequences, and the ``street-drive`` camera path.

A straight street along +y, 16 m between the building lines (issue 17: forward motion at about 1 m per
frame, as KITTI at frame skip 2, with exact ground truth). What a feature detector sees there: town-house
facades of varied height, set-back, colour and material (plaster or brick), windows with their own glass,
curtains and mullions, shop fronts with doors, signs and posters (:func:`~slamkit.sources.textures.facade`);
an asphalt road with lane marks and repairs; paved sidewalks; parked cars; street lamps and traffic signs;
a building closing the far end. Everything is drawn from one seed, so every building differs and features
are distinctive; the sky is the uniform ``background``.

Geometry (world frame: z up, metres, ground at z = 0): the road spans x in [-:data:`ROAD_HALF`,
:data:`ROAD_HALF`], sidewalks reach the building line at |x| = :data:`BUILDING_LINE` (facades stand 0 to
1.5 m behind it), the street runs from y = :data:`STREET_START` to :data:`STREET_END`. Texel density is
about ``texels_per_metre`` on facades and road (40: a texel of 2.5 cm, 2.5 px at 5 m with the 500 px focal
length of the synthetic camera, a fifth of a pixel at 60 m where the renderer's mipmaps take over), 1.5 to
2 times that on cars and signs, which are seen from closer. A fixed sun is baked into the textures as one
shading factor per facing direction (a brightness-constancy world, as the room).
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from ..errors import ConfigError
from .motions import _check_frames, _check_range
from .render import look_at
from .scene import Scene, box_quads
from .surfaces import Quad, Texture
from .textures import asphalt, base_surface, facade, mix_colours, paving, random_colour, shapes, value_noise

STREET_START, STREET_END = -40.0, 420.0
"""Extent of the street along y (metres); a building closes it at ``STREET_END``."""
ROAD_HALF = 5.0
"""Half width of the road (metres): two 3 m lanes and a 2 m parking lane on each side."""
BUILDING_LINE = 8.0
"""|x| of the building line (metres): 16 m between the building lines, 3 m of sidewalk a side."""
LANE_X = -1.6
"""x of the centre of the driving lane of :func:`street_drive` (metres)."""
SKY = (222, 196, 165)
"""BGR colour of the sky (pixels that see no surface)."""
SUN = {"+x": 1.0, "-x": 0.82, "-y": 0.72, "+y": 0.9, "+z": 0.95}
"""Shading factor baked into a surface by the direction it faces (a fixed sun)."""


def _shade(img: np.ndarray, facing: str) -> Texture:
    return Texture(cv2.convertScaleAbs(img, alpha=SUN[facing]))


def _size(metres_u: float, metres_v: float, tpm: float) -> tuple[int, int]:
    """(width, height) in texels of a surface, at least 16 so that it has mipmaps."""
    return max(int(round(metres_u * tpm)), 16), max(int(round(metres_v * tpm)), 16)


def _buildings(side: int, rng: np.random.Generator, tpm: float) -> list[Quad]:
    """Facades and side walls of the houses along one side (``side`` -1: x < 0, +1: x > 0)."""
    quads = []
    y = STREET_START
    k = 0
    while y < STREET_END:
        width = float(rng.uniform(8.0, 24.0))
        if rng.random() < 0.12:  # an alley: a gap between two houses
            y += float(rng.uniform(3.0, 6.0))
        y1 = min(y + width, STREET_END)
        height = float(rng.uniform(7.0, 22.0))
        x = side * (BUILDING_LINE + float(rng.uniform(0.0, 1.5)))
        depth = 12.0
        w, h = _size(y1 - y, height, tpm)
        img = facade(h, w, rng, tpm, storey=float(rng.uniform(2.9, 3.6)), spacing=float(rng.uniform(2.2, 3.6)))
        name = f"house_{'left' if side < 0 else 'right'}_{k:02d}"
        # seen from the street, the texture reads left to right: +y on the left side, -y on the right side
        if side < 0:
            quads.append(Quad(name, (x, y, height), (0, y1 - y, 0), (0, 0, -height), _shade(img, "+x")))
        else:
            quads.append(Quad(name, (x, y1, height), (0, -(y1 - y), 0), (0, 0, -height), _shade(img, "-x")))
        sw, sh = _size(depth, height, tpm / 4)  # plain walls, seen at a grazing angle
        for end, yy, facing in (("start", y, "-y"), ("end", y1, "+y")):
            wall = base_surface(sh, sw, rng, random_colour(rng, 110, 220), contrast=0.15, grain=0.08, largest=64)
            shapes(wall, rng, int(depth * height / 6), (int(0.2 * tpm), int(1.0 * tpm)),
                   lambda r: random_colour(r, 40, 200), alpha=(0.3, 0.7))
            quads.append(Quad(f"{name}_{end}", (x, yy, height), (side * depth, 0, 0), (0, 0, -height),
                              _shade(wall, facing)))
        y, k = y1, k + 1
    return quads


def _road(rng: np.random.Generator, tpm: float, tile: float = 24.0) -> list[Quad]:
    """Road tiles with lane marks (dashed centre line: 3 m dashes every 12 m; solid lines at |x| = 3 m
    between the lanes and the parking lanes) and sidewalk tiles, ``tile`` metres long."""
    quads = []
    w, h = _size(2 * ROAD_HALF, tile, tpm)
    x = -ROAD_HALF + (np.arange(w) + 0.5) / tpm
    line = max(int(0.12 * tpm), 2)
    for k, y0 in enumerate(np.arange(STREET_START, STREET_END, tile)):
        img = asphalt(h, w, rng, tpm)
        y = y0 + (np.arange(h) + 0.5) / tpm
        dash = (np.mod(y, 12.0) < 3.0)[:, None]
        paint = np.array([215, 220, 222], np.uint8)
        wear = value_noise(h, w, rng, max(int(0.1 * tpm), 1)) > 0.25  # worn paint
        centre = (np.abs(x) < line / tpm / 2)[None, :] & dash & wear
        edges = (np.abs(np.abs(x) - 3.0) < line / tpm / 2)[None, :] & wear
        img[centre | edges] = paint
        quads.append(Quad(f"road_{k:02d}", (-ROAD_HALF, y0, 0.0), (2 * ROAD_HALF, 0, 0), (0, tile, 0),
                          _shade(img, "+z")))
        sw, sh = _size(BUILDING_LINE - ROAD_HALF + 1.5, tile, tpm)
        for side in (-1, 1):
            walk = paving(sh, sw, rng, tpm)
            kerb = max(int(0.25 * tpm), 2)
            if side < 0:  # the kerb stones along the road edge
                walk[:, -kerb:] = mix_colours((150, 150, 150), random_colour(rng, 100, 200), 0.2)
                origin = (-BUILDING_LINE - 1.5, y0, 0.0)
            else:
                walk[:, :kerb] = mix_colours((150, 150, 150), random_colour(rng, 100, 200), 0.2)
                origin = (ROAD_HALF, y0, 0.0)
            quads.append(Quad(f"sidewalk_{'left' if side < 0 else 'right'}_{k:02d}", origin,
                              (BUILDING_LINE + 1.5 - ROAD_HALF, 0, 0), (0, tile, 0), _shade(walk, "+z")))
    return quads


def _car_face(face: str, w: int, h: int, rng: np.random.Generator, paint, tpm: float, cabin: bool) -> np.ndarray:
    img = base_surface(h, w, rng, paint, contrast=0.06, grain=0.03, largest=32)
    if face == "top":
        return img
    if cabin and face != "top":  # windows all round, pillars between them
        glass = base_surface(h, w, rng, (60, 50, 40), contrast=0.3, grain=0.05, largest=16)
        m = max(int(0.08 * tpm), 2)
        img[m:, m:w - m] = glass[m:, m:w - m]
        if face in ("left", "right"):
            img[:, w // 2 - m // 2:w // 2 + m // 2 + 1] = paint
        return img
    if face in ("left", "right"):  # wheels, a door seam, a handle
        r = int(0.33 * tpm)
        for cx in (int(0.18 * w), int(0.82 * w)):
            cv2.circle(img, (cx, h), r, (25, 25, 25), -1, cv2.LINE_AA)
            cv2.circle(img, (cx, h), r // 2, (170, 170, 170), -1, cv2.LINE_AA)
            for a in np.linspace(0, np.pi, 6):
                cv2.line(img, (cx, h), (int(cx + r // 2 * math.cos(a)), int(h - r // 2 * math.sin(a))), (60, 60, 60),
                         max(r // 10, 1), cv2.LINE_AA)
        cv2.line(img, (w // 2, 0), (w // 2, h - r // 2), mix_colours(paint, (0, 0, 0), 0.5), 2, cv2.LINE_AA)
        img[int(0.3 * h):int(0.3 * h) + 3, w // 2 - int(0.3 * tpm):w // 2 - int(0.15 * tpm)] = 40
    else:  # lights and a number plate
        lw = int(0.25 * tpm)
        light = (30, 30, 200) if rng.random() < 0.5 else (200, 230, 240)
        img[int(0.2 * h):int(0.45 * h), :lw] = light
        img[int(0.2 * h):int(0.45 * h), w - lw:] = light
        pw, ph = int(0.52 * tpm), int(0.12 * tpm)
        x0, y0 = (w - pw) // 2, int(0.55 * h)
        img[y0:y0 + ph, x0:x0 + pw] = (235, 235, 235)
        plate = "".join(chr(int(c)) for c in rng.integers(65, 91, 2)) + f" {int(rng.integers(10, 9999))}"
        cv2.putText(img, plate, (x0 + 2, y0 + ph - 2), cv2.FONT_HERSHEY_SIMPLEX, ph / 34.0, (20, 20, 20),
                    max(ph // 12, 1), cv2.LINE_AA)
    return img


def _cars(rng: np.random.Generator, tpm: float) -> list[Quad]:
    """Parked cars (a body box and a cabin box each) in the parking lanes, about one every 10 m a side."""
    quads = []
    for side in (-1, 1):
        y, k = STREET_START + 2.0, 0
        while y < STREET_END - 6.0:
            length = float(rng.uniform(3.8, 4.8))
            if rng.random() < 0.55:
                paint = random_colour(rng, 20, 235)
                cx = side * (ROAD_HALF - 1.0 + float(rng.uniform(-0.15, 0.15)))
                cy = y + length / 2
                body = box_quads(f"car_{side:+d}_{k:02d}", cx, cy, 1.8, length, 0.75, z0=0.25)
                cabin = box_quads(f"car_{side:+d}_{k:02d}_cabin", cx, cy + 0.2 * side, 1.65, 0.55 * length, 0.55,
                                  z0=1.0)
                for quads_of, is_cabin in ((body, False), (cabin, True)):
                    for q in quads_of:
                        face = q.name.rsplit("_", 1)[1]
                        w, h = _size(np.linalg.norm(q.edge_u), np.linalg.norm(q.edge_v), 1.5 * tpm)
                        facing = {"front": "-y", "back": "+y", "left": "-x", "right": "+x", "top": "+z"}[face]
                        q.texture = _shade(_car_face(face, w, h, rng, paint, 1.5 * tpm, is_cabin), facing)
                    quads += quads_of
                k += 1
            y += length + float(rng.uniform(1.0, 8.0))
    return quads


def _sign_board(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size, size, 3) uint8 BGR traffic sign: a ring with a speed limit, a triangle or a square, with a
    letter."""
    w = h = size
    img = np.full((h, w, 3), 235, np.uint8)
    colour = random_colour(rng, 10, 240)
    shape = int(rng.integers(0, 3))
    c, r = (w // 2, h // 2), int(0.45 * w)
    if shape == 0:
        cv2.circle(img, c, r, colour, -1, cv2.LINE_AA)
        cv2.circle(img, c, int(0.7 * r), (240, 240, 240), -1, cv2.LINE_AA)
        label = str(int(rng.choice([10, 20, 30, 50, 70, 80, 100])))
    else:
        if shape == 1:
            pts = np.array([[w // 2, int(0.05 * h)], [int(0.95 * w), int(0.9 * h)], [int(0.05 * w), int(0.9 * h)]])
            cv2.fillPoly(img, [pts.astype(np.int32)], colour, cv2.LINE_AA)
            cv2.fillPoly(img, [((pts - c) * 0.6 + c).astype(np.int32)], (240, 240, 240), cv2.LINE_AA)
        else:
            img[int(0.1 * h):int(0.9 * h), int(0.1 * w):int(0.9 * w)] = colour
        label = chr(int(rng.integers(65, 91)))
    cv2.putText(img, label, (int(0.3 * w), int(0.62 * h)), cv2.FONT_HERSHEY_DUPLEX, w / 90.0, (20, 20, 20),
                max(w // 40, 1), cv2.LINE_AA)
    return img


def _poles(rng: np.random.Generator, tpm: float) -> list[Quad]:
    """Street lamps every 25 m on both sidewalks, some of them traffic signs (a 2.6 m post and a 0.75 m
    board facing -y)."""
    quads = []
    for side in (-1, 1):
        for k, y in enumerate(np.arange(STREET_START + 10.0, STREET_END - 10.0, 25.0) + rng.uniform(-3, 3)):
            x = side * (ROAD_HALF + 0.6)
            sign = rng.random() < 0.4
            height = 2.6 if sign else float(rng.uniform(5.0, 7.0))
            metal = random_colour(rng, 50, 140)
            for q in box_quads(f"pole_{side:+d}_{k:02d}", x, float(y), 0.16, 0.16, height):
                w, h = 32, _size(1.0, height, tpm)[1]  # 32 texels across: mipmaps down to 4 px wide
                img = base_surface(h, w, rng, metal, contrast=0.1, grain=0.05, largest=8)
                for _ in range(int(rng.integers(0, 3))):  # stickers and bands, 0.3 m tall
                    y0 = int(rng.uniform(0.5, 2.0) * tpm)
                    img[y0:y0 + int(0.3 * tpm)] = random_colour(rng, 30, 240)
                q.texture = _shade(img, "+z" if q.name.endswith("top") else "-y")
                quads.append(q)
            if sign:
                s = 0.75
                board = _sign_board(rng, _size(s, s, 2 * tpm)[0])
                quads.append(Quad(f"sign_{side:+d}_{k:02d}", (x - s / 2, float(y) - 0.09, height + s),
                                  (s, 0, 0), (0, 0, -s), _shade(board, "-y")))
    return quads


@functools.lru_cache(maxsize=2)
def street_scene(seed: int = 0, texels_per_metre: float = 40.0) -> Scene:
    """The street (built once per process and cached; treat as read-only): see the module docstring.

    Textures are synthesized from ``seed`` at about ``texels_per_metre`` (a few seconds; about 150 MB).
    """
    tpm = float(texels_per_metre)
    root = np.random.SeedSequence(int(seed))
    rngs = [np.random.default_rng(s) for s in root.spawn(6)]
    quads = _road(rngs[0], tpm) + _buildings(-1, rngs[1], tpm) + _buildings(1, rngs[2], tpm)
    quads += _cars(rngs[3], tpm) + _poles(rngs[4], tpm)
    half = BUILDING_LINE + 14.0
    w, h = _size(2 * half, 20.0, tpm / 2)
    end = facade(h, w, rngs[5], tpm / 2)
    quads.append(Quad("house_end", (-half, STREET_END, 20.0), (2 * half, 0, 0), (0, 0, -20.0), _shade(end, "-y")))
    bounds = np.array([[-half, STREET_START, 0.0], [half, STREET_END, 25.0]])
    return Scene(quads, name=f"street(seed={seed})", background=SKY, bounds=bounds)


def street_drive(n: int = 150, speed: float = 1.0, weave: float = 0.3, seed: int = 0) -> np.ndarray:
    """Driving down the street: the camera 1.6 m above the road (KITTI's camera height) in the lane at
    x = :data:`LANE_X`, looking ahead along the path and 2 degrees down, ``speed`` metres per frame along y
    (1.0: KITTI at frame skip 2), weaving ``weave`` metres to the sides (a sine of 80 m period) with a 2 cm
    bob, so that the path is not a line and a Sim(3) alignment to it is defined. ``seed`` picks the start
    (y in [0, 20] m) and the phases. The drive must end 45 m before the far end of the street:
    ``(n - 1) * speed`` is at most 355 m."""
    n = _check_frames(n)
    _check_range("speed", speed, 0, 5, "metres per frame", open_low=True)
    _check_range("weave", weave, 0, 1.5, "metres")
    if (n - 1) * speed > 355.0:
        raise ConfigError(f"street-drive: frames x speed = {(n - 1) * speed:g} m is longer than the street "
                          f"allows (at most 355 m)")
    rng = np.random.default_rng(int(seed))
    start, phase, bob = rng.uniform(0.0, 20.0), rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi)
    y = start + speed * np.arange(n)
    k = 2 * np.pi / 80.0
    x = LANE_X + weave * np.sin(k * y + phase)
    z = 1.6 + 0.02 * np.sin(2 * np.pi * y / 7.0 + bob)
    slope = weave * k * np.cos(k * y + phase)  # dx/dy: the heading follows the path
    centers = np.stack([x, y, z], axis=1)
    ahead = np.stack([slope, np.ones(n), np.full(n, -math.tan(math.radians(2.0)))], axis=1)
    return np.stack([look_at(c, c + d) for c, d in zip(centers, ahead)])
