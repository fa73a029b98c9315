"""Procedural textures of the synthetic scenes: noise, painted surfaces, shapes, paper notes, handwriting,
wooden planks, bookshelves, and the sample photographs that ship with scikit-image.

Deterministic: every function draws from the numpy Generator it is given, so a texture is a function of
its seed. Images are uint8 BGR (OpenCV's order), sizes in texels.
"""

from __future__ import annotations

import functools
import warnings

import cv2
import numpy as np
import skimage.data as skdata

from ..errors import ConfigError

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
    if name not in _PHOTOS:
        raise ConfigError(f"photo: unknown sample photograph {name!r}; choose from {', '.join(_PHOTOS)}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = skdata.stereo_motorcycle()[0] if name == "motorcycle" else getattr(skdata, name)()
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


def random_colour(rng: np.random.Generator, lo: int = 20, hi: int = 235) -> tuple[int, int, int]:
    """A BGR colour whose channels are drawn uniformly from [lo, hi)."""
    return tuple(int(v) for v in rng.integers(lo, hi, 3))


def mix_colours(c0, c1, f: float) -> tuple[int, int, int]:
    """The colour ``(1 - f) c0 + f c1``, rounded."""
    return tuple(int(round(a * (1 - f) + b * f)) for a, b in zip(c0, c1))


def base_surface(h: int, w: int, rng: np.random.Generator, colour, contrast: float = 0.12,
                 grain: float = 0.06, largest: int = 128) -> np.ndarray:
    """(h, w, 3) uint8 BGR painted/plastered surface: ``colour`` modulated by multi-scale noise (relative
    ``contrast``) and a fine grain."""
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
    h, w = canvas.shape[:2]
    palette = palette or (lambda r: random_colour(r, 0, 256))
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
            col = random_colour(rng, 20, 220)
            x1 = min(x + bw, w)
            canvas[bottom - bh:bottom, x:x1] = col
            for _ in range(int(rng.integers(0, 3))):
                yb = bottom - int(bh * rng.uniform(0.1, 0.9))
                canvas[yb:yb + max(bw // 6, 2), x:x1] = mix_colours(col, (230, 220, 190), 0.7)
            label = "".join(chr(int(c)) for c in rng.integers(65, 91, 2))
            cv2.putText(canvas, label, (x + 1, bottom - bh // 2), cv2.FONT_HERSHEY_SIMPLEX, bw / 45.0,
                        mix_colours(col, (255, 255, 255), 0.8), 1, cv2.LINE_AA)
            canvas[bottom - bh:bottom, x:x + 1] = (20, 20, 20)
            x = x1 + int(rng.integers(0, 3))
            if rng.random() < 0.06:
                x += int(rng.uniform(0.05, 0.15) * tpm)  # a gap
    return canvas
