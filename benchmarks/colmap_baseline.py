"""COLMAP's own incremental SfM, run through pycolmap on exactly the frames slamkit sees: the baseline.

Stages (each the pycolmap call it is named after, COLMAP's ``feature_extractor`` / ``sequential_matcher`` /
``mapper``):

1. ``write_images``: every frame of the :class:`~slamkit.sources.base.FrameSource` as a grey PNG
   (``NNNNNN.png`` = delivered frame index; undistorted to the pinhole camera when the source has distortion).
2. ``extract_features``: SIFT on the CPU, one shared PINHOLE camera with the source's known (fx, fy, cx, cy)
   (``CameraMode.SINGLE``).
3. ``match_sequential``: each image against the next ``overlap`` images (plus COLMAP's quadratic overlap),
   loop detection off (no vocabulary tree: it would download one), geometric verification.
4. ``incremental_mapping``: intrinsics held fixed (no focal, principal point or extra-parameter refinement),
   stopped when the whole run reaches ``max_total_s`` seconds (``IncrementalPipelineOptions.max_runtime_seconds``
   gets what is left after extraction and matching); a stopped run is reported with ``complete = False``.

The largest reconstruction gives the trajectory: image names map back to the source's timestamps, and
:func:`slamkit.eval.ate` (Sim(3)) scores it against the source's ground truth over the registered frames.

Results are cached hloc-style under ``benchmarks/cache/colmap/<name>-<key>/`` (``result.json``,
``trajectory_tum.txt``, ``database.db``, ``sparse/``): ``key`` hashes the configuration, the pycolmap
version, the camera and the frame list, so a changed setting or frame selection re-runs and an unchanged one
is read back in milliseconds. A run that was interrupted resumes: finished stages (features, matches) are
kept with their recorded times.

Usage::

    .venv/bin/python benchmarks/colmap_baseline.py ../shared/data/7scenes-redkitchen
    .venv/bin/python benchmarks/colmap_baseline.py ../shared/data/kitti-odometry --sequence 07
    .venv/bin/python benchmarks/colmap_baseline.py synthetic:sideways?frames=30 --conf fast --force
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

import cv2  # noqa: F401  (before pycolmap: the other order crashed in cv2.imwrite's zlib, "double free")
import pycolmap

pycolmap.logging.minloglevel = 2

from slamkit.eval import ate  # noqa: E402
from slamkit.io import atomic_write_text, read_tum, write_tum  # noqa: E402
from slamkit.sources import open_source  # noqa: E402
from slamkit.sources.base import FrameSource  # noqa: E402
from slamkit.types import Trajectory  # noqa: E402

BENCH_DIR = Path(__file__).resolve().parent
CACHE_DIR = BENCH_DIR / "cache" / "colmap"


@dataclass(frozen=True)
class ColmapConf:
    """Settings of the COLMAP baseline (everything that changes the result is part of the cache key)."""

    max_num_features: int = 8192
    """SIFT features per image (COLMAP's default 8192)."""
    overlap: int = 10
    """Sequential matching: each image is matched with the next ``overlap`` images."""
    quadratic_overlap: bool = False
    """Also match image i with i + 2^k (COLMAP's default is True; off here: +60 % matching time)."""
    max_total_s: int = 100 * 60
    """Wall-time budget of extraction + matching + mapping, seconds (-1: none). The mapper is stopped when it
    is used up (at least 60 s of mapping), and the run is then reported as incomplete."""
    num_threads: int = -1
    """Threads for extraction, matching and mapping (-1: all cores)."""
    random_seed: int = 0
    """Seed of the mapper's RANSAC (reproducible runs; -1 = random)."""

    def key(self) -> dict:
        d = asdict(self)
        d.pop("num_threads")  # does not change the result (beyond thread-scheduling noise)
        return d


CONFS: dict[str, ColmapConf] = {
    "default": ColmapConf(),
    "fast": ColmapConf(max_num_features=2048, overlap=5, max_total_s=15 * 60),
}
"""Named presets; ``default`` is COLMAP's own defaults with the overlap the comparison uses."""


@dataclass(frozen=True)
class ColmapResult:
    """Outcome of one baseline run (all times in seconds of wall-clock time; ATE in metres)."""

    sequence: str
    frames: int
    registered: int
    fraction_registered: float
    ate_rmse_m: float | None
    wall_time_s: float
    """extraction + matching + mapping (writing the PNGs is not counted)."""
    fps: float
    """frames / wall_time_s."""
    timings_s: dict
    """per stage: write_images, extract_features, match_sequential, incremental_mapping."""
    complete: bool
    """False when the mapper was stopped by ``max_total_s``: the numbers are then what it had reached."""
    num_models: int
    points3D: int
    mean_reprojection_error_px: float | None
    conf: dict
    key: str
    pycolmap_version: str
    date: str
    trajectory_path: str
    notes: str = ""
    registration_progress: list = field(default_factory=list)
    """[(seconds into mapping, images registered so far in the current model)], sampled."""
    cpu_time_s: float | None = None
    """process CPU time (all threads) of extraction + matching + mapping; None in results of older versions."""
    load_avg: list | None = None
    """1/5/15-minute load averages of the machine when the run ended."""

    def trajectory(self) -> Trajectory:
        return read_tum(self.trajectory_path)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2)

    @classmethod
    def from_json(cls, text: str) -> "ColmapResult":
        return cls(**json.loads(text))


