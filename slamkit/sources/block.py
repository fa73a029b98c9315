"""A city block driven round, and the ``block-loop`` camera path (issue 18: a loop with real drift).

A rectangular ring road round one block of houses: on returning to the start the local map no longer holds
the first keyframes (the block is 250 m round, as KITTI 00/05's loops are large), so drift builds up and a
loop detector has something to close. The block's houses face the road from the inside and the houses of
the neighbouring blocks face it from the outside; every facade is drawn from one seed with the street
scene's generators (:func:`~slamkit.sources.textures.facade`, asphalt, paving and the fixed sun of
:mod:`slamkit.sources.street`), so all of them differ and features are distinctive.

Geometry (world frame: z up, metres, ground at z = 0): the inner block's building line is the rectangle
|x| <= 30, |y| <= 20 (:data:`BLOCK_HALF`: 60 x 40 m); outward from it come 3 m of
sidewalk, the 10 m road, 3 m of sidewalk and the outer building line (at 16 m). Facades stand 0 to 1.5 m
behind their building line. The road's centre line is the rectangle offset by :data:`CENTRE_OFFSET` (8 m)
with corners rounded on circles of that radius round the block's corners, so the turns take about 12 m of
driving. The ground of the corners is one quad each (road inside the annulus 3..13 m from the block corner,
paving outside), the ground of the sides one quad per 20 m. Texel density as the street's (``texels_per_metre``
40); no cars or poles (the block's facades alone give ORB 2,000 features per frame).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..errors import ConfigError
from .motions import _check_frames, _check_range
from .render import look_at
from .scene import Scene
from .street import SKY, _shade, _size
from .surfaces import Quad
from .textures import asphalt, base_surface, facade, mix_colours, paving, random_colour, shapes, value_noise

BLOCK_HALF = (30.0, 20.0)
"""Half extents (x, y) of the inner block's building line (metres)."""
SIDEWALK, ROAD = 3.0, 10.0
"""Width of each sidewalk and of the road (metres)."""
CENTRE_OFFSET = SIDEWALK + ROAD / 2
"""Distance of the road's centre line from the inner building line, and radius of its corners (metres)."""
OUTER_OFFSET = 2 * SIDEWALK + ROAD
"""Distance of the outer building line from the inner one (metres)."""
BEHIND = 1.5
"""Ground reaches this far behind each building line (metres), under the set-back facades."""
TILE = 20.0
"""Length of one ground quad along a side (metres); divides both sides of the block."""
LAP = 2 * (2 * BLOCK_HALF[0] + 2 * BLOCK_HALF[1]) + 2 * math.pi * CENTRE_OFFSET
"""Length of one lap of the centre line (metres): four straights and four quarter circles."""

_SIDES = (  # (start corner, direction along the side, outward normal), counter-clockwise seen from above
    ((-1, -1), (1, 0), (0, -1)),
    ((1, -1), (0, 1), (1, 0)),
    ((1, 1), (-1, 0), (0, 1)),
    ((-1, 1), (0, -1), (-1, 0)),
)
_FACING = {(1, 0): "+x", (-1, 0): "-x", (0, 1): "+y", (0, -1): "-y"}


def _corner(k: int) -> np.ndarray:
    sx, sy = _SIDES[k][0]
    return np.array([sx * BLOCK_HALF[0], sy * BLOCK_HALF[1]])


def _side_length(k: int) -> float:
    return 2 * BLOCK_HALF[0] if _SIDES[k][1][0] else 2 * BLOCK_HALF[1]


def _row(name: str, start, direction, facing, length: float, rng: np.random.Generator, tpm: float) -> list[Quad]:
    """Houses in a row from ``start`` (2D, on the building line) ``length`` metres along ``direction``, their
    facades facing ``facing`` (2D unit, towards the road), 0 to 1.5 m behind the line, with side walls."""
    start, d, m = (np.asarray(v, np.float64) for v in (start, direction, facing))
    u = np.array([-m[1], m[0]])  # a viewer facing the facade reads its texture along (-m) x z
    quads, s, k = [], 0.0, 0
    while s < length - 1e-9:
        s1 = min(s + float(rng.uniform(8.0, 24.0)), length)
        if length - s1 < 4.0:  # no sliver of a house at the end of the row
            s1 = length
        height, back, depth = float(rng.uniform(7.0, 22.0)), float(rng.uniform(0.0, BEHIND)), 8.0
        p0, p1 = start + s * d - back * m, start + s1 * d - back * m
        w, h = _size(s1 - s, height, tpm)
        img = facade(h, w, rng, tpm, storey=float(rng.uniform(2.9, 3.6)), spacing=float(rng.uniform(2.2, 3.6)))
        origin = p0 if u @ d > 0 else p1
        label = f"{name}_{k:02d}"
        quads.append(Quad(label, (*origin, height), (*(u * (s1 - s)), 0), (0, 0, -height),
                          _shade(img, _FACING[tuple(int(round(c)) for c in m)])))
        sw, sh = _size(depth, height, tpm / 4)
        for end, p, sign in (("start", p0, -1), ("end", p1, 1)):
            wall = base_surface(sh, sw, rng, random_colour(rng, 110, 220), contrast=0.15, grain=0.08, largest=64)
            shapes(wall, rng, int(depth * height / 6), (int(0.2 * tpm), int(1.0 * tpm)),
                   lambda r: random_colour(r, 40, 200), alpha=(0.3, 0.7))
            facing_end = _FACING[tuple(int(round(c)) for c in sign * d)]
            quads.append(Quad(f"{label}_{end}", (*p, height), (*(-m * depth), 0), (0, 0, -height),
                              _shade(wall, facing_end)))
        s, k = s1, k + 1
    return quads


