"""Slam: composes the stages over one :class:`~slamkit.state.SlamState`, one frame per step. Imports no UI.

One frame (:meth:`Slam.step`): read and extract features -> initializing: ``Initializer.step`` (on success a
new segment, the rest of its window tracked) | tracking: ``MotionModel.step`` (constant-velocity prediction)
-> ``Tracker.step`` against the local map (-> ``Relocalizer.step`` when lost) -> ``KeyframeSelector.decide``
(flow score, parallax, tracked matches) -> [keyframe] ``Mapper.step`` -> ``BundleAdjuster.step``
-> ``KeyframeCuller.step`` -> a new local map -> :class:`~slamkit.results.StepResult` -> callbacks.
Everything the run has done lives in :attr:`Slam.state`; the attributes below it are thin views of it.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .config import SlamConfig
from .errors import CalibrationError, ImageReadError, check_type
from .features import FrameFeatures, create_extractor, create_matcher
from .frames import FrameLoader, thumbnail
from .interrupt import deferred_interrupt
from .io.run import save_run
from .local_map import LocalMap
from .map import SlamMap
from .map_reuse import MapReuse, map_config
from .merging import MergeResult, merge_candidate
from .results import StepResult, TrackedMatches
from .rotation_phase import RotationPhase
from .run_camera import (calibrate_radial, camera_report, choose_camera, describe_camera, final_global_ba,
                         first_estimate, open_for_config, radial_due, refined_camera, refines)
from .session import load_session, save_session, unfinished_snapshot
from .sources.base import FrameSource
from .stages.ba import BundleAdjuster, filter_angle_after
from .stages.culling import KeyframeCuller, KeyframeCullingConfig
from .stages.initializer import Initializer, track_window
from .stages.keyframes import KeyframeDecision, KeyframeSelector
from .stages.local_mapper import LocalMapper
from .stages.loop_closer import LoopCloser, LoopClosingResult, MergeCandidate
from .stages.mapper import Mapper
from .stages.motion import MotionModel
from .stages.pose_refinement import FinalPoseRefiner
from .stages.relocalizer import Relocalizer, RelocalizerConfig
from .stages.self_calibration import SelfCalibrator
from .stages.tracker import Tracker, TrackingResult, retrack_initial_frames
from .state import FrameRecord, FrameStatus, Segment, SlamState
from .types import Frame

RETRACK_BELOW_KEYFRAMES = 5
"""Frames tracked while the map had fewer keyframes are tracked again against the final map (finish)."""

# frame statuses, by their old names
INITIALIZING, INITIALIZED, TRACKED = FrameStatus.INITIALIZING, FrameStatus.INITIALIZED, FrameStatus.TRACKED
LOST, SKIPPED, ERROR = FrameStatus.LOST, FrameStatus.SKIPPED, FrameStatus.ERROR

Callback = Callable[["Slam", StepResult], None]


def _state_view(name: str, doc: str) -> property:
    """A Slam attribute that is a field of its state."""
    return property(lambda self: getattr(self.state, name), lambda self, v: setattr(self.state, name, v), doc=doc)


class Slam:
    """Monocular SLAM over a frame source, one frame per :meth:`step`.

    >>> slam = Slam(open_source("default"), SlamConfig())      # doctest: +SKIP
    >>> for result in slam: print(result)                      # doctest: +SKIP
    >>> slam.save("runs/demo")                                 # doctest: +SKIP
    """

    records = _state_view("records", "Frame records, one per processed frame (:class:`~slamkit.state.FrameRecord`).")
    segments = _state_view("segments", "Map segments (:class:`~slamkit.state.Segment`).")
    segment = _state_view("segment", "The segment being tracked, or None.")
    local_map = _state_view("local_map", "The local map frames are tracked against.")
    last_keyframe = _state_view("last_keyframe", "Image id of the last keyframe of the current segment.")
    timings = _state_view("timings", "Seconds per stage over the run.")
    wall_time = _state_view("wall_time", "Wall-clock seconds of the steps so far.")
    cpu_time = _state_view("cpu_time", "CPU seconds of the steps so far.")
    errors = _state_view("errors", "Frame index -> the exception a stage raised on it (status ``error``).")
    finished = _state_view("finished", "Whether :meth:`finish` ran.")
    _cursor = _state_view("cursor", "Frames consumed.")
    _points_at_last_keyframe = _state_view("points_at_last_keyframe", "")
    _consecutive_lost = _state_view("consecutive_lost", "")
    _last_ids = _state_view("last_ids", "")

    def __init__(self, source: FrameSource | str, config: SlamConfig | str | None = None,
                 callbacks: list[Callback] | None = None, map: str | Path | None = None, localize_only: bool = False):
        if not isinstance(source, (str, Path)) and not all(hasattr(source, a) for a in ("camera", "__len__")):
            check_type(source, (FrameSource, str, Path), "source", "give a spec ('default'), a path or a "
                       "FrameSource (or an object with its camera, frames and timestamps)")
        check_type(config, (SlamConfig, str, type(None)), "config",
                   "give a SlamConfig (SlamConfig().with_overrides(...)), a preset name or None")
        if config is None:
            config = SlamConfig()
        elif isinstance(config, str):
            config = SlamConfig.preset(config)
        self._map = (map, bool(localize_only))  # a saved run's map to localize in (slamkit.map_reuse)
        self.config = config.validate() if map is None else map_config(config, localize_only)
        self.source_spec = str(source) if isinstance(source, (str, Path)) else getattr(source, "spec", None)
        """How the source was opened (a spec; an ``open_source`` source's own), so resume and export reopen it."""
        if isinstance(source, (str, Path)):
            source = open_for_config(source, config)
        self.source = source
        self.callbacks: list[Callback] = list(callbacks or [])
        self.loader = FrameLoader(source)
        """Reads each frame and extracts its features (one frame ahead with ``config.prefetch``)."""
        self.reset()

    # ----------------------------------------------------------------- lifecycle
    def reset(self, config: SlamConfig | None = None) -> None:
        """Start over (with a new config if given): empty map, first frame next."""
        self.loader.drain()  # before the stages it uses are replaced
        if config is not None:
            self.config = config.validate() if self._map[0] is None else map_config(config, self._map[1])
        c = self.config
        self.camera, self.camera_origin, self.calibrator = choose_camera(
            c, self.source.camera, bool(getattr(self.source, "camera_in_spec", False)))
        """The intrinsics in use; how they were obtained (the source's calibration, ``--camera``, a camera.txt, or
        estimated); and the self-calibration (``camera="auto"``, or no calibration given or found), else None."""
        extractor = create_extractor(c.features, **c.extractor_options())  # first: its missing weights first
        matcher = None if c.matcher == "nn" else create_matcher(c.matcher, **c.matcher_options())  # "nn": per stage
        self.tracker = Tracker(replace(c.tracker, random_seed=c.seed))
        self.motion_model = MotionModel()
        self.rotation_phase = RotationPhase(replace(c.motion_model, random_seed=c.seed), matcher)
        self.pose_refiner = FinalPoseRefiner(c.pose_refinement)  # the tracked frames, on the final map
        self.relocalizer = Relocalizer(RelocalizerConfig(c.relocalization_candidates, c.tracker.local_keyframes,
                                                         c.tracker.point_descriptor))
        self.selector = KeyframeSelector(c.keyframes)
        self.mapper = Mapper(c.mapper, matcher)
        self.local_mapper = LocalMapper(c.local_mapping, c.mapper.min_keyframe_points)
        self.bundle_adjuster = BundleAdjuster(c.ba, c.self_calibration.refine_principal_point)
        k = c.keyframes
        self.culler = KeyframeCuller(KeyframeCullingConfig(k.cull_redundant, k.cull_min_observers, k.cull_keep_recent,
                                                           c.ba.local_window, max(RETRACK_BELOW_KEYFRAMES, 4)))
        self.initializer = Initializer(self.camera, replace(c.initializer, random_seed=c.seed), matcher)
        self.loop_closer = LoopCloser(c.loop_closing, c.features)
        self.indices = np.arange(0, len(self.source), c.frame_skip)[: c.max_frames]
        self.loader.configure(self.indices, extractor, self.camera, c.prefetch)
        self.state = SlamState()
        """Everything the run has done (records, segments, cursor, counters): what a session saves."""
        self.unfinished_session: dict[str, bytes] | None = None
        """The session files just before :meth:`finish` (what a finished run's session/ holds), or None."""
        self.last_frame: Frame | None = None
        self.last_features: FrameFeatures | None = None
        self.last_result: StepResult | None = None
        self.map_reuse = MapReuse.attach(self, *self._map) if self._map[0] is not None else None

    @property
    def extractor(self):
        """The feature extractor (``config.features``); replaceable (e.g. by a timing wrapper)."""
        return self.loader.extractor

    @extractor.setter
    def extractor(self, extractor) -> None:
        self.loader.extractor = extractor

    @property
    def _prefetched(self) -> tuple | None:
        """(cursor, Future) of the frame being read ahead, or None."""
        return self.loader.prefetched

    @property
    def done(self) -> bool:
        return self.state.cursor >= len(self.indices)

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
        cursor, num_records, last_result = self.state.cursor, len(self.state.records), self.last_result
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
        st = self.state
        untouched, done = len(st.records) == num_records, self.last_result is not last_result
        if isinstance(e, KeyboardInterrupt) and (untouched or done):
            st.cursor = cursor if untouched else st.cursor
            e.add_note(f"slamkit: interrupted at frame {cursor}; earlier frames are kept, save() works")
            return
        st.cursor = max(st.cursor, cursor + 1)
        if untouched:  # failed before its record existed (reading, features)
            i = int(self.indices[cursor])
            ids, ts = getattr(self.source, "frame_ids", None), getattr(self.source, "timestamps", None)
            st.records.append(FrameRecord(cursor, int(ids[i]) if ids is not None else i,
                                          float(ts[i]) if ts is not None else float("nan"), ERROR))
        rec = st.records[num_records]
        st.mark_error(rec, f"{type(e).__name__}: {e}" + (" (in a callback)" if done else ""), posed=done)
        e.add_note(f"slamkit: while processing frame {rec.index} (frame id {rec.frame_id})"
                   + (" in a callback, after the frame was processed" if done else "")
                   + "; earlier frames are kept, save() works, step() continues with the next frame")

    def _step(self) -> StepResult:
        st = self.state
        if self.calibrator is not None and self.calibrator.initial is None:
            self.calibrate()
        t_start, cpu_start = time.perf_counter(), time.process_time()
        timings: dict[str, float] = {}
        loaded = self.loader.next(st.cursor)
        if isinstance(loaded[0], (ImageReadError, CalibrationError)):  # a bad frame is skipped with its reason
            result = self._skip_unreadable(loaded[0], timings, t_start)
        else:
            frame, ff, timings["read"], timings["features"] = loaded
            st.cursor += 1
            self.last_frame, self.last_features = frame, ff
            record = FrameRecord.of_frame(frame, LOST)  # with its fingerprint, measured as it was read (issue 50)
            st.records.append(record)
            if st.segment is None:  # with a saved map it is looked for there first (map_reuse)
                result = (self.map_reuse.seek(self, ff, record, timings) if self.map_reuse is not None
                          else self._initialize(ff, record, timings))
            else:
                result = self._track(ff, record, timings)
        st.wall_time += time.perf_counter() - t_start
        st.cpu_time += time.process_time() - cpu_start
        st.add_timings(timings)
        self.last_result = result
        for cb in self.callbacks:
            cb(self, result)
        return result

    def _skip_unreadable(self, error: Exception, timings: dict, t_start: float) -> StepResult:
        """A frame the source cannot deliver: status "skipped", the source's message (file, frame) in the
        result and in ``summary()["unreadable_frames"]``; the map and the tracking state are untouched."""
        i = int(self.indices[self.state.cursor])
        record = self.state.skip_unreadable(int(self.source.frame_ids[i]), float(self.source.timestamps[i]), error)
        timings["read"] = time.perf_counter() - t_start
        return self._result(record, SKIPPED, f"bad frame skipped: {error}", timings)

    # ----------------------------------------------------------------- self-calibration
    def calibrate(self) -> SelfCalibrator | None:
        """Estimate the focal length from the first frames now (self-calibration's first phase; the first
        :meth:`step` does it otherwise), so that :attr:`camera` holds the estimate. Returns the calibrator,
        or None when the camera is known."""
        cal = self.calibrator
        if cal is None or cal.initial is not None:
            return cal
        self.loader.drain()  # the source is read by one thread at a time
        t, cpu = time.perf_counter(), time.process_time()
        self._use_camera(first_estimate(cal, self.source, self.indices, self.camera))
        self.state.add_timings({"calibrate": time.perf_counter() - t})
        self.state.wall_time += time.perf_counter() - t
        self.state.cpu_time += time.process_time() - cpu
        return cal

    def _use_camera(self, camera) -> None:
        self.camera = camera
        self.loader.camera = camera  # no distortion is known while tracking: the keypoints are the same
        self.initializer.set_camera(camera)

    def _refined(self, slam_map: SlamMap, final: bool = False, k1: float = 0.0, before: float | None = None) -> None:
        """After a refining BA: its focal length (and ``k1``) used from now on, and recorded by the calibrator."""
        self._use_camera(refined_camera(self.camera, slam_map, k1))
        self.calibrator.refined(self.camera.fx, slam_map.num_keyframes, final, self.camera.dist[0], before)

    # ----------------------------------------------------------------- initialization
    def _initialize(self, ff: FrameFeatures, record: FrameRecord, timings: dict) -> StepResult:
        st = self.state
        t = time.perf_counter()
        if len(ff) < 8:
            record.status, timings["initialize"] = SKIPPED, time.perf_counter() - t
            return self._result(record, SKIPPED, f"{len(ff)} keypoints: featureless frame skipped", timings)
        res = self.initializer.step(ff, last=self.done)  # the cursor has moved past this frame
        timings["initialize"] = time.perf_counter() - t
        if not res.initialized:  # meanwhile a frame that only turns gets its orientation (rotation_phase)
            record.status, st.init_message = INITIALIZING, res.reason if res.status == "failed" else st.init_message
            t = time.perf_counter()
            turn = self.rotation_phase.step(st, self.initializer, ff, record, self.camera.K)
            timings["rotation"] = time.perf_counter() - t
            return self._result(record, INITIALIZING, turn.note + res.reason, timings, **turn.fields)
        # a new segment with the two initial keyframes; the rest of the window is tracked below
        st.start_segment(res.slam_map, res.frames, [f for f in res.frames if f.index < res.second and f.index != res.first])
        st.local_map = self._local_map(res.slam_map, st.last_keyframe)
        posed, message = track_window(st, res, self.tracker, self._track, timings)
        posed += self.rotation_phase.anchor(st)  # the frames that only turned before, posed in this map
        record.status = record.status if record.rel_pose is not None else LOST
        return self._result(record, INITIALIZED, res.reason + message, timings, posed_frames=tuple(sorted(posed)),
                            is_keyframe=record.keyframe_image_id > 0)

    # ----------------------------------------------------------------- tracking
    def _track(self, ff: FrameFeatures, record: FrameRecord, timings: dict) -> StepResult:
        """Track a frame against the local map (relocalize when that fails), then decide on a keyframe and
        insert it: the named steps below, in order."""
        st = self.state
        seg = st.segment
        t = time.perf_counter()
        if len(ff) < self.config.tracker.min_inliers:
            record.status, timings["track"] = SKIPPED, time.perf_counter() - t
            return self._result(record, SKIPPED, f"{len(ff)} keypoints: featureless frame skipped", timings)
        prediction = self.motion_model.step(st.records, record.index, seg.id, st.pose_of)
        tr = self.tracker.step(ff, st.local_map, seg.slam_map.pycolmap_camera, prediction.cam_from_world, st.last_ids)
        relocalized = False
        if not tr.tracked and self.config.relocalization_candidates > 0:
            t_reloc = time.perf_counter()
            found = self._relocalize(ff)
            timings["relocalize"] = time.perf_counter() - t_reloc
            if found is not None:
                tr, relocalized = found, True
        timings["track"] = time.perf_counter() - t - timings.get("relocalize", 0.0)
        if not tr.tracked:
            return self._lost(record, tr, timings, ff)
        st.consecutive_lost, st.last_ids = 0, tr.point3D_ids
        if len(seg.recent_points.ids):  # local mapping's recent-point test counts every tracked frame
            cam = seg.slam_map.pycolmap_camera
            visible, _ = st.local_map.project(tr.cam_from_world, cam.calibration_matrix(), (cam.width, cam.height))
            seg.recent_points.observe(st.local_map.ids[visible], tr.point3D_ids)
        reference, tr = (st.last_keyframe, tr) if self.map_reuse is None else self.map_reuse.reference(self, tr, ff)
        st.set_pose(record, reference, tr.cam_from_world, TRACKED, absolute=True)
        self.pose_refiner.observe(record.index, seg.id, ff.keypoints[tr.point2D_idxs], tr.point3D_ids, self.camera.dist)
        if seg.slam_map.num_keyframes < RETRACK_BELOW_KEYFRAMES:  # young map: track again in finish()
            seg.initial_frames.append(ff)
        t = time.perf_counter()
        decision = self.selector.decide(tr.ref_xy, tr.cur_xy, seg.slam_map.cam_from_world(reference).matrix(),
                                        tr.cam_from_world, self.camera.K, tr.num_inliers, st.points_at_last_keyframe)
        flow, parallax = decision.flow, decision.parallax_deg
        record.degenerate = decision.degenerate
        timings["keyframe"] = time.perf_counter() - t
        message = (f"relocalized against keyframe {reference}: " if relocalized else "") + tr.reason
        is_kf, ba_kind, (loop, merge), mapping = False, "", (LoopClosingResult(), None), None
        if decision.is_keyframe and self.map_reuse is not None and self.map_reuse.localize_only:
            decision = self.map_reuse.gate(self, tr, decision)  # the map is left as it is, but outside it
        if decision.is_keyframe:
            inserted = self._insert_keyframe(ff, record, tr, decision, timings)
            is_kf, ba_kind, message, decision, (loop, merge), mapping = inserted
        return self._result(record, TRACKED, message, timings, decision=decision, matches=tr.ref_matches,
                            inliers=tr.num_inliers, flow=flow, is_keyframe=is_kf, ba=ba_kind,
                            degenerate=decision.degenerate, parallax_deg=parallax, relocalized=relocalized,
                            tracked=tr.matches, reference_keyframe=reference, loop_closure=loop.closure,
                            merge_candidate=loop.merge_candidate, map_merge=merge, mapping=mapping,
                            **self.rotation_phase.posed_by_pnp(st, ff, record, tr.num_inliers))

    def _lost(self, record: FrameRecord, tr: TrackingResult, timings: dict, ff: FrameFeatures) -> StepResult:
        """Neither the local map nor relocalization found the frame; unless it only turned (posed by rotation:
        ``RotationPhase.track_lost``), after ``max_lost_frames`` such frames (or with an empty local map) the
        segment ends and the next frames initialize a new one."""
        st = self.state
        t = time.perf_counter()
        turn = self.rotation_phase.track_lost(st, ff, record, self.camera.K)
        timings["rotation"] = timings.get("rotation", 0.0) + time.perf_counter() - t
        if turn.oriented:
            return self._result(record, TRACKED, turn.note + tr.reason, timings, **turn.fields)
        record.status, st.last_ids = LOST, None
        st.consecutive_lost += 1
        msg = tr.reason
        if st.consecutive_lost >= self.config.max_lost_frames or len(st.local_map) == 0:
            msg += f"; {st.consecutive_lost} frames lost: starting a new map segment"
            st.end_segment()  # resets the count
            self.initializer.reset()
        return self._result(record, LOST, msg, timings, matches=0, inliers=tr.num_inliers)

    def _relocalize(self, ff: FrameFeatures) -> TrackingResult | None:
        """:class:`~slamkit.stages.relocalizer.Relocalizer` over the segment's keyframes; on success tracking
        resumes at the keyframe that found the frame. Returns its tracking result, or None."""
        st = self.state
        seg = st.segment
        res = self.relocalizer.step(ff, seg.slam_map, seg.signatures, st.last_keyframe, self.tracker)
        if not res.relocalized:
            return None
        st.local_map, st.last_keyframe = res.local_map, res.keyframe
        st.points_at_last_keyframe = seg.slam_map.num_points_observed(res.keyframe,
                                                                      self.config.keyframes.reference_min_observers)
        seg.relocalizations += 1
        return res.tracking

    def _insert_keyframe(self, ff: FrameFeatures, record: FrameRecord, tr: TrackingResult,
                         decision: KeyframeDecision, timings: dict
                         ) -> tuple[bool, str, str, KeyframeDecision, tuple, object]:
        """Map the frame as a keyframe, bundle-adjust, cull redundant keyframes, close a loop through it, and
        track from it next. Returns (registered, BA kind, message, decision — a rejection by the mapper
        replaces it, (what loop closing did, a map merge), the mapper's result)."""
        st = self.state
        seg = st.segment
        slam_map = seg.slam_map
        ff = FrameFeatures(ff.index, ff.frame_id, ff.timestamp, ff.features, ff.keypoints, ff.colors,
                           thumbnail(self.last_frame, ff.index, self.config.thumbnail_width), ff.signature)
        t = time.perf_counter()
        local = self.config.mapper.method == "local"
        if local:
            mres = self.local_mapper.step(slam_map, ff, tr.cam_from_world, tr.point2D_idxs, tr.point3D_ids,
                                          seg.recent_points)
        else:
            mres = self.mapper.step(slam_map, ff, tr.cam_from_world, tr.point2D_idxs, tr.point3D_ids,
                                    st.last_keyframe)
        timings["map"] = time.perf_counter() - t
        if not mres.registered:
            return False, "", mres.reason, KeyframeDecision(False, f"keyframe rejected: {mres.reason}", decision.flow,
                                                            tr.ref_matches), (LoopClosingResult(), None), mres
        t = time.perf_counter()
        small = filter_angle_after(mres.starved, local, self.config.mapper, self.config.local_mapping, self.config.ba)
        bres = self._adjust(seg, lambda m, refine_focal: self.bundle_adjuster.step(m, mres.image_id, small,
                                                                                   refine_focal=refine_focal))
        timings["ba"] = time.perf_counter() - t
        t = time.perf_counter()
        culled = self._cull_keyframes(seg, mres.image_id, exclude=(st.last_keyframe,))
        slam_map.compact_when(self.config.mapper.compact_dropped)
        timings["cull"] = time.perf_counter() - t
        message = mres.reason
        if culled:
            message += f"; culled redundant keyframe{'s' if len(culled) > 1 else ''} " + ", ".join(map(str, culled))
        st.last_keyframe = mres.image_id
        if ff.signature is not None:  # every keyframe can relocalize a lost frame
            seg.signatures[mres.image_id] = ff.signature
        st.add_keyframe(record, mres.image_id)
        if self.config.loop_closing.enabled:
            t = time.perf_counter()
            loop, merge = self._close_loop(seg, mres.image_id)
            timings["loop"] = time.perf_counter() - t
            seg, slam_map = st.segment, st.segment.slam_map  # after a merge: the earlier segment's map
        else:
            loop, merge = LoopClosingResult(), None
        st.points_at_last_keyframe = slam_map.num_points_observed(st.last_keyframe,
                                                                  self.config.keyframes.reference_min_observers)
        t = time.perf_counter()
        st.local_map = self._local_map(slam_map, st.last_keyframe)
        timings["local_map"] = time.perf_counter() - t
        return True, bres.kind, message, decision, (loop, merge), mres

    def _close_loop(self, seg: Segment, image_id: int) -> tuple[LoopClosingResult, MergeResult | None]:
        """:class:`~slamkit.stages.loop_closer.LoopCloser` through the new keyframe; a place of an earlier segment
        merges the current segment into it (:meth:`_merge_maps`). After a correction or a merge a global BA, and
        the next frame searches the new local map (fused points changed their ids)."""
        res = self.loop_closer.step(self.state, seg, image_id)
        merge = None
        if res.merge_candidate is not None:
            merge = self._merge_maps(res.merge_candidate)
            seg = self.state.segment
        if res.needs_global_ba or (merge is not None and merge.global_ba_advised):
            self._adjust(seg, self.bundle_adjuster.adjust_global)
            self.state.last_ids = None
        return res, merge

    def _adjust(self, seg: Segment, adjust: Callable):
        """A BA of ``seg``'s map (``adjust(slam_map, refine_focal=...)``), refining the focal length when
        self-calibration says so, then a given camera's radial distortion when due. Returns the BA's result."""
        refine = refines(self.calibrator, seg.slam_map)
        bres = adjust(seg.slam_map, refine_focal=refine)
        if refine:
            self._refined(seg.slam_map)
        if bres.normalization is not None:
            self.state.apply_normalization(seg, float(bres.normalization.scale))
        if radial_due(self.calibrator, self.camera, seg.slam_map, self.config):  # a given camera's distortion
            self.loader.drain()  # a frame read ahead is loaded again, its keypoints undistorted with k1
            self._use_camera(calibrate_radial(self.state, seg, self.bundle_adjuster, self.camera, self.config))
        return bres

    def _merge_maps(self, candidate: MergeCandidate) -> MergeResult:
        """The current segment recognised a place of an earlier one: merged into it
        (:func:`~slamkit.merging.merge_candidate`); tracking continues in the merged map."""
        res = merge_candidate(self.state, self.map_reuse.orient(self.state, candidate) if self.map_reuse else candidate)
        self.loop_closer.rebuild(self.state.segments)  # image ids of the moved keyframes changed
        return res

    def _cull_keyframes(self, seg: Segment, new_image_id: int, exclude: tuple[int, ...] = ()) -> list[int]:
        """:class:`~slamkit.stages.culling.KeyframeCuller` around the new keyframe; frames anchored to a culled
        keyframe keep their poses, re-anchored to its most covisible remaining keyframe. Returns the ids culled."""
        res = self.culler.step(seg.slam_map, new_image_id, exclude)
        for c in res.culled:
            self.state.reanchor(seg, c.image_id, c.anchor, c.culled_from_anchor)
            seg.signatures.pop(c.image_id, None)
            self.loop_closer.forget(seg, c.image_id)
            seg.keyframes_culled += 1
        return res.image_ids

    def _local_map(self, slam_map: SlamMap, keyframe: int) -> LocalMap:
        c = self.config.tracker
        return LocalMap.build(slam_map, keyframe, c.local_keyframes, c.point_descriptor)

    # ----------------------------------------------------------------- end of the run
    def finish(self) -> None:
        """End of the run: a last global BA of every segment (when configured), then the frames posed at
        initialization (against a two-keyframe map) are tracked again against the final map."""
        st = self.state
        if st.finished:
            return
        try:
            self.unfinished_session = unfinished_snapshot(self)  # saved as session/: --resume extends from here
        except OSError:  # no room for the temporary copy: the finished state is saved, and not extended later
            self.unfinished_session = None
        st.finished = True
        t = time.perf_counter()
        for seg in st.segments:
            if self.config.ba.final_global and seg.slam_map.num_keyframes >= 3:
                refine = seg is st.main_segment and refines(self.calibrator, seg.slam_map, final=True)
                sc = self.config.self_calibration
                before, k1 = final_global_ba(st, seg, self.bundle_adjuster, refine, refine and sc.refine_radial,
                                             sc.max_radial)
                if refine:
                    self._refined(seg.slam_map, final=True, k1=k1, before=before)
        if self.map_reuse is not None:  # a saved map goes back to the frame and scale it was loaded in
            self.map_reuse.keep_frame(st)
        st.timings["ba"] = st.timings.get("ba", 0.0) + time.perf_counter() - t
        t2 = time.perf_counter()
        self.pose_refiner.refine(st, self.camera.dist)  # motion-only BA of the frames PnP posed, on the final map
        for seg in st.segments:
            if seg.initial_frames and seg.slam_map.num_keyframes >= 3:  # against the map around its first keyframe
                first = self._local_map(seg.slam_map, min(seg.slam_map.keyframes))
                retrack_initial_frames(st, seg, self.tracker, first)
        self.rotation_phase.finish(st, self.initializer, self.camera)  # a pure rotation; frames held re-centred
        st.timings["track"] = st.timings.get("track", 0.0) + time.perf_counter() - t2
        st.wall_time += time.perf_counter() - t

    def _result(self, rec: FrameRecord, status: FrameStatus, message: str, timings: dict,
                decision: KeyframeDecision | None = None, **kw) -> StepResult:
        seg = self.state.segment
        slam_map = seg.slam_map if seg is not None else None
        return StepResult(
            frame_index=rec.index, frame_id=rec.frame_id, timestamp=rec.timestamp, status=status,
            message=message, segment=seg.id if seg is not None else -1,
            keyframe_reason=decision.reason if decision is not None else "",
            cam_from_world=self.state.pose_of(rec),
            num_keyframes=slam_map.num_keyframes if slam_map else 0,
            num_points=slam_map.num_points if slam_map else 0, timings=dict(timings), **kw)

    # ----------------------------------------------------------------- state queries
    def pose_of(self, rec: FrameRecord | int) -> np.ndarray | None:
        """(4, 4) cam_from_world of a frame (record or index) in its segment's map, or None."""
        return self.state.pose_of(rec)

    slam_map = _state_view("slam_map", "The map of the current segment (or of the largest one once tracking ended).")
    main_segment = _state_view("main_segment", "The segment with the most posed frames.")

    def trajectory(self, keyframes_only: bool = False, segment: int | None = None):
        """Camera-to-world poses of the posed frames of a segment (default: the main one), source timestamps
        (a :class:`~slamkit.types.Trajectory`)."""
        return self.state.trajectory(keyframes_only, segment)

    def summary(self) -> dict:
        """The numbers of the seed's Table 2 and more, JSON-serialisable."""
        st = self.state
        why = None if st.segments else st.why_not_initialized()
        return {"source": getattr(self.source, "name", str(self.source)), **st.summary(len(self.indices), why),
                "camera": self.camera_report(), "config": self.config.to_dict(),
                **({"map": self.map_reuse.summary(st)} if self.map_reuse is not None else {})}

    def camera_report(self) -> dict:
        """The camera used and how it was obtained (with self-calibration: its estimate, uncertainty and
        history), JSON-serialisable."""
        return camera_report(self.camera, self.camera_origin, self.calibrator)

    def describe_camera(self) -> str:
        """One line: the intrinsics used and where they come from."""
        return describe_camera(self.camera, self.camera_origin, self.calibrator)

    # ----------------------------------------------------------------- saving and resuming
    def save(self, out_dir: str | Path) -> Path:
        """Write trajectories, COLMAP model, PLY, summary and a session to resume from (:meth:`resume`) to
        ``out_dir``, atomically (see :func:`slamkit.io.save_run`)."""
        return save_run(self, out_dir)

    def save_session(self, out_dir: str | Path) -> Path:
        """Write only the session (everything :meth:`resume` needs) to ``out_dir``, atomically.
        :meth:`save` writes one too, in ``out_dir/session/``."""
        return save_session(self, out_dir)

    @classmethod
    def resume(cls, path: str | Path, source: FrameSource | str | None = None, config=None,
               callbacks: list[Callback] | None = None) -> "Slam":
        """The Slam saved in ``path`` (a run folder from :meth:`save`, or a session folder), ready to continue
        at the next frame. ``source`` defaults to the recorded one; ``config`` None = the saved config, a dict
        overrides some of its values (see :func:`slamkit.session.load_session`)."""
        return load_session(path, source, config, callbacks, cls=cls)


__all__ = ["Slam", "StepResult", "TrackedMatches", "FrameRecord", "FrameStatus", "Segment", "SlamState",
           "RETRACK_BELOW_KEYFRAMES", "INITIALIZING", "INITIALIZED", "TRACKED", "LOST", "SKIPPED", "ERROR"]
