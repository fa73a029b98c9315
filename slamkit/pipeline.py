"""Slam: owns the state, composes the stages, steps one frame per call. Imports no UI.

One frame: extract features -> (initializing: Initializer.step) | Tracker.step against the local map ->
KeyframeSelector.step (flow score, tracked matches) -> [keyframe] Mapper.step -> BundleAdjuster.step ->
StepResult -> callbacks. Every frame's pose is stored relative to its reference keyframe, so frames follow
their keyframe through bundle adjustment, and normalization only rescales those relative translations.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .camera import Intrinsics
from .config import SlamConfig
from .errors import CalibrationError, ConfigError, ImageReadError
from .features import FrameFeatures, create_extractor, create_matcher, image_signature
from .map import SlamMap
from .sources.base import FrameSource
from .stages.ba import BundleAdjuster
from .stages.flow import flow_score
from .stages.initializer import Initializer
from .stages.keyframes import KeyframeDecision, KeyframeSelector, keyframe_redundancy, median_parallax_deg
from .stages.mapper import Mapper
from .stages.tracker import LocalMap, Tracker
from .types import Frame, Trajectory

RETRACK_BELOW_KEYFRAMES = 5
"""Frames tracked while the map had fewer keyframes are tracked again against the final map (finish)."""

# frame statuses
INITIALIZING, INITIALIZED, TRACKED, LOST, SKIPPED = "initializing", "initialized", "tracked", "lost", "skipped"
ERROR = "error"
"""A stage raised while processing the frame (``Slam.errors`` has the message); see :meth:`Slam.step`."""


@dataclass(frozen=True, eq=False)
class StepResult:
    """What happened to one frame. ``cam_from_world`` is (4, 4) in the frame's segment, or None."""

    frame_index: int
    frame_id: int
    timestamp: float
    status: str
    message: str
    segment: int
    is_keyframe: bool = False
    keyframe_reason: str = ""
    flow: float = float("nan")
    matches: int = 0
    """Tracked matches to the last keyframe (the number compared with min_tracked_matches)."""
    inliers: int = 0
    """Pose inliers (2D-3D) of the frame."""
    cam_from_world: np.ndarray | None = None
    num_keyframes: int = 0
    num_points: int = 0
    ba: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    posed_frames: tuple[int, ...] = ()
    """Frames that received a pose with this step (the initialization window on success)."""
    relocalized: bool = False
    """The local map lost the frame and relocalization against all keyframes found it."""
    degenerate: bool = False
    """Degenerate motion (e.g. pure rotation): a keyframe was due but refused for too little parallax to
    the last keyframe; the frame is tracked by PnP only (``keyframe_reason`` gives the numbers)."""
    parallax_deg: float = float("nan")
    """Median parallax (triangulation angle, rotation removed) of the tracked matches to the last keyframe."""

    @property
    def has_pose(self) -> bool:
        return self.cam_from_world is not None

    @property
    def world_from_cam(self) -> np.ndarray | None:
        return None if self.cam_from_world is None else np.linalg.inv(self.cam_from_world)

    def __str__(self) -> str:
        kf = f"KEYFRAME ({self.keyframe_reason})" if self.is_keyframe else (
            f"no keyframe ({self.keyframe_reason})" if self.keyframe_reason else "")
        flow = "" if np.isnan(self.flow) else f" flow={self.flow:.3f}"
        ms = sum(self.timings.values()) * 1e3
        return (f"frame {self.frame_index} [{self.status}]{flow} matches={self.matches} inliers={self.inliers} "
                f"kf={self.num_keyframes} pts={self.num_points} {ms:.0f} ms {kf} {self.message}".rstrip())


@dataclass(eq=False)
class FrameRecord:
    """Pose bookkeeping of one frame: pose = rel_pose (cam_from_refcam) @ pose of the reference keyframe."""

    index: int
    frame_id: int
    timestamp: float
    status: str
    segment: int = -1
    ref_image_id: int = -1
    rel_pose: np.ndarray | None = None
    keyframe_image_id: int = -1
    degenerate: bool = False
    unreadable: str = ""
    """Why the source could not deliver the frame (corrupt file, undecodable video frame, another image
    size), when it was skipped for that."""


@dataclass(eq=False)
class Segment:
    """One map segment: its map, the frames posed in it, and the features of the frames posed at
    initialization (re-tracked against the final map by ``Slam.finish``)."""

    id: int
    slam_map: SlamMap
    frames: list[int] = field(default_factory=list)
    initial_frames: list[FrameFeatures] = field(default_factory=list)
    signatures: dict[int, np.ndarray] = field(default_factory=dict)
    """Global image signature of each keyframe (image id), for relocalization."""
    relocalizations: int = 0
    keyframes_culled: int = 0
    """Keyframes removed from the map as redundant (``keyframes.cull_redundant``)."""


Callback = Callable[["Slam", StepResult], None]