# ------------------------------------------------------------------------------------------- cache key

def _frames_fingerprint(source: FrameSource) -> dict:
    c = source.camera
    return {
        "name": source.name,
        "n": len(source),
        "camera": [c.width, c.height, c.fx, c.fy, c.cx, c.cy, *c.dist],
        "frame_ids": hashlib.sha1(np.asarray(source.frame_ids, np.int64).tobytes()).hexdigest(),
        "timestamps": hashlib.sha1(np.round(np.asarray(source.timestamps), 6).tobytes()).hexdigest(),
        "paths": hashlib.sha1("\n".join(str(Path(p).name) for p in getattr(source, "paths", [])).encode())
        .hexdigest(),
    }


def cache_key(source: FrameSource, conf: ColmapConf) -> str:
    """12 hex digits identifying (configuration, pycolmap version, camera, frame list)."""
    blob = json.dumps({"conf": conf.key(), "pycolmap": pycolmap.__version__,
                       "frames": _frames_fingerprint(source)}, sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()[:12]


def _slug(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name).strip("_")[:60]


def cache_dir_for(source: FrameSource, conf: ColmapConf, cache_root: Path = CACHE_DIR) -> Path:
    return Path(cache_root) / f"{_slug(source.name)}-{cache_key(source, conf)}"


def load_cached(source: FrameSource, conf: ColmapConf = CONFS["default"],
                cache_root: Path = CACHE_DIR) -> ColmapResult | None:
    """The cached result for this source and configuration, or None."""
    p = cache_dir_for(source, conf, cache_root) / "result.json"
    if not p.is_file():
        return None
    return ColmapResult.from_json(p.read_text())


# ------------------------------------------------------------------------------------------- stages

def write_images(source: FrameSource, image_dir: Path) -> list[str]:
    """Write each delivered frame as ``image_dir/NNNNNN.png`` (grey, undistorted). Existing files are kept."""
    import cv2

    image_dir.mkdir(parents=True, exist_ok=True)
    cam = source.camera
    names = []
    for i in range(len(source)):
        name = f"{i:06d}.png"
        names.append(name)
        out = image_dir / name
        if out.is_file():
            continue
        gray = source[i].gray
        if cam.has_distortion:
            gray = cv2.undistort(gray, cam.K, np.asarray(cam.dist))
        tmp = out.with_suffix(".tmp.png")
        if not cv2.imwrite(str(tmp), gray):
            raise OSError(f"could not write {tmp}")
        os.replace(tmp, out)
    return names


def _stage_done(work: Path, stage: str) -> float | None:
    p = work / f"stage_{stage}.json"
    return json.loads(p.read_text())["seconds"] if p.is_file() else None


def _stage_cpu(work: Path, stage: str) -> float | None:
    p = work / f"stage_{stage}.json"
    return json.loads(p.read_text()).get("cpu_seconds") if p.is_file() else None


def _mark_stage(work: Path, stage: str, seconds: float, cpu_seconds: float | None = None) -> None:
    atomic_write_text(work / f"stage_{stage}.json", json.dumps({"seconds": seconds, "cpu_seconds": cpu_seconds}))


def _log(msg: str) -> None:
    print(f"[colmap {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def run_colmap(source: FrameSource, conf: ColmapConf = CONFS["default"], *, cache_root: Path = CACHE_DIR,
               force: bool = False, verbose: bool = True) -> ColmapResult:
    """Run (or read from the cache) COLMAP's incremental SfM on ``source`` and score it against its ground truth.

    ``force``: discard a cached result and all intermediate files and run from scratch.
    """
    log = _log if verbose else (lambda msg: None)
    work = cache_dir_for(source, conf, cache_root)
    if force and work.exists():
        shutil.rmtree(work)
    cached = load_cached(source, conf, cache_root)
    if cached is not None:
        log(f"{source.name}: cached result in {work}")
        return cached
    work.mkdir(parents=True, exist_ok=True)
    atomic_write_text(work / "settings.json", json.dumps(
        {"conf": asdict(conf), "pycolmap": pycolmap.__version__, "frames": _frames_fingerprint(source)}, indent=2))
    image_dir, db_path, sparse_dir = work / "images", work / "database.db", work / "sparse"
    timings: dict[str, float] = {}
    cam = source.camera

    t0 = time.perf_counter()
    names = write_images(source, image_dir)
    timings["write_images"] = time.perf_counter() - t0
    log(f"{source.name}: {len(names)} images in {image_dir} ({timings['write_images']:.1f} s)")

    # -- SIFT extraction, one shared PINHOLE camera with the known intrinsics
    done = _stage_done(work, "extract_features")
    if done is None:
        if db_path.exists():  # a partial database from an interrupted extraction: start it again
            db_path.unlink()
        reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE",
                                             camera_params=f"{cam.fx},{cam.fy},{cam.cx},{cam.cy}")
        extraction = pycolmap.FeatureExtractionOptions(num_threads=conf.num_threads, use_gpu=False)
        extraction.sift.max_num_features = conf.max_num_features
        log(f"extract_features: SIFT (max {conf.max_num_features}) on {len(names)} images, CPU")
        t0, c0 = time.perf_counter(), time.process_time()
        pycolmap.extract_features(db_path, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu)
        done = time.perf_counter() - t0
        _mark_stage(work, "extract_features", done, time.process_time() - c0)
    timings["extract_features"] = done
    log(f"extract_features: {done:.1f} s")

    # -- sequential matching, no loop detection (it needs a vocabulary tree)
    done = _stage_done(work, "match_sequential")
    if done is None:
        pairing = pycolmap.SequentialPairingOptions(overlap=conf.overlap, quadratic_overlap=conf.quadratic_overlap,
                                                    loop_detection=False, num_threads=conf.num_threads)
        matching = pycolmap.FeatureMatchingOptions(num_threads=conf.num_threads, use_gpu=False)
        log(f"match_sequential: overlap {conf.overlap}, quadratic {conf.quadratic_overlap}, no loop detection")
        t0, c0 = time.perf_counter(), time.process_time()
        # resumable: COLMAP skips pairs already in the database, so an interrupted run adds the time it had
        before = json.loads((work / "match_partial.json").read_text())["seconds"] \
            if (work / "match_partial.json").is_file() else 0.0
        atomic_write_text(work / "match_partial.json", json.dumps({"seconds": before, "started": time.time()}))
        pycolmap.match_sequential(db_path, matching_options=matching, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
        done = before + time.perf_counter() - t0
        _mark_stage(work, "match_sequential", done, None if before else time.process_time() - c0)
    timings["match_sequential"] = done
    log(f"match_sequential: {done:.1f} s")

    # -- incremental mapping, intrinsics fixed
    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.mapper.abs_pose_refine_focal_length = False
    opts.mapper.abs_pose_refine_extra_params = False
    opts.num_threads = conf.num_threads
    opts.random_seed = conf.random_seed
    map_cap = -1 if conf.max_total_s < 0 else \
        max(60, int(conf.max_total_s - timings["extract_features"] - timings["match_sequential"]))
    opts.max_runtime_seconds = map_cap
    progress: list[tuple[float, int]] = []
    t_map, c_map = time.perf_counter(), time.process_time()
    count = [0]

    def on_next_image() -> None:  # called by the mapper after each registration
        count[0] += 1
        if count[0] % 10 == 0:
            progress.append((round(time.perf_counter() - t_map, 1), count[0] + 2))
            if verbose and count[0] % 50 == 0:
                log(f"incremental_mapping: ~{count[0] + 2} registered after {progress[-1][0]:.0f} s")

    def on_initial_pair() -> None:
        count[0] = 0
        progress.append((round(time.perf_counter() - t_map, 1), 2))

    if sparse_dir.exists():
        shutil.rmtree(sparse_dir)
    sparse_dir.mkdir(parents=True)
    log(f"incremental_mapping: fixed intrinsics, cap {map_cap} s")
    models = pycolmap.incremental_mapping(db_path, image_dir, sparse_dir, options=opts,
                                          initial_image_pair_callback=on_initial_pair,
                                          next_image_callback=on_next_image)
    timings["incremental_mapping"] = time.perf_counter() - t_map
    cpu_parts = [_stage_cpu(work, "extract_features"), _stage_cpu(work, "match_sequential"),
                 time.process_time() - c_map]
    complete = map_cap < 0 or timings["incremental_mapping"] < map_cap - 1
    log(f"incremental_mapping: {timings['incremental_mapping']:.1f} s, {len(models)} model(s)"
        + ("" if complete else " (stopped at the time cap)"))

    # -- largest model -> trajectory on the source's timestamps
    traj_path = work / "trajectory_tum.txt"
    notes = []
    if models:
        best_idx, rec = max(models.items(), key=lambda kv: kv[1].num_reg_images())
        rows = []
        for image in rec.images.values():
            if not image.has_pose:
                continue
            i = int(Path(image.name).stem)
            T = np.eye(4)
            T[:3, :] = image.cam_from_world().inverse().matrix()
            rows.append((float(source.timestamps[i]), T))
        rows.sort(key=lambda r: r[0])
        traj = Trajectory(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]).reshape(-1, 4, 4))
        points3D = rec.num_points3D()
        mre = float(rec.compute_mean_reprojection_error())
        (sparse_dir / "largest").write_text(f"{best_idx}\n")
        if len(models) > 1:
            notes.append("model sizes: " + ", ".join(str(m.num_reg_images()) for m in models.values()))
    else:
        traj, points3D, mre = Trajectory(np.zeros(0), np.zeros((0, 4, 4))), 0, None
        notes.append("no reconstruction")
    write_tum(traj_path, traj)

    ate_rmse = None
    gt = source.ground_truth()
    if gt is not None and len(traj) >= 3:
        ate_rmse = float(ate(gt, traj, align="sim3").rmse)
    wall = timings["extract_features"] + timings["match_sequential"] + timings["incremental_mapping"]
    result = ColmapResult(
        sequence=source.name, frames=len(source), registered=len(traj),
        fraction_registered=len(traj) / len(source), ate_rmse_m=ate_rmse, wall_time_s=wall,
        fps=len(source) / wall, timings_s=timings, complete=complete, num_models=len(models),
        points3D=points3D, mean_reprojection_error_px=mre, conf=asdict(conf), key=cache_key(source, conf),
        pycolmap_version=pycolmap.__version__, date=time.strftime("%Y-%m-%d %H:%M"),
        trajectory_path=str(traj_path), notes="; ".join(notes), registration_progress=progress,
        cpu_time_s=None if None in cpu_parts else float(sum(cpu_parts)), load_avg=list(os.getloadavg()),
    )
    atomic_write_text(work / "result.json", result.to_json())
    log(f"{source.name}: {result.registered}/{result.frames} registered, ATE "
        f"{'n/a' if ate_rmse is None else f'{ate_rmse:.4f} m'}, {wall:.0f} s ({result.fps:.2f} frames/s)")
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", help="dataset path or spec (as slamkit.sources.open_source takes)")
    ap.add_argument("--sequence", help="KITTI sequence, e.g. 07")
    ap.add_argument("--max-frames", type=int)
    ap.add_argument("--frame-skip", type=int, default=1)
    ap.add_argument("--conf", default="default", choices=sorted(CONFS))
    ap.add_argument("--max-total-s", type=int, help="override the run's time budget (seconds; -1: none)")
    ap.add_argument("--threads", type=int, help="override num_threads")
    ap.add_argument("--force", action="store_true", help="ignore and replace the cached result")
    ap.add_argument("--cache", type=Path, default=CACHE_DIR)
    args = ap.parse_args(argv)
    kw = {"sequence": args.sequence} if args.sequence else {}
    source = open_source(args.source, frame_skip=args.frame_skip, max_frames=args.max_frames, **kw)
    conf = CONFS[args.conf]
    if args.max_total_s is not None:
        conf = replace(conf, max_total_s=args.max_total_s)
    if args.threads is not None:
        conf = replace(conf, num_threads=args.threads)
    r = run_colmap(source, conf, cache_root=args.cache, force=args.force)
    print(json.dumps({k: v for k, v in asdict(r).items() if k != "registration_progress"}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
