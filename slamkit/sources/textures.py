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


# ----------------------------------------------------------------------------------------------------------
# outdoor surfaces of the street scene (slamkit.sources.street)


def brick(h: int, w: int, rng: np.random.Generator, tpm: float, colour=(60, 80, 150)) -> np.ndarray:
    """(h, w, 3) uint8 BGR brick wall at ``tpm`` texels per metre: 0.25 x 0.075 m bricks in running bond,
    each with its own tint around ``colour``, grey mortar joints and a fine grain."""
    bw, bh = max(int(0.25 * tpm), 4), max(int(0.075 * tpm), 3)
    rows, cols = -(-h // bh) + 1, -(-w // bw) + 2
    tints = np.clip(np.asarray(colour, np.float32) * rng.uniform(0.7, 1.25, (rows, cols, 1)).astype(np.float32)
                    + rng.uniform(-12, 12, (rows, cols, 3)).astype(np.float32), 0, 255)
    r = np.arange(h) // bh
    shift = np.where(r % 2 == 1, bw // 2, 0)
    c = (np.arange(w)[None, :] + shift[:, None]) // bw
    img = tints[r[:, None], c]
    grain = value_noise(h, w, rng, 1) * np.float32(0.25) + np.float32(0.875)
    img *= grain[..., None]
    joint = max(bh // 6, 1)
    img[(np.arange(h) % bh) < joint] = (150, 155, 160)
    mortar = ((np.arange(w)[None, :] + shift[:, None]) % bw) < joint
    img[mortar] = (150, 155, 160)
    return cv2.convertScaleAbs(img)


def _window(img: np.ndarray, rng: np.random.Generator, x: int, y: int, w: int, h: int, frame_colour,
            tpm: float) -> None:
    """One window of a facade, in place: frame, glass with reflections, mullions, maybe curtains/blinds."""
    f = max(int(0.06 * tpm), 2)
    w, h = min(w, img.shape[1] - x - 2 * f), min(h, img.shape[0] - y - 2 * f)
    if w < 4 or h < 4:
        return
    img[y - f:y + h + f, x - f:x + w + f] = frame_colour
    glass = fractal_noise(h, w, rng, largest=max(w // 2, 4), smallest=2, roughness=0.7)
    base = np.array([70, 60, 45], np.float32) * np.float32(rng.uniform(0.6, 1.5))
    img[y:y + h, x:x + w] = cv2.convertScaleAbs(base[None, None, :] * (0.6 + 0.9 * glass[..., None]))
    if rng.random() < 0.5:  # curtains or a blind, drawn to a random height
        depth = int(h * rng.uniform(0.15, 0.9))
        img[y:y + depth, x:x + w] = mix_colours(random_colour(rng, 60, 240), (200, 200, 200), 0.3)
        for k in range(0, depth, max(int(0.05 * tpm), 3)):
            img[y + k, x:x + w] = (img[y + k, x:x + w] * 0.8).astype(np.uint8)
    if rng.random() < 0.3:  # a pot, a sticker, a lamp behind the glass
        shapes(img[y:y + h, x:x + w], rng, 2, (max(w // 8, 2), max(w // 3, 3)), alpha=(0.8, 1.0))
    m = max(f // 2, 1)
    kind = int(rng.integers(0, 3))
    if kind >= 1:
        img[y:y + h, x + w // 2 - m // 2:x + w // 2 + m] = frame_colour
    if kind == 2:
        img[y + h // 3:y + h // 3 + m, x:x + w] = frame_colour
    sill = max(int(0.05 * tpm), 2)
    img[y + h + f:y + h + f + sill, x - 2 * f:x + w + 2 * f] = mix_colours(frame_colour, (230, 230, 230), 0.5)


def facade(h: int, w: int, rng: np.random.Generator, tpm: float, *, storey: float = 3.2,
           spacing: float = 2.8) -> np.ndarray:
    """(h, w, 3) uint8 BGR front of a town house, ``tpm`` texels per metre (rows from the roof down to the
    ground): plaster or brick, a cornice, string courses between storeys of ``storey`` metres, windows
    every ``spacing`` metres (each with its own glass, curtains and mullions), and a ground floor with
    shop windows, a door, a sign with lettering, posters and stains. Everything is drawn from ``rng``, so
    every building differs."""
    if rng.random() < 0.4:
        img = brick(h, w, rng, tpm, random_colour(rng, 40, 170))
    else:
        img = base_surface(h, w, rng, random_colour(rng, 110, 235), contrast=0.12, grain=0.06,
                           largest=int(2 * tpm))
    frame_colour = random_colour(rng, 20, 240)
    st, sp = int(storey * tpm), int(spacing * tpm)
    cornice = int(0.4 * tpm)
    img[:cornice] = (img[:cornice] * rng.uniform(0.5, 0.8)).astype(np.uint8)
    img[cornice - 4:cornice] = 40
    ground = h - int(1.1 * st)  # top of the ground floor
    win_w, win_h = int(rng.uniform(0.8, 1.4) * tpm), int(rng.uniform(1.2, 1.7) * tpm)
    offset = int(rng.uniform(0.3, 0.7) * sp)
    for top in range(ground - st, cornice - st // 2, -st):
        band = max(int(0.12 * tpm), 3)
        img[top + st - band:top + st] = (img[top + st - band:top + st] * 0.75).astype(np.uint8)
        y = top + int(0.35 * tpm)
        for x in range(offset, w - win_w - 4, sp):
            if y - 8 > cornice and rng.random() < 0.95:
                _window(img, rng, x, y, win_w, win_h, frame_colour, tpm)
    _ground_floor(img, rng, ground, tpm)
    return img


def _ground_floor(img: np.ndarray, rng: np.random.Generator, top: int, tpm: float) -> None:
    """Shop windows, a door, a sign band with lettering, posters and stains below row ``top``, in place."""
    h, w = img.shape[:2]
    sign_h = int(0.6 * tpm)
    sign = random_colour(rng, 10, 245)
    img[top:top + sign_h] = sign
    words = " ".join(str(rng.choice(list(_WORDS))) for _ in range(3)).upper()
    cv2.putText(img, words, (int(rng.uniform(0.2, 2.0) * tpm), top + int(0.48 * tpm)), cv2.FONT_HERSHEY_DUPLEX,
                0.45 * tpm / 30.0, mix_colours(sign, (255, 255, 255) if sum(sign) < 380 else (0, 0, 0), 0.85),
                max(int(0.05 * tpm), 1), cv2.LINE_AA)
    frame = random_colour(rng, 10, 120)
    x = int(rng.uniform(0.3, 1.5) * tpm)
    y0 = top + sign_h + int(0.3 * tpm)
    while x < w - int(1.5 * tpm):
        if rng.random() < 0.35:  # a door
            dw = int(rng.uniform(0.9, 1.4) * tpm)
            img[y0 - 4:h, x - 4:x + dw + 4] = frame
            with np.errstate(invalid="ignore"):  # wood() scales unfilled texels before filling them
                img[y0:h, x:x + dw] = wood(h - y0, dw, rng, max(dw // 4, 2), vertical=True)
            cv2.circle(img, (x + dw - int(0.15 * tpm), y0 + (h - y0) // 2), max(int(0.04 * tpm), 2),
                       (190, 200, 210), -1, cv2.LINE_AA)
            x += dw + int(rng.uniform(0.4, 1.5) * tpm)
        else:  # a shop window
            ww = int(rng.uniform(1.2, 3.0) * tpm)
            bottom = h - int(rng.uniform(0.3, 0.6) * tpm)
            _window(img, rng, x, y0, ww, bottom - y0, frame, tpm)
            shapes(img[y0:bottom, x:x + ww], rng, int(rng.integers(3, 10)), (int(0.1 * tpm), int(0.5 * tpm)),
                   alpha=(0.8, 1.0))  # goods on display
            x += ww + int(rng.uniform(0.5, 1.5) * tpm)
    notes(img, rng, int(rng.integers(1, 5)), (int(0.3 * tpm), int(0.6 * tpm)))  # posters
    stains = img[top + sign_h:]
    shapes(stains, rng, int(w / tpm), (int(0.1 * tpm), int(0.6 * tpm)), lambda r: random_colour(r, 0, 256),
           alpha=(0.2, 0.5))


def asphalt(h: int, w: int, rng: np.random.Generator, tpm: float) -> np.ndarray:
    """(h, w, 3) uint8 BGR asphalt at ``tpm`` texels per metre: grey with gravel grain, darker patches,
    repair seams, cracks and a few manhole covers."""
    img = base_surface(h, w, rng, (92, 95, 98), contrast=0.2, grain=0.18, largest=int(4 * tpm))
    for _ in range(int(h * w / tpm**2 / 30) + 1):  # patches of newer asphalt
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        pw, ph = int(rng.uniform(0.5, 3.0) * tpm), int(rng.uniform(0.5, 3.0) * tpm)
        img[y:y + ph, x:x + pw] = (img[y:y + ph, x:x + pw] * rng.uniform(0.6, 0.85)).astype(np.uint8)
    for _ in range(int(h * w / tpm**2 / 8) + 1):  # cracks
        steps = rng.normal(0, 0.15 * tpm, (int(rng.integers(4, 12)), 2)).cumsum(0)
        pts = (steps + (rng.integers(0, w), rng.integers(0, h))).astype(np.int32)
        cv2.polylines(img, [pts], False, (40, 42, 45), max(int(0.015 * tpm), 1), cv2.LINE_AA)
    for _ in range(int(rng.integers(0, 2))):  # a manhole
        x, y, r = int(rng.integers(0, w)), int(rng.integers(0, h)), int(0.3 * tpm)
        cv2.circle(img, (x, y), r, (55, 58, 60), -1, cv2.LINE_AA)
        for k in range(-r, r, max(int(0.06 * tpm), 2)):
            cv2.line(img, (x - r, y + k), (x + r, y + k), (85, 88, 90), 1, cv2.LINE_AA)
        cv2.circle(img, (x, y), r, (30, 30, 30), max(int(0.03 * tpm), 1), cv2.LINE_AA)
    return img


def paving(h: int, w: int, rng: np.random.Generator, tpm: float, slab: float = 0.5) -> np.ndarray:
    """(h, w, 3) uint8 BGR pavement of ``slab``-metre concrete slabs (each its own tint), grain, joints and
    stains, at ``tpm`` texels per metre."""
    s = max(int(slab * tpm), 4)
    rows, cols = -(-h // s), -(-w // s)
    tint = rng.uniform(0.8, 1.15, (rows, cols)).astype(np.float32)
    img = base_surface(h, w, rng, (165, 170, 172), contrast=0.1, grain=0.15, largest=s)
    f = cv2.resize(tint, (cols * s, rows * s), interpolation=cv2.INTER_NEAREST)[:h, :w]
    img = cv2.convertScaleAbs(img.astype(np.float32) * f[..., None])
    img[(np.arange(h) % s) < 2] = 90
    img[:, (np.arange(w) % s) < 2] = 90
    shapes(img, rng, int(h * w / tpm**2), (int(0.05 * tpm), int(0.4 * tpm)), lambda r: random_colour(r, 40, 160),
           alpha=(0.2, 0.5))
    return img