class Slam:
    """Monocular SLAM over a frame source, one frame per :meth:`step`.

    >>> slam = Slam(open_source("default"), SlamConfig())      # doctest: +SKIP
    >>> for result in slam: print(result)                      # doctest: +SKIP
    >>> slam.save("runs/demo")                                 # doctest: +SKIP
    """

    def __init__(self, source: FrameSource | str, config: SlamConfig | str | None = None,
                 callbacks: list[Callback] | None = None):
        if config is None:
            config = SlamConfig()
        elif isinstance(config, str):
            config = SlamConfig.preset(config)
        self.config = config.validate()
        self.source_spec = str(source) if isinstance(source, (str, Path)) else None
        """How the source was opened (a path or spec), recorded in sessions so ``Slam.resume`` can reopen it."""
        if isinstance(source, (str, Path)):
            from .sources import open_source

            source = open_source(str(source))
        self.source = source
        self.callbacks: list[Callback] = list(callbacks or [])
        self.reset()

    # ----------------------------------------------------------------- lifecycle
    def reset(self, config: SlamConfig | None = None) -> None:
        """Start over (with a new config if given): empty map, first frame next."""
        self._drain_prefetch(getattr(self, "_prefetched", None))  # before the stages it uses are replaced
        self._prefetched: tuple | None = None
        """(cursor, Future of :meth:`_load`) of the frame being read ahead (``config.prefetch``)."""
        self._prefetcher = getattr(self, "_prefetcher", None)
        if config is not None:
            self.config = config.validate()
        c = self.config
        self.camera = self.source.camera
        if c.camera:  # the user's intrinsics instead of the source's (or its guess)
            self.camera = Intrinsics.parse(c.camera, self.camera.width, self.camera.height)
        self.extractor = create_extractor(c.features, **c.extractor_options())
        matcher = None if c.matcher == "nn" else create_matcher(c.matcher, **c.matcher_options())  # "nn": per stage
        self.tracker = Tracker(_seeded(c.tracker, c.seed))
        self.selector = KeyframeSelector(c.keyframes)
        self.mapper = Mapper(c.mapper, matcher)
        self.bundle_adjuster = BundleAdjuster(c.ba)
        self.initializer = Initializer(self.camera, _seeded(c.initializer, c.seed), matcher)
        self.indices = np.arange(0, len(self.source), c.frame_skip)[: c.max_frames]
        self.records: list[FrameRecord] = []
        self.segments: list[Segment] = []
        self.segment: Segment | None = None
        self.local_map: LocalMap | None = None
        self.last_keyframe: int = -1
        self._points_at_last_keyframe = 0
        self._consecutive_lost = 0
        self._last_ids: np.ndarray | None = None
        self._cursor = 0
        self.timings: dict[str, float] = {}
        self.wall_time = 0.0
        self.cpu_time = 0.0
        self.last_frame: Frame | None = None
        self.last_features: FrameFeatures | None = None
        self.last_result: StepResult | None = None
        self.finished = False
        self._init_message = ""
        self.errors: dict[int, str] = {}
        """Frame index -> the exception a stage raised on it (those frames have status ``"error"``)."""

    @property
    def done(self) -> bool:
        return self._cursor >= len(self.indices)

    def __len__(self) -> int:
        return len(self.indices)

    def __iter__(self) -> Iterator[StepResult]:
        while not self.done:
            yield self.step()

    def run(self, max_steps: int | None = None) -> list[StepResult]:
        """Step until the end (or ``max_steps``) and finish; returns the step results."""
        out = []
        while not self.done and (max_steps is None or len(out) < max_steps):
            out.append(self.step())
        if self.done:
            self.finish()
        return out

    # ----------------------------------------------------------------- one frame
    def step(self) -> StepResult:
        """Process the next frame and return what happened to it.

        Interruptions never leave half a frame: Ctrl-C (SIGINT, "interrupt kernel") during a step is held
        back until the frame is done, then raises KeyboardInterrupt. An exception in a stage propagates (with a
        note naming the frame) after the frame is marked ``"error"`` without a pose (message in
        :attr:`errors`); every earlier frame is kept, :meth:`save` works, and ``step()`` goes on with the next
        frame. Like COLMAP's mapper, a failure stops the loop rather than being hidden in a status.
        """
        if self.done:
            raise StopIteration("no frames left")
        from .session import deferred_interrupt

        cursor, num_records, last_result = self._cursor, len(self.records), self.last_result
        with deferred_interrupt():
            try:
                return self._step()
            except BaseException as e:
                self._step_failed(e, cursor, num_records, last_result)
                raise

    def _step_failed(self, e: BaseException, cursor: int, num_records: int, last_result) -> None:
        """Leave the state of whole frames after ``_step`` raised: the frame is consumed and marked "error"
        without a pose (unless it already became a keyframe, or only a callback failed after it was done).
        An interrupt is no failure: a frame it cut short before the frame changed any state is given back (the
        next step or a resume processes it), and a frame whose callback it cut short stays as it was."""
        untouched, done = len(self.records) == num_records, self.last_result is not last_result
        if isinstance(e, KeyboardInterrupt) and (untouched or done):
            self._cursor = cursor if untouched else self._cursor
            e.add_note(f"slamkit: interrupted at frame {cursor}; earlier frames are kept, save() works")
            return
        self._cursor = max(self._cursor, cursor + 1)
        if len(self.records) == num_records:  # failed before its record existed (reading, features)
            i = int(self.indices[cursor])
            ids, ts = getattr(self.source, "frame_ids", None), getattr(self.source, "timestamps", None)
            self.records.append(FrameRecord(cursor, int(ids[i]) if ids is not None else i,
                                            float(ts[i]) if ts is not None else float("nan"), ERROR))
        rec = self.records[num_records]
        done = self.last_result is not last_result  # the step finished; a callback raised
        if not done:
            if rec.rel_pose is not None and rec.keyframe_image_id < 0:
                if 0 <= rec.segment < len(self.segments) and rec.index in self.segments[rec.segment].frames:
                    self.segments[rec.segment].frames.remove(rec.index)
                rec.rel_pose, rec.ref_image_id, rec.segment = None, -1, -1
            rec.status = ERROR
        self.errors[rec.index] = f"{type(e).__name__}: {e}" + (" (in a callback)" if done else "")
        e.add_note(f"slamkit: while processing frame {rec.index} (frame id {rec.frame_id})"
                   + (" in a callback, after the frame was processed" if done else "")
                   + "; earlier frames are kept, save() works, step() continues with the next frame")

    def _step(self) -> StepResult:
        t_start = time.perf_counter()
        cpu_start = time.process_time()
        timings: dict[str, float] = {}
        loaded = self._next_frame()
        if isinstance(loaded[0], (ImageReadError, CalibrationError)):  # a bad frame is skipped with its reason
            return self._skip_unreadable(loaded[0], timings, t_start, cpu_start)
        frame, ff, timings["read"], timings["features"] = loaded
        self._cursor += 1
        self.last_frame, self.last_features = frame, ff
        record = FrameRecord(frame.index, frame.frame_id, frame.timestamp, LOST)
        self.records.append(record)
        if self.segment is None:
            result = self._initialize(ff, record, timings)
        else:
            result = self._track(ff, record, timings)
        self.wall_time += time.perf_counter() - t_start
        self.cpu_time += time.process_time() - cpu_start
        for k, v in timings.items():
            self.timings[k] = self.timings.get(k, 0.0) + v
        self.last_result = result
        for cb in self.callbacks:
            cb(self, result)
        return result

    def _load(self, cursor: int) -> tuple:
        """Read frame ``cursor`` and extract its features: (frame, features, read s, features s), or
        (the source's ImageReadError / CalibrationError, read s) for a frame it cannot deliver."""
        t = time.perf_counter()
        try:
            frame = self.source[int(self.indices[cursor])]
        except (ImageReadError, CalibrationError) as e:
            return e, time.perf_counter() - t
        frame = _reindexed(frame, cursor)
        t_read = time.perf_counter() - t
        t = time.perf_counter()
        ff = self._frame_features(frame)
        return frame, ff, t_read, time.perf_counter() - t

    def _next_frame(self) -> tuple:
        """:meth:`_load` of the frame at the cursor, done ahead on the prefetch thread when
        ``config.prefetch`` (then the next frame's load starts here, before this one is processed)."""
        cursor, job = self._cursor, self._prefetched
        self._prefetched = None
        if job is not None and job[0] == cursor:
            loaded = job[1].result()  # the worker's exception, if any, is raised here
        else:
            self._drain_prefetch(job)
            loaded = self._load(cursor)
        if self.config.prefetch and cursor + 1 < len(self.indices):
            if self._prefetcher is None:
                from concurrent.futures import ThreadPoolExecutor

                self._prefetcher = ThreadPoolExecutor(1, thread_name_prefix="slamkit-prefetch")
            self._prefetched = (cursor + 1, self._prefetcher.submit(self._load, cursor + 1))
        return loaded

    @staticmethod
    def _drain_prefetch(job) -> None:
        """Wait for a prefetch that will not be used (the source is read by one thread at a time)."""
        if job is not None:
            try:
                job[1].result()
            except Exception:  # noqa: BLE001 - the frame is read again when it is due
                pass

    def _skip_unreadable(self, error: Exception, timings: dict, t_start: float, cpu_start: float) -> StepResult:
        """A frame the source cannot deliver: status "skipped", the source's message (file, frame) in the
        result and in ``summary()["unreadable_frames"]``; the map and the tracking state are untouched."""
        i = int(self.indices[self._cursor])
        record = FrameRecord(self._cursor, int(self.source.frame_ids[i]), float(self.source.timestamps[i]),
                             SKIPPED, unreadable=str(error))
        self._cursor += 1
        self.records.append(record)
        timings["read"] = time.perf_counter() - t_start
        result = self._result(record, SKIPPED, f"bad frame skipped: {error}", timings)
        self.wall_time += time.perf_counter() - t_start
        self.cpu_time += time.process_time() - cpu_start
        self.timings["read"] = self.timings.get("read", 0.0) + timings["read"]
        self.last_result = result
        for cb in self.callbacks:
            cb(self, result)
        return result

    def _frame_features(self, frame: Frame) -> FrameFeatures:
        feats = self.extractor.extract(frame.gray)
        kp = self.camera.undistort_points(feats.keypoints)
        h, w = frame.gray.shape
        ij = np.clip(np.round(feats.keypoints).astype(np.int64), 0, [w - 1, h - 1])
        colors = frame.color[ij[:, 1], ij[:, 0]]
        return FrameFeatures(frame.index, frame.frame_id, frame.timestamp, feats, kp, colors,
                             signature=image_signature(frame.gray))

    def _thumbnail(self, frame_index: int) -> np.ndarray | None:
        if self.config.thumbnail_width <= 0 or self.last_frame is None or self.last_frame.index != frame_index:
            return None
        import cv2

        img = self.last_frame.color
        scale = self.config.thumbnail_width / img.shape[1]
        return cv2.resize(img, (self.config.thumbnail_width, max(1, int(img.shape[0] * scale))),
                          interpolation=cv2.INTER_AREA)

    # ----------------------------------------------------------------- initialization
    def _initialize(self, ff: FrameFeatures, record: FrameRecord, timings: dict) -> StepResult:
        t = time.perf_counter()
        if len(ff) < 8:
            record.status = SKIPPED
            timings["initialize"] = time.perf_counter() - t
            return self._result(record, SKIPPED, f"{len(ff)} keypoints: featureless frame skipped", timings)
        res = self.initializer.step(ff)
        timings["initialize"] = time.perf_counter() - t
        if not res.initialized:
            record.status = INITIALIZING
            if res.status == "failed":
                self._init_message = res.reason
            return self._result(record, INITIALIZING, res.reason, timings)
        # a new segment with the two initial keyframes; the rest of the window is tracked below
        seg = Segment(len(self.segments), res.slam_map,
                      initial_frames=[f for f in res.frames if f.index < res.second and f.index != res.first])
        self.segments.append(seg)
        self.segment = seg
        by_index = {f.index: f for f in res.frames}
        for image_id, kf in sorted(res.slam_map.keyframes.items()):
            if by_index.get(kf.frame_index) is not None and by_index[kf.frame_index].signature is not None:
                seg.signatures[image_id] = by_index[kf.frame_index].signature
            rec = self.records[kf.frame_index]
            self._set_pose(rec, image_id, np.eye(4), TRACKED)
            rec.keyframe_image_id = image_id
        self.last_keyframe = max(res.slam_map.keyframes)
        self._points_at_last_keyframe = res.slam_map.reconstruction.image(self.last_keyframe).num_points3D
        self.local_map = self._local_map(res.slam_map, self.last_keyframe)
        self._consecutive_lost = 0
        posed, message = self._track_window(res, timings)
        record.status = record.status if record.rel_pose is not None else LOST
        return self._result(record, INITIALIZED, res.reason + message, timings, posed_frames=tuple(sorted(posed)),
                            is_keyframe=record.keyframe_image_id > 0)

    def _track_window(self, res, timings: dict) -> tuple[list[int], str]:
        """The rest of the initialization window. Frames between the initial pair, then those before it, are
        posed against the two-keyframe map (each predicted by its already-posed neighbour). Frames after
        the pair go through tracking as if they came now, keyframes and mapping included: the map grows up
        to the current frame (with fast motion a map of the pair alone may no longer be in view). Returns
        the posed frames and a note for the result's message ("" or why the new map was lost again)."""
        t = time.perf_counter()
        frames = sorted(res.frames, key=lambda f: f.index)
        camera = res.slam_map.pycolmap_camera
        posed = [res.first, res.second]
        between = [f for f in frames if res.first < f.index < res.second]
        before = [f for f in reversed(frames) if f.index < res.first]
        for seq in (between, before):
            neighbour = self.pose_of(self.records[res.first])
            for f in seq:
                tr = self.tracker.step(f, self.local_map, camera, neighbour)
                rec = self.records[f.index]
                if tr.tracked:
                    self._set_pose(rec, self.last_keyframe, tr.cam_from_world, TRACKED, absolute=True)
                    posed.append(f.index)
                    neighbour = tr.cam_from_world
                else:
                    rec.status = LOST
        self.segment.frames.sort()
        timings["track"] = timings.get("track", 0.0) + time.perf_counter() - t
        seg = self.segment
        for f in (f for f in frames if f.index > res.second):
            step_timings: dict = {}
            result = self._track(f, self.records[f.index], step_timings)
            for k, v in step_timings.items():
                timings[k] = timings.get(k, 0.0) + v
            if result.has_pose:
                posed.append(f.index)
            if self.segment is not seg:  # lost again at once: the next frame starts a new window
                return posed, f"; frame {f.index}: {result.message}"
        seg.frames.sort()
        return posed, ""

    # ----------------------------------------------------------------- tracking
    def _track(self, ff: FrameFeatures, record: FrameRecord, timings: dict) -> StepResult:
        seg = self.segment
        slam_map = seg.slam_map
        t = time.perf_counter()
        if len(ff) < self.config.tracker.min_inliers:
            record.status = SKIPPED
            timings["track"] = time.perf_counter() - t
            return self._result(record, SKIPPED, f"{len(ff)} keypoints: featureless frame skipped", timings)
        tr = self.tracker.step(ff, self.local_map, slam_map.pycolmap_camera, self._predict(record.index),
                               self._last_ids)
        relocalized = False
        if not tr.tracked and self.config.relocalization_candidates > 0:
            t_reloc = time.perf_counter()
            found = self._relocalize(ff)
            timings["relocalize"] = time.perf_counter() - t_reloc
            if found is not None:
                tr, relocalized = found, True
        timings["track"] = time.perf_counter() - t - timings.get("relocalize", 0.0)
        if not tr.tracked:
            record.status = LOST
            self._last_ids = None
            self._consecutive_lost += 1
            msg = tr.reason
            if self._consecutive_lost >= self.config.max_lost_frames or len(self.local_map) == 0:
                msg += f"; {self._consecutive_lost} frames lost: starting a new map segment"
                self._end_segment()  # resets the count
            return self._result(record, LOST, msg, timings, matches=0, inliers=tr.num_inliers)
        self._consecutive_lost = 0
        self._last_ids = tr.point3D_ids
        self._set_pose(record, self.last_keyframe, tr.cam_from_world, TRACKED, absolute=True)
        if slam_map.num_keyframes < RETRACK_BELOW_KEYFRAMES:  # young map: track again in finish()
            seg.initial_frames.append(ff)
        t = time.perf_counter()
        flow = flow_score(tr.ref_xy, tr.cur_xy, self.camera.fx, self.camera.fy)
        parallax, rotation = median_parallax_deg(tr.ref_xy, tr.cur_xy, slam_map.cam_from_world(
            self.last_keyframe).matrix(), tr.cam_from_world, self.camera.K)
        decision = self.selector.step(flow, tr.ref_matches, tr.num_inliers, self._points_at_last_keyframe,
                                      parallax, rotation)
        record.degenerate = decision.degenerate
        timings["keyframe"] = time.perf_counter() - t
        ba_kind = ""
        message = (f"relocalized against keyframe {self.last_keyframe}: " if relocalized else "") + tr.reason
        is_kf = False
        if decision.is_keyframe:
            ff = FrameFeatures(ff.index, ff.frame_id, ff.timestamp, ff.features, ff.keypoints, ff.colors,
                               self._thumbnail(ff.index))
            t = time.perf_counter()
            mres = self.mapper.step(slam_map, ff, tr.cam_from_world, tr.point2D_idxs, tr.point3D_ids,
                                    self.last_keyframe)
            timings["map"] = time.perf_counter() - t
            message = mres.reason
            if mres.registered:
                is_kf = True
                t = time.perf_counter()
                bres = self.bundle_adjuster.step(slam_map, mres.image_id)
                timings["ba"] = time.perf_counter() - t
                ba_kind = bres.kind
                if bres.normalization is not None:
                    self._apply_normalization(seg, float(bres.normalization.scale))
                t = time.perf_counter()
                culled = self._cull_keyframes(seg, mres.image_id, exclude=(self.last_keyframe,))
                n_drop, every = slam_map.num_dropped_images(), self.config.mapper.compact_dropped
                if every > 0 and n_drop >= max(every, slam_map.num_keyframes):
                    slam_map.compact()
                timings["cull"] = time.perf_counter() - t
                if culled:
                    message += f"; culled redundant keyframe{'s' if len(culled) > 1 else ''} " + ", ".join(
                        map(str, culled))
                self.last_keyframe = mres.image_id
                if ff.signature is not None:
                    seg.signatures[mres.image_id] = ff.signature
                record.keyframe_image_id = mres.image_id
                self._set_pose(record, mres.image_id, np.eye(4), TRACKED)
                self._points_at_last_keyframe = slam_map.reconstruction.image(mres.image_id).num_points3D
                t = time.perf_counter()
                self.local_map = self._local_map(slam_map, self.last_keyframe)
                timings["local_map"] = time.perf_counter() - t
            else:
                decision = KeyframeDecision(False, f"keyframe rejected: {mres.reason}", flow, tr.ref_matches)
        return self._result(record, TRACKED, message, timings, decision=decision, matches=tr.ref_matches,
                            inliers=tr.num_inliers, flow=flow, is_keyframe=is_kf, ba=ba_kind,
                            degenerate=decision.degenerate, parallax_deg=parallax,
                            relocalized=relocalized)

    def _cull_keyframes(self, seg: Segment, new_image_id: int, exclude: tuple[int, ...] = ()) -> list[int]:
        """ORB-SLAM's keyframe culling over the new keyframe's local window (``keyframes.cull_redundant``):
        remove redundant keyframes from the map; the frames anchored to one (itself included) keep their
        poses, re-anchored to its most covisible remaining keyframe. Never the new keyframe, ``exclude``,
        the map's first two keyframes (they hold the gauge), the ``keyframes.cull_keep_recent`` newest, or
        while the map is young. Returns their ids."""
        c = self.config.keyframes
        slam_map = seg.slam_map
        if c.cull_redundant <= 0 or slam_map.num_keyframes < max(RETRACK_BELOW_KEYFRAMES, 4):
            return []
        ids = sorted(slam_map.keyframes)
        protected = {new_image_id, *exclude, *ids[:2], *ids[len(ids) - c.cull_keep_recent:]}
        culled = []
        for iid, _ in slam_map.covisible(new_image_id, self.config.ba.local_window):
            if iid in protected or keyframe_redundancy(slam_map, iid, c.cull_min_observers) < c.cull_redundant:
                continue
            anchor = next((j for j, _ in slam_map.covisible(iid) if j != iid), None)
            if anchor is None:
                continue
            self._reanchor(seg, iid, anchor)
            slam_map.cull(iid)
            seg.signatures.pop(iid, None)
            seg.keyframes_culled += 1
            culled.append(iid)
        return culled

    def _reanchor(self, seg: Segment, image_id: int, anchor: int) -> None:
        """Frames posed relative to keyframe ``image_id`` (and the keyframe's own frame) are posed relative
        to ``anchor`` instead, with the same absolute poses."""
        slam_map = seg.slam_map
        old = np.eye(4)
        old[:3] = slam_map.cam_from_world(image_id).matrix()
        new = np.eye(4)
        new[:3] = slam_map.cam_from_world(anchor).matrix()
        change = old @ np.linalg.inv(new)  # refcam_old_from_refcam_new
        for i in seg.frames:
            rec = self.records[i]
            if rec.ref_image_id == image_id and rec.rel_pose is not None:
                rec.rel_pose = rec.rel_pose @ change
                rec.ref_image_id = anchor
            if rec.keyframe_image_id == image_id:
                rec.keyframe_image_id = -1

    def _relocalize(self, ff: FrameFeatures):
        """Localize a frame the local map could not track against the keyframes that look most alike
        (global image signature), each with its own local map; on success tracking resumes there."""
        seg = self.segment
        if ff.signature is None or not seg.signatures:
            return None
        ids = [i for i in seg.signatures if i in seg.slam_map.keyframes and i != self.last_keyframe]
        if not ids:
            return None
        scores = np.array([float(seg.signatures[i] @ ff.signature) for i in ids])
        camera = seg.slam_map.pycolmap_camera
        for k in np.argsort(-scores, kind="stable")[: self.config.relocalization_candidates]:
            local_map = self._local_map(seg.slam_map, ids[k])
            tr = self.tracker.step(ff, local_map, camera, None)
            if tr.tracked:
                self.local_map, self.last_keyframe = local_map, ids[k]
                self._points_at_last_keyframe = seg.slam_map.reconstruction.image(ids[k]).num_points3D
                seg.relocalizations += 1
                return tr
        return None

    def _local_map(self, slam_map: SlamMap, keyframe: int) -> LocalMap:
        c = self.config.tracker
        return LocalMap.build(slam_map, keyframe, c.local_keyframes, c.point_descriptor)

    def _predict(self, index: int) -> np.ndarray | None:
        """Constant-velocity prediction for frame ``index`` from the two posed frames of the current segment
        before it."""
        posed = []
        for rec in reversed(self.records[:index]):
            if rec.status == LOST and rec.segment != self.segment.id:
                break
            if rec.rel_pose is not None and rec.segment == self.segment.id:
                posed.append(rec)
                if len(posed) == 2:
                    break
            if index - rec.index > 5:
                break
        if not posed:
            return None
        last = self.pose_of(posed[0])
        if len(posed) == 1:
            return last
        prev = self.pose_of(posed[1])
        steps = max(posed[0].index - posed[1].index, 1)
        velocity = last @ np.linalg.inv(prev)
        if steps > 1:  # velocity per frame is not simply divisible; use it once per gap
            return last
        return velocity @ last

    def _set_pose(self, rec: FrameRecord, ref_image_id: int, pose: np.ndarray, status: str,
                  absolute: bool = False) -> None:
        slam_map = self.segment.slam_map
        if absolute:
            ref = np.eye(4)
            ref[:3] = slam_map.cam_from_world(ref_image_id).matrix()
            pose = pose @ np.linalg.inv(ref)
        rec.ref_image_id = ref_image_id
        rec.rel_pose = pose
        rec.segment = self.segment.id
        rec.status = status
        if not self.segment.frames or self.segment.frames[-1] != rec.index:
            self.segment.frames.append(rec.index)

    def _apply_normalization(self, seg: Segment, scale: float) -> None:
        for i in seg.frames:
            rel = self.records[i].rel_pose
            if rel is not None:
                rel[:3, 3] *= scale

    def _end_segment(self) -> None:
        self._last_ids = None
        self.segment = None
        self.local_map = None
        self.last_keyframe = -1
        self._consecutive_lost = 0
        self.initializer.reset()

    def finish(self) -> None:
        """End of the run: a last global BA of every segment (when configured), then the frames posed at
        initialization (against a two-keyframe map) are tracked again against the final map."""
        if self.finished:
            return
        self.finished = True
        t = time.perf_counter()
        for seg in self.segments:
            if self.config.ba.final_global and seg.slam_map.num_keyframes >= 3:
                bres = self.bundle_adjuster.adjust_global(seg.slam_map)
                if bres.normalization is not None:
                    self._apply_normalization(seg, float(bres.normalization.scale))
        self.timings["ba"] = self.timings.get("ba", 0.0) + time.perf_counter() - t
        t2 = time.perf_counter()
        for seg in self.segments:
            self._retrack_initial_frames(seg)
        self.timings["track"] = self.timings.get("track", 0.0) + time.perf_counter() - t2
        self.wall_time += time.perf_counter() - t

    def _retrack_initial_frames(self, seg: Segment) -> None:
        """Track the frames posed while the map was young again, against the final map around the first
        keyframes (their first poses came from a two- or three-keyframe map)."""
        if not seg.initial_frames or seg.slam_map.num_keyframes < 3:
            return
        slam_map = seg.slam_map
        first_kf = min(slam_map.keyframes)
        local_map = self._local_map(slam_map, first_kf)
        for f in seg.initial_frames:
            rec = self.records[f.index]
            if rec.keyframe_image_id > 0:  # keyframes are posed by bundle adjustment
                continue
            tr = self.tracker.step(f, local_map, slam_map.pycolmap_camera, self.pose_of(rec))
            if tr.tracked:
                ref = np.eye(4)
                ref[:3] = slam_map.cam_from_world(first_kf).matrix()
                rec.ref_image_id, rec.rel_pose, rec.segment, rec.status = (first_kf, tr.cam_from_world @ np.linalg.inv(ref),
                                                                            seg.id, TRACKED)
                if rec.index not in seg.frames:
                    seg.frames.append(rec.index)
        seg.frames.sort()
        seg.initial_frames = []  # done: features are no longer needed

    def _result(self, rec: FrameRecord, status: str, message: str, timings: dict,
                decision: KeyframeDecision | None = None, **kw) -> StepResult:
        slam_map = self.segment.slam_map if self.segment is not None else None
        return StepResult(
            frame_index=rec.index, frame_id=rec.frame_id, timestamp=rec.timestamp, status=status,
            message=message, segment=self.segment.id if self.segment is not None else -1,
            keyframe_reason=decision.reason if decision is not None else "",
            cam_from_world=self.pose_of(rec),
            num_keyframes=slam_map.num_keyframes if slam_map else 0,
            num_points=slam_map.num_points if slam_map else 0, timings=dict(timings), **kw)

    # ----------------------------------------------------------------- state queries
    def pose_of(self, rec: FrameRecord | int) -> np.ndarray | None:
        """(4, 4) cam_from_world of a frame (record or index) in its segment's map, or None."""
        if isinstance(rec, (int, np.integer)):
            rec = self.records[int(rec)]
        if rec.rel_pose is None:
            return None
        slam_map = self.segments[rec.segment].slam_map
        ref = np.eye(4)
        ref[:3] = slam_map.reconstruction.frame(rec.ref_image_id).rig_from_world.matrix()
        return rec.rel_pose @ ref

    @property
    def slam_map(self) -> SlamMap | None:
        """The map of the current segment (or of the largest one once tracking ended)."""
        if self.segment is not None:
            return self.segment.slam_map
        main = self.main_segment
        return main.slam_map if main is not None else None

    @property
    def main_segment(self) -> Segment | None:
        """The segment with the most posed frames."""
        if not self.segments:
            return None
        return max(self.segments, key=lambda s: (len(s.frames), -s.id))

    def trajectory(self, keyframes_only: bool = False, segment: int | None = None) -> Trajectory:
        """Camera-to-world poses of the posed frames of a segment (default: the main one), source timestamps."""
        seg = self.main_segment if segment is None else self.segments[segment]
        if seg is None:
            return Trajectory(np.empty(0), np.empty((0, 4, 4)))
        ts, poses = [], []
        for i in seg.frames:
            rec = self.records[i]
            if rec.segment != seg.id or rec.rel_pose is None:
                continue
            if keyframes_only and rec.keyframe_image_id < 0:
                continue
            ts.append(rec.timestamp)
            poses.append(np.linalg.inv(self.pose_of(rec)))
        return Trajectory(np.array(ts), np.array(poses).reshape(-1, 4, 4))

    def summary(self) -> dict:
        """The numbers of the seed's Table 2 and more, JSON-serialisable."""
        n = len(self.records)
        posed = sum(r.rel_pose is not None for r in self.records)
        lost = sum(r.status == LOST for r in self.records)
        main = self.main_segment
        slam_map = main.slam_map if main else None
        init_s = self.timings.get("initialize", 0.0)
        n_kf = slam_map.num_keyframes if slam_map else 0
        return {
            "source": getattr(self.source, "name", str(self.source)),
            "frames": n,
            "frames_total": int(len(self.indices)),
            "frames_posed": int(posed),
            "frames_lost": int(lost),
            "frames_skipped": int(sum(r.status == SKIPPED for r in self.records)),
            "frames_degenerate": int(sum(r.degenerate for r in self.records)),
            "frames_unreadable": int(sum(bool(r.unreadable) for r in self.records)),
            "unreadable_frames": [{"frame": r.index, "frame_id": r.frame_id, "error": r.unreadable}
                                  for r in self.records if r.unreadable],
            "not_initialized_reason": None if self.segments else self._why_not_initialized(),
            "fraction_posed": posed / n if n else 0.0,
            "keyframes": n_kf,
            "points3D": slam_map.num_points if slam_map else 0,
            "points_per_image": slam_map.points_per_image() if slam_map else 0.0,
            "mean_reprojection_error_px": slam_map.mean_reprojection_error() if slam_map else 0.0,
            "segments": [{"id": s.id, "frames": len(s.frames), "first_frame": s.frames[0] if s.frames else None,
                          "last_frame": s.frames[-1] if s.frames else None, "relocalizations": s.relocalizations,
                          "keyframes": s.slam_map.num_keyframes, "points3D": s.slam_map.num_points}
                         for s in self.segments],
            "main_segment": main.id if main else None,
            "relocalizations": int(sum(s.relocalizations for s in self.segments)),
            "keyframes_culled": int(sum(s.keyframes_culled for s in self.segments)),
            "cpu_time_s": self.cpu_time,
            "wall_time_s": self.wall_time,
            "fps": n / self.wall_time if self.wall_time > 0 else 0.0,
            "initialization_s": init_s,
            "seconds_per_frame": self.wall_time / n if n else 0.0,
            "seconds_per_keyframe": self.wall_time / n_kf if n_kf else 0.0,
            "timings_s": dict(self.timings),
            "config": self.config.to_dict(),
        }

    def save_session(self, out_dir: str | Path) -> Path:
        """Write only the session (everything :meth:`resume` needs) to ``out_dir``, atomically.
        :meth:`save` writes one too, in ``out_dir/session/``."""
        from .session import save_session

        return save_session(self, out_dir)

    @classmethod
    def resume(cls, path: str | Path, source: FrameSource | str | None = None, config=None,
               callbacks: list[Callback] | None = None) -> "Slam":
        """The Slam saved in ``path`` (a run folder from :meth:`save`, or a session folder), ready to continue
        at the next frame. ``source`` defaults to the recorded one; ``config`` None = the saved config, a dict
        overrides some of its values (see :func:`slamkit.session.load_session`)."""
        from .session import load_session

        return load_session(path, source, config, callbacks, cls=cls)

    def _why_not_initialized(self) -> str:
        """Why no map exists yet (for the summary): too short a sequence, or the initializer's last reason."""
        c = self.config.initializer
        if c.strategy == "best_pair" and len(self.indices) < c.init_frames:
            return (f"the sequence has {len(self.indices)} frames, fewer than the initialization window "
                    f"(initializer.init_frames = {c.init_frames}): lower init_frames to at least 2")
        if self._init_message:
            return f"no initial pair found; last attempt: {self._init_message}"
        if not self.records:
            return "no frame processed yet"
        return f"no initial pair tried yet ({self.records[-1].status}: {len(self.records)} frames so far)"

    def save(self, out_dir: str | Path) -> Path:
        """Write trajectories, COLMAP model, PLY, summary and a session to resume from (:meth:`resume`) to
        ``out_dir``, atomically (see :func:`slamkit.io.save_run`)."""
        from .io.run import save_run

        return save_run(self, out_dir)


def _seeded(stage_config, seed: int):
    from dataclasses import replace

    return replace(stage_config, random_seed=seed)


def _reindexed(frame: Frame, index: int) -> Frame:
    if frame.index == index:
        return frame
    from dataclasses import replace

    return replace(frame, index=index)
