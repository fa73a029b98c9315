"""What fingerprinting frames costs (issue 50): hashing each frame when it is read, and a resume's proof.

1. read time: each frame of a source read as a run reads it (``source[i]``: file read, decoded, converted), and
   the part of it that is the SHA-256 of the bytes (``Fingerprint.of_file`` on the bytes already in memory) —
   per frame, in milliseconds;
2. resume: re-measuring N processed frames of an image folder against their fingerprints
   (:func:`slamkit.io.fingerprint.changed`, as ``Slam.resume`` does for every processed frame) — the files
   read and hashed, nothing decoded; N = 1,000 by default, the folder's frames repeated (hard links) to reach it;
3. a video: the SHA-256 of each decoded frame's pixels (what the fingerprint of a video frame is), and the
   resume check of its frames (each decoded again).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_fingerprints.py \\
        --images ../shared/data/7scenes-redkitchen --video ../shared/data/video/test_kitti984.mp4 \\
        --csv benchmarks/fingerprints.csv

Times are wall-clock medians over the frames (page cache warm: the files were read once before), on whatever
else the machine is doing; the table says so.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slamkit.io.fingerprint import changed  # noqa: E402
from slamkit.sources import open_source  # noqa: E402
from slamkit.sources.base import ImageListSource  # noqa: E402
from slamkit.types import Fingerprint  # noqa: E402


def _ms(times: list[float]) -> float:
    return 1000.0 * float(np.median(times))


def read_costs(source, frames: int) -> dict:
    """Median ms per frame: reading a frame (``source[i]``), and hashing its bytes alone."""
    n = min(frames, len(source))
    for i in range(n):  # warm the page cache: the run read them too
        source[i]
    read, hashed, sizes = [], [], []
    for i in range(n):
        t = time.perf_counter()
        frame = source[i]
        read.append(time.perf_counter() - t)
        if isinstance(source, ImageListSource):
            data = Path(source.paths[i]).read_bytes()
        else:  # a video: the decoded pixels
            data = np.ascontiguousarray(frame.color[..., ::-1])
        t = time.perf_counter()
        Fingerprint.of_bytes("x", data, 1, 1)
        hashed.append(time.perf_counter() - t)
        sizes.append(memoryview(data).nbytes)
    return {"frames": n, "read_ms": _ms(read), "sha256_ms": _ms(hashed), "kib_hashed": float(np.median(sizes)) / 1024}


def resume_cost(source: ImageListSource, frames: int) -> dict:
    """Seconds to re-measure ``frames`` frames against their read-time fingerprints (every one unchanged)."""
    with tempfile.TemporaryDirectory(prefix="slamkit-bench-fp-") as tmp:
        paths = []
        for k in range(frames):  # the folder's files repeated: hard links (copies where links cannot be made)
            src = Path(source.paths[k % len(source)])
            dst = Path(tmp) / f"{k:06d}{src.suffix}"
            try:
                os.link(src, dst)
            except OSError:
                dst.write_bytes(src.read_bytes())
            paths.append(dst)
        big = ImageListSource("bench", source.camera, paths, np.arange(frames) / 30.0, np.arange(frames))
        recorded = [big[i].fingerprint for i in range(frames)]  # as the run read them (also warms the cache)
        t = time.perf_counter()
        bad = [i for i in range(frames) if changed(recorded[i], big, i)]
        seconds = time.perf_counter() - t
        mib = sum(p.stat().st_size for p in paths) / 2**20
    assert not bad, bad
    return {"frames": frames, "seconds": seconds, "ms_per_frame": 1000 * seconds / frames, "mib_read": mib}


def video_resume_cost(source, frames: int) -> dict:
    """Seconds to re-measure the first ``frames`` frames of a video (decoded again, forward) against theirs."""
    n = min(frames, len(source))
    recorded = [source[i].fingerprint for i in range(n)]
    t = time.perf_counter()
    bad = [i for i in range(n) if changed(recorded[i], source, i)]
    seconds = time.perf_counter() - t
    assert not bad, bad
    return {"frames": n, "seconds": seconds, "ms_per_frame": 1000 * seconds / n,
            "mib_read": source.path.stat().st_size / 2**20 * n / len(source)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", default="default",
                    help="an image source (folder or dataset): read-time and resume cost")
    ap.add_argument("--video", default=None, help="a video file: the per-frame hash of its decoded frames")
    ap.add_argument("--frames", type=int, default=200, help="frames timed for the read-time cost")
    ap.add_argument("--resume-frames", type=int, default=1000, help="frames of the resume check")
    ap.add_argument("--csv", default=None, help="write the table as CSV here")
    args = ap.parse_args(argv)
    rows = []
    src = open_source(args.images)
    r = read_costs(src, args.frames)
    rows.append({"what": f"read a frame ({src.name})", **r})
    if isinstance(src, ImageListSource):
        rows.append({"what": f"resume check ({src.name} files, repeated)", **resume_cost(src, args.resume_frames)})
    if args.video:
        v = open_source(args.video)
        rows.append({"what": f"read a frame ({v.name})", **read_costs(v, args.frames)})
        rows.append({"what": f"resume check ({v.name}, decoded again)", **video_resume_cost(v, args.resume_frames)})
    keys = ["what", "frames", "read_ms", "sha256_ms", "kib_hashed", "seconds", "ms_per_frame", "mib_read"]
    print(" | ".join(keys))
    for row in rows:
        print(" | ".join(f"{row[k]:.3f}" if isinstance(row.get(k), float) else str(row.get(k, "")) for k in keys))
    print(f"(wall-clock medians, page cache warm, load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, keys)
            w.writeheader()
            w.writerows({k: row.get(k, "") for k in keys} for row in rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