def _paint(img: np.ndarray, road: np.ndarray, kerb: np.ndarray, centre: np.ndarray, edges: np.ndarray,
           rng: np.random.Generator, tpm: float) -> np.ndarray:
    """Asphalt where ``road``, paving elsewhere, kerb stones on ``kerb``, worn white paint on ``centre`` and
    ``edges`` (all (H, W) bool masks); ``img`` is the paving, changed in place and returned."""
    h, w = img.shape[:2]
    img[road] = asphalt(h, w, rng, tpm)[road]
    img[kerb] = mix_colours((150, 150, 150), random_colour(rng, 100, 200), 0.2)
    wear = value_noise(h, w, rng, max(int(0.1 * tpm), 1)) > 0.25
    img[(centre | edges) & wear] = (215, 220, 222)
    return img


def _marks(lateral: np.ndarray, along: np.ndarray, tpm: float) -> tuple[np.ndarray, ...]:
    """(road, kerb, dashed centre line, edge lines) masks from the distance ``lateral`` to the inner building
    line and the distance ``along`` the road (metres, broadcastable arrays)."""
    lateral, along = np.broadcast_arrays(lateral, along)
    half = max(int(0.12 * tpm), 2) / tpm / 2
    road = (lateral >= SIDEWALK) & (lateral < SIDEWALK + ROAD)
    kerb = ~road & ((np.abs(lateral - SIDEWALK) < 0.25) | (np.abs(lateral - SIDEWALK - ROAD) < 0.25))
    centre = (np.abs(lateral - CENTRE_OFFSET) < half) & (np.mod(along, 12.0) < 3.0)
    edges = (np.abs(lateral - SIDEWALK - 0.4) < half) | (np.abs(lateral - SIDEWALK - ROAD + 0.4) < half)
    return road, kerb, centre, edges


def _ground(rng: np.random.Generator, tpm: float) -> list[Quad]:
    """The ground: the block's inside (paving, seen only at the foot of the set-back facades), one quad per
    :data:`TILE` metres of each side (sidewalks, road with lane marks) and one per corner (the road on the
    annulus round the block's corner)."""
    width = OUTER_OFFSET + BEHIND
    a, b = BLOCK_HALF
    w, h = _size(2 * a, 2 * b, tpm)
    quads = [Quad("ground_block", (-a, -b, 0.0), (2 * a, 0, 0), (0, 2 * b, 0), _shade(paving(h, w, rng, tpm), "+z"))]
    for k, (_, d, o) in enumerate(_SIDES):
        d, o, c = np.array(d, np.float64), np.array(o, np.float64), _corner(k)
        for t in range(int(round(_side_length(k) / TILE))):
            w, h = _size(TILE, width, tpm)
            along = t * TILE + (np.arange(w) + 0.5)[None, :] / tpm
            lateral = (np.arange(h) + 0.5)[:, None] / tpm
            img = _paint(paving(h, w, rng, tpm), *_marks(lateral, along, tpm), rng, tpm)
            quads.append(Quad(f"ground_{k}_{t}", (*(c + t * TILE * d), 0.0), (*(d * TILE), 0), (*(o * width), 0),
                              _shade(img, "+z")))
        o_prev = np.array(_SIDES[k - 1][2], np.float64)
        n = _size(width, width, tpm)[0]
        grid = (np.arange(n) + 0.5) / tpm
        radius = np.hypot(grid[None, :], grid[:, None])  # texel (i, j) is at c + o * x_i + o_prev * y_j
        angle = np.arctan2(grid[None, :], grid[:, None]) * CENTRE_OFFSET  # arc length along the centre line
        img = _paint(paving(n, n, rng, tpm), *_marks(radius, angle, tpm), rng, tpm)
        quads.append(Quad(f"ground_corner_{k}", (*c, 0.0), (*(o * width), 0), (*(o_prev * width), 0),
                          _shade(img, "+z")))
    return quads


