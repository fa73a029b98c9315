"""A long corridor whose surfaces repeat one tile, and the ``corridor-walk`` camera path.

Perceptual aliasing on purpose (issue 18: a loop detector must find no loop on a sequence that never
revisits a place, even where places look alike): every :data:`TILE` metres the walls show the same door,
poster, notice board and light switch, the floor the same linoleum and the ceiling the same light panel --
one texture per surface shared by all tiles, so the images at two positions one tile apart are identical
up to what is seen at the very ends. The two end walls are plain paint, without features.

Geometry (world frame: z up, metres, floor at z = 0): x in [-:data:`HALF_WIDTH`, :data:`HALF_WIDTH`],
y in [0, :data:`LENGTH`], z in [0, :data:`HEIGHT`]. Tile k spans y in [k * TILE, (k + 1) * TILE]. Textures
are about ``texels_per_metre`` (200: 5 mm texels, 2 px at the 1.2 m to the nearest wall).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from ..errors import ConfigError
from .motions import _check_frames, _check_range
from .render import look_at
from .scene import Scene
from .surfaces import Quad, Texture
from .textures import base_surface, notes, paste, photo, shapes, wood

LENGTH, HALF_WIDTH, HEIGHT = 60.0, 1.2, 2.7
"""Corridor extent (metres): 60 m long, 2.4 m wide, 2.7 m high."""
TILE = 3.0
"""Period of the repeated texture along the corridor (metres)."""


def _wall_tile(tpm: float, rng: np.random.Generator) -> np.ndarray:
    """The wall tile (TILE x HEIGHT metres, rows from the ceiling down): paint, dado rail and skirting, a
    door with frame, handle and sign, a framed poster, a notice board with notes, a light switch."""
    w, h = int(TILE * tpm), int(HEIGHT * tpm)
    img = base_surface(h, w, rng, (200, 215, 225), contrast=0.05, grain=0.04)
    m = lambda metres: int(round(metres * tpm))  # noqa: E731
    img[h - m(1.0):h - m(1.0) + m(0.04)] = (120, 140, 150)  # dado rail
    img[h - m(1.0) + m(0.04):] = (np.float32(0.85) * img[h - m(1.0) + m(0.04):]).astype(np.uint8)
    img[h - m(0.1):] = (70, 80, 90)  # skirting
    dx, dw, dh = m(0.3), m(0.9), m(2.1)
    img[h - dh - m(0.06):h, dx - m(0.06):dx + dw + m(0.06)] = (60, 70, 80)  # door frame
    with np.errstate(invalid="ignore"):  # wood() scales unfilled texels before filling them
        img[h - dh:h, dx:dx + dw] = wood(dh, dw, rng, m(0.15), vertical=True)
    cv2.circle(img, (dx + dw - m(0.1), h - m(1.05)), m(0.035), (180, 190, 200), -1, cv2.LINE_AA)
    img[h - m(1.75):h - m(1.6), dx + m(0.3):dx + m(0.6)] = (235, 235, 235)  # door sign
    cv2.putText(img, "B-1", (dx + m(0.33), h - m(1.63)), cv2.FONT_HERSHEY_SIMPLEX, tpm / 250.0, (30, 30, 30),
                max(m(0.01), 1), cv2.LINE_AA)
    paste(img, photo("astronaut"), m(1.55), h - m(2.35), m(0.7), m(0.7), frame=m(0.03), frame_colour=(30, 30, 30))
    board = base_surface(m(0.55), m(0.55), rng, (70, 110, 160), contrast=0.2, grain=0.1, largest=16)
    notes(board, rng, 6, (m(0.1), m(0.2)))
    paste(img, board, m(2.35), h - m(1.9), m(0.55), m(0.55), frame=m(0.02), frame_colour=(40, 60, 90))
    img[h - m(1.25):h - m(1.15), m(1.3):m(1.38)] = (240, 240, 240)  # light switch
    shapes(img[:h - m(1.0)], rng, 6, (m(0.03), m(0.12)), alpha=(0.4, 0.8))  # scuffs and stickers
    shade = np.linspace(1.05, 0.8, h, dtype=np.float32)[:, None, None]  # lit from the ceiling
    return cv2.convertScaleAbs(img.astype(np.float32) * shade)


def _floor_tile(tpm: float, rng: np.random.Generator) -> np.ndarray:
    """Speckled linoleum in 0.6 m squares (2 * HALF_WIDTH x TILE metres)."""
    w, h = int(2 * HALF_WIDTH * tpm), int(TILE * tpm)
    img = base_surface(h, w, rng, (110, 130, 140), contrast=0.15, grain=0.2, largest=32)
    s = int(0.6 * tpm)
    img[(np.arange(h) % s) < 2] = 60
    img[:, (np.arange(w) % s) < 2] = 60
    shapes(img, rng, 25, (int(0.02 * tpm), int(0.1 * tpm)), alpha=(0.3, 0.7))
    return img


def _ceiling_tile(tpm: float, rng: np.random.Generator) -> np.ndarray:
    """Ceiling panels with one light panel and a smoke detector (2 * HALF_WIDTH x TILE metres)."""
    w, h = int(2 * HALF_WIDTH * tpm), int(TILE * tpm)
    img = base_surface(h, w, rng, (225, 228, 230), contrast=0.05, grain=0.05)
    s = int(0.6 * tpm)
    img[(np.arange(h) % s) < 3] = 150
    img[:, (np.arange(w) % s) < 3] = 150
    img[int(1.2 * tpm):int(1.8 * tpm), int(0.6 * tpm):int(1.8 * tpm)] = 250
    cv2.circle(img, (int(1.9 * tpm), int(0.3 * tpm)), int(0.06 * tpm), (200, 200, 200), -1, cv2.LINE_AA)
    return img


@functools.lru_cache(maxsize=2)
def corridor_scene(seed: int = 0, texels_per_metre: float = 200.0) -> Scene:
    """The corridor (built once per process and cached; treat as read-only): see the module docstring.
    ``seed`` draws the one tile's details; all tiles are the same."""
    tpm = float(texels_per_metre)
    rng = np.random.default_rng(int(seed))
    wall, floor, ceiling = (Texture(f(tpm, rng)) for f in (_wall_tile, _floor_tile, _ceiling_tile))
    X, L, Z = HALF_WIDTH, LENGTH, HEIGHT
    quads = []
    for k in range(int(round(L / TILE))):
        y0, y1 = k * TILE, (k + 1) * TILE
        # both walls read left to right from inside the corridor (texture columns along the wall)
        quads.append(Quad(f"wall_left_{k:02d}", (-X, y0, Z), (0, TILE, 0), (0, 0, -Z), wall))
        quads.append(Quad(f"wall_right_{k:02d}", (X, y1, Z), (0, -TILE, 0), (0, 0, -Z), wall))
        quads.append(Quad(f"floor_{k:02d}", (-X, y0, 0.0), (2 * X, 0, 0), (0, TILE, 0), floor))
        quads.append(Quad(f"ceiling_{k:02d}", (-X, y0, Z), (2 * X, 0, 0), (0, TILE, 0), ceiling))
    plain = Texture(np.full((16, 16, 3), (170, 180, 190), np.uint8))
    quads.append(Quad("end_far", (-X, L, Z), (2 * X, 0, 0), (0, 0, -Z), plain))
    quads.append(Quad("end_near", (X, 0.0, Z), (-2 * X, 0, 0), (0, 0, -Z), plain))
    bounds = np.array([[-X, 0.0, 0.0], [X, L, Z]])
    return Scene(quads, name=f"corridor(seed={seed})", bounds=bounds)


