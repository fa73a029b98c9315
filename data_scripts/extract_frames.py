#!/usr/bin/env python3
"""Extract frames of a video into an image folder slamkit reads (``folder:`` source layout).

    python data_scripts/extract_frames.py clip.mp4 data/clip --every 2 --max 300 [--width 960]

Writes ``OUT/NNNNNN.png`` and ``OUT/times.txt`` (one timestamp in seconds per image, from the video's frame
rate). slamkit's folder source times frames by ``fps`` (``open_folder(OUT, fps=VIDEO_FPS / EVERY)``); the
printed line gives that rate. Decoding uses OpenCV (a slamkit dependency); an unreadable video is a clear error (exit status 2).
A rerun replaces the frames.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


class ExtractError(Exception):
    pass


def extract_frames(video: str | Path, out: str | Path, every: int = 1, max_frames: int | None = None,
                   width: int | None = None, log=print) -> int:
    """Write every ``every``-th frame (at most ``max_frames``) of ``video`` to ``out``; returns the count."""
    import cv2

    video, out = Path(video), Path(out)
    if every < 1:
        raise ExtractError(f"--every must be >= 1 (got {every})")
    if not video.is_file():
        raise ExtractError(f"{video}: no such file")
    from slamkit.sources.base import plain_name

    with plain_name(video) as name:  # any bytes in the name (OpenCV crashes on a name that is not UTF-8)
        cap = cv2.VideoCapture(name)
    if not cap.isOpened():
        raise ExtractError(f"{video}: cannot be opened as a video (unknown format or codec)")
    fps = cap.get(cv2.CAP_PROP_FPS) or 30.0
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("[0-9][0-9][0-9][0-9][0-9][0-9].png"):
        old.unlink()
    times, i, n = [], 0, 0
    try:
        while max_frames is None or n < max_frames:
            ok, img = cap.read()
            if not ok:
                break
            if i % every == 0:
                if width and img.shape[1] != width:
                    h = round(img.shape[0] * width / img.shape[1])
                    img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
                ok, png = cv2.imencode(".png", img)  # written by Python: any bytes in the folder's name
                if not ok:
                    raise ExtractError(f"{video}: frame {i} cannot be encoded as PNG")
                try:
                    (out / f"{n:06d}.png").write_bytes(png.tobytes())
                except OSError as e:
                    raise ExtractError(f"{out}: cannot write images there ({e.strerror})") from None
                times.append(i / fps)
                n += 1
            i += 1
    finally:
        cap.release()
    if n == 0:
        raise ExtractError(f"{video}: no frame could be decoded")
    (out / "times.txt").write_text("".join(f"{t:.6f}\n" for t in times))
    log(f"{n} frames of {video} ({fps:.3g} fps, every {every}: {fps / every:.4g} fps) -> {out}/")
    return n


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("video")
    p.add_argument("out")
    p.add_argument("--every", type=int, default=1, help="keep every n-th frame")
    p.add_argument("--max", type=int, dest="max_frames", help="stop after this many frames")
    p.add_argument("--width", type=int, help="resize to this width (pixels)")
    args = p.parse_args(argv)
    try:
        extract_frames(args.video, args.out, args.every, args.max_frames, args.width)
    except ExtractError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