@functools.lru_cache(maxsize=2)
def block_scene(seed: int = 0, texels_per_metre: float = 40.0) -> Scene:
    """The city block (built once per process and cached; treat as read-only): see the module docstring.

    Textures are synthesized from ``seed`` at about ``texels_per_metre`` (as the street: a few seconds,
    about 150 MB).
    """
    tpm = float(texels_per_metre)
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(9)]
    quads = _ground(rngs[0], tpm)
    for k, (_, d, o) in enumerate(_SIDES):
        d, o, c = np.array(d, np.float64), np.array(o, np.float64), _corner(k)
        quads += _row(f"house_inner_{k}", c, d, o, _side_length(k), rngs[1 + k], tpm)
        # the outer row runs the whole side of the neighbouring blocks, from outer corner to outer corner
        start = c + OUTER_OFFSET * (o - d)
        quads += _row(f"house_outer_{k}", start, d, -o, _side_length(k) + 2 * OUTER_OFFSET, rngs[5 + k], tpm)
    a, b = BLOCK_HALF[0] + OUTER_OFFSET + BEHIND, BLOCK_HALF[1] + OUTER_OFFSET + BEHIND
    bounds = np.array([[-a, -b, 0.0], [a, b, 25.0]])
    return Scene(quads, name=f"block(seed={seed})", background=SKY, bounds=bounds)


def _centre_line(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centre line of the road at arc lengths ``s`` (N,) metres (any real; one lap is :data:`LAP`):
    (N, 2) points, (N, 2) unit tangents, (N, 2) unit normals towards the block, (N,) curvature (1/m)."""
    s = np.mod(s, LAP)
    pts, tan, nrm, kappa = (np.zeros((len(s), 2)), np.zeros((len(s), 2)), np.zeros((len(s), 2)),
                            np.zeros(len(s)))
    start, arc = 0.0, math.pi / 2 * CENTRE_OFFSET
    for k, (_, d, o) in enumerate(_SIDES):
        d, o, c = np.array(d, np.float64), np.array(o, np.float64), _corner(k)
        o_next, length = np.array(_SIDES[(k + 1) % 4][2], np.float64), _side_length(k)
        on = (s >= start) & (s < start + length)
        pts[on] = c + CENTRE_OFFSET * o + (s[on] - start)[:, None] * d
        tan[on], nrm[on] = d, -o
        on = (s >= start + length) & (s < start + length + arc)
        f = ((s[on] - start - length) / CENTRE_OFFSET)[:, None]  # angle turned in the corner (radians)
        radial = np.cos(f) * o + np.sin(f) * o_next
        pts[on] = _corner((k + 1) % 4) + CENTRE_OFFSET * radial
        tan[on], nrm[on], kappa[on] = -np.sin(f) * o + np.cos(f) * o_next, -radial, 1.0 / CENTRE_OFFSET
        start += length + arc
    return pts, tan, nrm, kappa


def block_loop(n: int | None = None, laps: int = 2, speed: float | None = None, weave: float = 0.3,
               seed: int = 0) -> np.ndarray:
    """Driving ``laps`` times round the city block, counter-clockwise (the block on the left): the camera
    1.5 m above the road's centre line, looking ahead along the path and 2 degrees down, weaving ``weave``
    metres to the sides (five sine periods a lap, so about 50 m each). ``seed`` picks the start (on the long
    side, 10 to 40 m past the corner) and the phase of the weave. The ``n`` frames cover exactly ``laps``
    laps of :data:`LAP` metres, so frame ``j * (n - 1) / laps`` ends lap j and the last pose equals the
    first. Give either ``n`` or ``speed`` (metres per frame; default 0.25 when neither is given: 1,003
    frames a lap), not both."""
    if int(laps) != laps or laps < 1:
        raise ConfigError(f"laps must be an integer >= 1 (got {laps})")
    if n is not None and speed is not None:
        raise ConfigError("block-loop: give frames or speed, not both (the frames cover exactly the laps)")
    if speed is not None:
        _check_range("speed", speed, 0.01, 5, "metres per frame")
    if n is None:
        n = int(round(laps * LAP / (0.25 if speed is None else speed))) + 1
    n = _check_frames(n)
    _check_range("weave", weave, 0, 1.5, "metres")
    rng = np.random.default_rng(int(seed))
    start, phase = rng.uniform(10.0, 40.0), rng.uniform(0, 2 * np.pi)
    s = start + int(laps) * LAP * np.arange(int(n)) / (int(n) - 1)
    pts, tan, nrm, kappa = _centre_line(s)
    k = 2 * np.pi * 5 / LAP
    w = weave * np.sin(k * s + phase)  # offset towards the block
    dw = weave * k * np.cos(k * s + phase)
    centers = np.concatenate([pts + w[:, None] * nrm, np.full((len(s), 1), 1.5)], axis=1)
    heading = tan * (1 - kappa * w)[:, None] + dw[:, None] * nrm  # derivative of the path along s
    heading /= np.linalg.norm(heading, axis=1, keepdims=True)
    ahead = np.concatenate([heading, np.full((len(s), 1), -math.tan(math.radians(2.0)))], axis=1)
    return np.stack([look_at(c, c + a) for c, a in zip(centers, ahead)])