def corridor_walk(n: int = 300, speed: float = 0.05, sway: float = 0.15, seed: int = 0) -> np.ndarray:
    """A straight walk down the corridor, never turning back: the camera 1.6 m high looks ahead along +y,
    ``speed`` metres per frame (0.05: 1.5 m/s at 30 fps) from y = 2 to 5 m (drawn from ``seed``), swaying
    ``sway`` metres to the sides (a sine of 7 m period) with the heading following the sway and a slow +-4
    degree gaze sweep. The walk must stop 10 m before the far end: ``(n - 1) * speed`` is at most 43 m."""
    n = _check_frames(n)
    _check_range("speed", speed, 0, 1, "metres per frame", open_low=True)
    _check_range("sway", sway, 0, 0.5, "metres")
    if (n - 1) * speed > 43.0:
        raise ConfigError(f"corridor-walk: frames x speed = {(n - 1) * speed:g} m is longer than the corridor "
                          f"allows (at most 43 m)")
    rng = np.random.default_rng(int(seed))
    start, phase, sweep = rng.uniform(2.0, 5.0), rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi)
    y = start + speed * np.arange(n)
    k = 2 * np.pi / 7.0
    x = sway * np.sin(k * y + phase)
    yaw = np.arctan(sway * k * np.cos(k * y + phase)) + np.radians(4.0) * np.sin(2 * np.pi * y / 11.0 + sweep)
    centers = np.stack([x, y, np.full(n, 1.6)], axis=1)
    ahead = np.stack([np.sin(yaw), np.cos(yaw), np.full(n, -0.05)], axis=1)
    return np.stack([look_at(c, c + d) for c, d in zip(centers, ahead)])
