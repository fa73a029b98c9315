"""Map reuse (issue 49): a new video localized in a saved run's map, and the map extended.

``Slam(source, config, map=RUN_DIR)`` (``slamkit run SOURCE --map RUN_DIR``) loads the map of a run folder a
finished run wrote (``slam.save`` / ``slamkit run --out``) as the state's first segment, marked
:attr:`~slamkit.state.Segment.prior` (ORB-SLAM3's atlas, COLMAP's image registrator into an existing model):

- **what is loaded**: the run's main segment as it was saved in ``sparse/`` (after the run's final bundle
  adjustment: the frame and scale of the run's ``trajectory_tum.txt``), with what the session holds beside it
  (``session/segment_XX/arrays.npz``: every keyframe's keypoints, descriptors, colours and thumbnail, its
  place-recognition signature, the correspondence graph), and the run's camera (``camera.txt``). The old
  run folder is only read. Its keyframes get negative frame indices (``-1 - k``, k-th in the old run's frame
  order) and image names ``map_`` + theirs (``map_frame_000010``): they are no frames of this run, whose
  records are the new source's frames only. Bundle adjustment holds them constant
  (:func:`slamkit.stages.ba.held_keyframes`, as ORB-SLAM3's welding BA holds the old map), culling keeps them
  and a loop's pose graph holds them.
- **seeking the map** (:meth:`MapReuse.seek`): while no segment is tracked, each frame is first
  relocalized against the map's keyframes (:class:`~slamkit.stages.relocalizer.Relocalizer`, the
  :data:`SEEK_CANDIDATES` most similar by global signature); found, tracking goes on in the map, in its frame
  and scale. Not found: the frame goes to the initializer as in any run; a new segment it starts is merged
  into the map when loop closing recognises a place of it (:mod:`slamkit.merging`; the merge always moves
  the new segment into the map, :meth:`MapReuse.orient`, so the map keeps its frame).
- **mapping goes on** in the map: keyframes and points are added, bundle adjustment runs as usual, but the map
  is never normalized (``ba.normalize`` off: ``Reconstruction.normalize`` would move it out of its frame) and
  a given camera's radial distortion is not estimated again (``ba.radial_keyframes`` 0: the map's is used).
- **the reference keyframe** (:meth:`MapReuse.reference`): with ``map_reuse.covisible_reference`` (off by
  default) the keyframe decision measures flow and parallax against the keyframe sharing most of the frame's
  tracked points, and the local map is centred on it (ORB-SLAM's reference keyframe), not against the last
  inserted one. Measured on 7-Scenes redkitchen 300-599 in the map of 0-299: 40 keyframes added instead of
  37, 5.36 cm instead of 5.02 cm under the first run's alignment, so it stays opt-in.
- **localize only** (``localize_only=True``, ORB-SLAM's localization mode): the map is left as loaded: no
  final BA, and where tracking would insert a keyframe while the frame still tracks
  ``map_reuse.odometry_below`` or more of the loaded map's points, none is inserted (the reference moves).
  Below that the camera is leaving the map: a *temporary* keyframe is inserted (ORB-SLAM's visual odometry,
  ``mbVO``, which a monocular camera can only do with points of its own), so tracking goes on outside the map
  and comes back into it by the motion model rather than by a relocalization (which repeated structure, a
  kitchen's cupboard doors, fools). At the end every temporary keyframe and point is dropped and the map is
  the loaded one again (:meth:`MapReuse.drop_temporary`); frames posed on them keep their poses. Frames that
  cannot be localized are ``lost`` and no segment is started.

Refusals (:class:`~slamkit.errors.MapError`, one line, before anything is read from the new source): a
folder that is not a run folder, a run that holds no map, a session of another format version, a map whose
images have another size or whose camera differs from the source's calibration.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from .camera import Intrinsics
from .errors import MapError, SlamkitError
from .io.run_dir import RUN_MARKER
from .io.saved import check_run, check_session
from .map import CAMERA_ID, Keyframe, SlamMap
from .map_reuse_config import MapReuseConfig
from .session import FORMAT, SESSION_DIR, SESSION_FILE, VERSION, _features_from, _get_list, _npz
from .sources.calibration import camera_from_path
from .stages.keyframes import KeyframeDecision
from .stages.loop_closer import MergeCandidate
from .stages.relocalizer import Relocalizer, RelocalizerConfig
from .state import FrameStatus, Segment

if TYPE_CHECKING:  # pragma: no cover
    from .config import SlamConfig
    from .pipeline import Slam

SEEK_CANDIDATES = 5
"""Map keyframes (most similar global signatures first) tried for a frame that looks for the map."""
SEEK_KEYFRAMES = 10
"""Covisible keyframes in each candidate's local map while seeking (the tracker's ``local_keyframes`` once
found): a frame that does not see the map costs every candidate's search, so each is kept small."""
CAMERA_RTOL = 1e-4
"""Relative tolerance on fx, fy, cx, cy: a source's calibration must equal the map's camera to it."""


@dataclass(eq=False)
class PriorMap:
    """A saved run's map, loaded (:func:`load_map`)."""

    run_dir: Path
    segment: Segment
    """The run's main segment (``prior``, no frames of this run yet)."""
    camera: Intrinsics
    """The camera the map was made with (the run's ``camera.txt``)."""
    source: str
    """What the run was made from (its recorded source name)."""
    keyframes: int
    points: int
    old_frame_index: dict[int, int] = field(default_factory=dict)
    """Image id -> the keyframe's frame index in the old run."""


def _refuse(run: Path, why: str) -> MapError:
    return MapError(f"--map {run}: {why}")


def load_map(run_dir: str | Path) -> PriorMap:
    """The map of the run folder ``run_dir`` (see the module docstring); MapError, one line, otherwise."""
    run = Path(run_dir)
    if not run.is_dir():
        raise _refuse(run, "no such folder (give a run folder written by `slamkit run --out` or slam.save)")
    session = run / SESSION_DIR
    if not (run / RUN_MARKER).is_file() or not (session / SESSION_FILE).is_file():
        raise _refuse(run, f"not a slamkit run folder (it needs {RUN_MARKER} and {SESSION_DIR}/{SESSION_FILE}, "
                           "as `slamkit run --out` writes them)")
    try:
        meta = json.loads((session / SESSION_FILE).read_text())
    except (OSError, ValueError) as e:
        raise _refuse(run, f"{SESSION_DIR}/{SESSION_FILE} cannot be read ({e})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or meta.get("version") != VERSION:
        got = (meta.get("format"), meta.get("version")) if isinstance(meta, dict) else (None, None)
        raise _refuse(run, f"saved by an incompatible slamkit (session format {got[0]!r} version {got[1]!r}; this "
                           f"slamkit reads {FORMAT!r} version {VERSION}): map the first video again with it")
    try:
        check_run(run, ("summary.json", "sparse", "camera.txt", SESSION_DIR))
        check_session(session)
        summary = json.loads((run / "summary.json").read_text())
        main = summary.get("main_segment")
        if main is None:
            raise _refuse(run, "holds no map (no frame of that run was posed)")
        smeta = next(s for s in meta["segments"] if s["id"] == main)
        size = Intrinsics.from_dict(smeta["camera"])
        camera = camera_from_path(run, size.width, size.height, "--map")
        prior, old = _read_segment(smeta, session / f"segment_{main:02d}", run / "sparse")
    except MapError:
        raise
    except SlamkitError as e:
        raise _refuse(run, str(e).replace("\n", " ")) from None
    except (KeyError, TypeError, ValueError, StopIteration, IndexError) as e:
        raise _refuse(run, f"its session cannot be read by this slamkit ({type(e).__name__}: {e})") from None
    return PriorMap(run, prior, camera, str(meta.get("source", {}).get("name", "")), prior.slam_map.num_keyframes,
                    prior.slam_map.num_points, old)


def _read_segment(smeta: dict, seg_folder: Path, model: Path) -> tuple[Segment, dict]:
    """Segment 0 of a new state from the run's final model and the session's keyframe data."""
    try:
        final = pycolmap.Reconstruction(str(model))
    except Exception as e:  # noqa: BLE001 - pycolmap raises plain RuntimeError/ValueError
        raise MapError(f"{model}: COLMAP model cannot be read ({e})") from None
    with _npz(seg_folder / "arrays.npz") as arrays:
        tri = pycolmap.IncrementalTriangulatorOptions()
        tri.mergedict(smeta["triangulation"])
        slam_map = SlamMap(Intrinsics.from_dict(smeta["camera"]), tri)
        saved_cam = final.camera(CAMERA_ID)
        if saved_cam.model != slam_map.reconstruction.camera(CAMERA_ID).model:
            slam_map.use_radial_camera()
        slam_map.reconstruction.camera(CAMERA_ID).params = saved_cam.params
        kmetas = smeta["keyframes"]
        missing = [k["image_id"] for k in kmetas if not final.exists_image(int(k["image_id"]))]
        if missing:
            raise MapError(f"{model}: keyframe image {missing[0]} of the session is not in the saved model")
        ids = sorted(int(k["image_id"]) for k in kmetas)
        order = [int(i) for i in smeta["registration_order"] if int(i) in set(ids)]
        max_id = max([int(smeta["max_point3D_id"]), *[int(p) for p in final.point3D_ids()]])
        slam_map.refill(final, ids, arrays["graph_pairs"].tolist(), _get_list(arrays, "graph_matches"), order,
                        max_id, [])
        feats = _features_from(smeta["keyframe_features"], "kf", arrays)
        sigs = dict(zip(smeta["signature_image_ids"], _get_list(arrays, "signatures")))
    old: dict[int, int] = {}
    by_frame = sorted(range(len(kmetas)), key=lambda k: int(kmetas[k]["frame_index"]))
    for rank, k in enumerate(by_frame):
        kmeta, (features, keypoints, colors, thumbnail, _) = kmetas[k], feats[k]
        iid = int(kmeta["image_id"])
        old[iid] = int(kmeta["frame_index"])
        slam_map.keyframes[iid] = Keyframe(iid, -1 - rank, float(kmeta["timestamp"]), keypoints, features, colors,
                                           thumbnail)
        image = slam_map.reconstruction.image(iid)
        image.name = f"map_{image.name}"  # frame_000010 -> map_frame_000010 (map_map_... for a map's map)
    slam_map.next_image_id = int(smeta["next_image_id"])
    slam_map.changed()
    signatures = {int(i): s for i, s in sigs.items() if int(i) in slam_map.keyframes and s is not None}
    return Segment(0, slam_map, signatures=signatures, prior=True), old


def map_config(config: "SlamConfig", localize_only: bool) -> "SlamConfig":
    """The configuration of a run in a saved map: the map is never normalized nor its camera's distortion
    estimated again; localizing only, no final BA either."""
    ba = replace(config.ba, normalize=False, radial_keyframes=0,
                 final_global=config.ba.final_global and not localize_only)
    return replace(config, ba=ba).validate()


class MapReuse:
    """A :class:`~slamkit.pipeline.Slam`'s saved map: seeking it, localize-only tracking, merge orientation."""

    def __init__(self, prior: PriorMap, localize_only: bool, relocalizer: RelocalizerConfig):
        self.prior = prior
        self.localize_only = localize_only
        self.relocalizer = Relocalizer(replace(relocalizer, candidates=max(relocalizer.candidates, SEEK_CANDIDATES),
                                               local_keyframes=min(relocalizer.local_keyframes, SEEK_KEYFRAMES)))
        self.found = 0
        """Frames that found the map while no segment was tracked."""
        self.centres = _centres(prior.segment.slam_map, sorted(prior.segment.slam_map.keyframes))
        """Image id -> camera centre of each loaded keyframe as it was loaded (:meth:`keep_frame`)."""
        self.frame_correction: dict | None = None
        rec = prior.segment.slam_map.reconstruction
        self.prior_points = np.array(sorted(rec.point3D_ids()), np.int64)
        """Ids of the loaded map's points (localizing only, :meth:`gate` counts those a frame tracks)."""
        self.temporary = 0
        """Temporary keyframes asked for while localizing only (visual odometry outside the map)."""
        self.dropped = 0
        self.odometry_frames = 0
        self.back_in_map = 0
        """Frames on visual odometry relocalized back into the loaded map."""

    @classmethod
    def attach(cls, slam: "Slam", run_dir: str | Path, localize_only: bool) -> "MapReuse":
        """Load ``run_dir``'s map into ``slam`` (a Slam just reset): the camera checked and adopted, the map as
        segment 0 of its state, the place database rebuilt with its keyframes."""
        prior = load_map(run_dir)
        check_camera(prior, slam)
        slam.loader.drain()
        slam.calibrator, slam.camera_origin = None, f"the map's ({prior.run_dir / 'camera.txt'})"
        slam._use_camera(prior.camera)
        slam.state.segments = [prior.segment]
        slam.loop_closer.rebuild(slam.state.segments)
        slam.bundle_adjuster.restore({**slam.bundle_adjuster.state(), "keyframes_at_last_global": prior.keyframes})
        c = slam.config
        return cls(prior, localize_only, RelocalizerConfig(c.relocalization_candidates, c.tracker.local_keyframes,
                                                           c.tracker.point_descriptor))

    # ----------------------------------------------------------------- one frame
    def seek(self, slam: "Slam", ff, record, timings: dict):
        """A frame while no segment is tracked: relocalized in the map, then tracked there (``Slam._track``);
        else localizing only, lost; else to the initializer (``Slam._initialize``)."""
        st = slam.state
        t = time.perf_counter()
        seg, res = st.resolve_segment(self.prior.segment.id), None
        if len(ff) >= slam.config.tracker.min_inliers:
            res = self.relocalizer.step(ff, seg.slam_map, seg.signatures, -1, slam.tracker)
        timings["relocalize"] = time.perf_counter() - t
        if res is not None and res.relocalized:
            st.segment, st.local_map, st.last_keyframe, st.last_ids = seg, res.local_map, res.keyframe, None
            st.points_at_last_keyframe = seg.slam_map.num_points_observed(
                res.keyframe, slam.config.keyframes.reference_min_observers)
            st.consecutive_lost = 0
            slam.initializer.reset()  # frames buffered for a segment of their own stay unposed
            seg.relocalizations += 1
            self.found += 1
            return slam._track(ff, record, timings)
        if self.localize_only:
            record.status = FrameStatus.LOST
            why = res.reason if res is not None else f"{len(ff)} keypoints"
            return slam._result(record, FrameStatus.LOST, f"not localized in the map: {why}", timings, matches=0)
        return slam._initialize(ff, record, timings)

    def reference(self, slam: "Slam", tr, ff=None, always: bool = False):
        """(The reference keyframe of a tracked frame, its tracking result): the keyframe observing most of its
        tracked points (:attr:`MapReuseConfig.covisible_reference`, ORB-SLAM's reference keyframe), the local
        map moved to it. Localizing only on temporary keyframes (outside the map), every
        ``odometry_relocalize_every`` frames the frame is relocalized in the loaded map too and, found there with
        ``odometry_below`` of its points, tracking goes back to it (ORB-SLAM's localization mode does both while
        on visual odometry)."""
        st = slam.state
        if (ff is not None and self.localize_only and st.last_keyframe in st.segment.slam_map.keyframes
                and st.segment.slam_map.keyframes[st.last_keyframe].frame_index >= 0):
            back = self._back_in_map(slam, ff)
            if back is not None:
                return st.last_keyframe, back
        if always or slam.config.map_reuse.covisible_reference:
            ranked = st.segment.slam_map.covisible_with(np.asarray(tr.point3D_ids, np.int64), limit=1)
            if ranked and int(ranked[0][0]) != st.last_keyframe:
                self._move_to(slam, int(ranked[0][0]))
        return st.last_keyframe, tr

    def _back_in_map(self, slam: "Slam", ff):
        """On visual odometry: the frame relocalized among the loaded keyframes, or None (not due, not found, or
        with fewer than ``odometry_below`` inliers: repeated structure finds a wrong place with a few dozen)."""
        c, st = slam.config.map_reuse, slam.state
        self.odometry_frames += 1
        if c.odometry_relocalize_every <= 0 or self.odometry_frames % c.odometry_relocalize_every:
            return None
        seg = st.segment
        signatures = {i: s for i, s in seg.signatures.items() if seg.slam_map.keyframes[i].frame_index < 0}
        res = self.relocalizer.step(ff, seg.slam_map, signatures, -1, slam.tracker)
        if not res.relocalized or res.tracking.num_inliers < max(c.odometry_below, 1):
            return None
        st.local_map, st.last_keyframe = res.local_map, res.keyframe
        st.points_at_last_keyframe = seg.slam_map.num_points_observed(res.keyframe,
                                                                      slam.config.keyframes.reference_min_observers)
        st.last_ids = res.tracking.point3D_ids
        self.back_in_map += 1
        return res.tracking

    def _move_to(self, slam: "Slam", keyframe: int) -> None:
        st = slam.state
        slam_map = st.segment.slam_map
        st.last_keyframe = keyframe
        st.local_map = slam._local_map(slam_map, keyframe)
        st.points_at_last_keyframe = slam_map.num_points_observed(keyframe,
                                                                  slam.config.keyframes.reference_min_observers)

    def gate(self, slam: "Slam", tr, decision: KeyframeDecision) -> KeyframeDecision:
        """Localizing only, where a keyframe is due: none while the frame tracks ``odometry_below`` or more of the
        loaded map's points (the reference keyframe moves instead, as ORB-SLAM's localization mode updates its
        local keyframes); a temporary one below (visual odometry outside the map, :meth:`drop_temporary`)."""
        c = slam.config.map_reuse
        ids = np.asarray(tr.point3D_ids, np.int64)
        in_map = int(np.count_nonzero(np.isin(ids, self.prior_points)))
        if in_map < c.odometry_below:
            self.temporary += 1
            return replace(decision, reason=f"temporary keyframe (localize-only, {in_map} points of the map tracked "
                                            f"< {c.odometry_below}): {decision.reason}")
        if not c.covisible_reference:
            self.reference(slam, tr, always=True)
        return replace(decision, is_keyframe=False, reason=f"localize-only: {in_map} points of the map tracked, "
                                                           f"tracking against keyframe {slam.state.last_keyframe}")

    def drop_temporary(self, state) -> int:
        """Localizing only, at the end: the map becomes the loaded one again (read again from its run folder);
        frames posed on a temporary keyframe are posed on a loaded one instead, with the same absolute poses
        (loaded keyframes are held in every adjustment, so those anchored to them stay put). Returns the
        temporary keyframes dropped."""
        seg = state.resolve_segment(self.prior.segment.id)
        slam_map = seg.slam_map
        temporary = sorted(i for i, kf in slam_map.keyframes.items() if kf.frame_index >= 0)
        if not temporary:
            return 0
        fresh = load_map(self.prior.run_dir).segment
        anchor = min(fresh.slam_map.keyframes)
        anchor_pose = _pose4(fresh.slam_map, anchor)
        for t in temporary:
            state.reanchor(seg, t, anchor, _pose4(slam_map, t) @ np.linalg.inv(anchor_pose))
        seg.slam_map, seg.signatures = fresh.slam_map, fresh.signatures
        if state.segment is seg:
            state.last_keyframe, state.local_map, state.last_ids = anchor, None, None
        return len(temporary)

    def orient(self, state, candidate: MergeCandidate) -> MergeCandidate:
        """A merge between the map and another segment always moves the other one into the map (the map keeps
        its frame and scale): a candidate whose query segment is the map is turned round."""
        if not state.segments[candidate.segment].prior:
            return candidate
        return MergeCandidate(candidate.candidate_segment, candidate.candidate_image_id, candidate.segment,
                              candidate.query_image_id, candidate.matches, candidate.inliers,
                              np.linalg.inv(candidate.tgt_from_src), candidate.point_pairs[:, ::-1].copy())

    def keep_frame(self, state) -> None:
        """After the final bundle adjustment: the map is moved back to the frame and scale it was loaded in, by
        the Sim(3) that best maps its loaded keyframes' centres now onto where they were loaded
        (``pycolmap.estimate_sim3d``), applied to the map and so to every frame posed in it. Bundle
        adjustment holds two poses of the map fixed (its gauge), local BA its window's neighbours; the other
        loaded keyframes may still move a little as the map grows, and a run in a map must keep its frame."""
        seg = state.resolve_segment(self.prior.segment.id)
        slam_map = seg.slam_map
        ids = [i for i in self.centres if i in slam_map.keyframes]
        if self.localize_only:  # localizing only: the map as loaded, without the temporary keyframes
            self.dropped = self.drop_temporary(state)
            return
        if len(ids) < 3:
            return
        now, was = _centres(slam_map, ids), np.array([self.centres[i] for i in ids])
        sim = pycolmap.estimate_sim3d(np.array([now[i] for i in ids]), was)
        if sim is None:
            return
        slam_map.reconstruction.transform(sim)
        slam_map.moved()  # every point moved
        state.apply_normalization(seg, float(sim.scale))
        moved = _centres(slam_map, ids)
        self.frame_correction = {"scale": float(sim.scale), "keyframes": len(ids),
                                 "residual_rms": float(np.sqrt(np.mean([np.sum((moved[i] - self.centres[i]) ** 2)
                                                                        for i in ids])))}

    # ----------------------------------------------------------------- the outcome
    def summary(self, state) -> dict:
        """What the run did with the map (``summary.json["map"]``), with a line when the video never met it."""
        seg = state.resolve_segment(self.prior.segment.id)
        in_map = sum(1 for r in state.records if r.rel_pose is not None and r.segment >= 0
                     and state.resolve_segment(r.segment) is seg)
        main = state.main_segment
        out = {"run": str(self.prior.run_dir.resolve()), "source": self.prior.source,
               "localize_only": self.localize_only, "segment": seg.id,
               "keyframes_loaded": self.prior.keyframes, "points_loaded": self.prior.points,
               "keyframes": seg.slam_map.num_keyframes, "points3D": seg.slam_map.num_points,
               "frames_in_map": int(in_map), "found_map": int(self.found),
               "main_in_map": main is seg, "frame_correction": self.frame_correction,
               **({"temporary_keyframes": self.temporary, "temporary_dropped": self.dropped,
                                    "back_in_map": self.back_in_map} if self.localize_only
                  else {})}
        if state.records and in_map == 0:
            where = (f"its frames are in a new segment ({main.id})" if main is not None and not self.localize_only
                     else "no frame was posed")
            out["note"] = f"the video never met the map of {self.prior.run_dir}: {where}"
        elif main is not None and main is not seg:
            out["note"] = (f"{in_map} frames are in the map of {self.prior.run_dir}, more in segment {main.id} "
                           "that never met it: trajectory_tum.txt is that segment's")
        return out


def _pose4(slam_map: SlamMap, image_id: int) -> np.ndarray:
    out = np.eye(4)
    out[:3] = slam_map.cam_from_world(image_id).matrix()
    return out


def _centres(slam_map: SlamMap, ids) -> dict[int, np.ndarray]:
    """Image id -> camera centre (world) of keyframes ``ids``."""
    out = {}
    for i in ids:
        m = slam_map.cam_from_world(i).matrix()
        out[i] = -m[:, :3].T @ m[:, 3]
    return out


def check_camera(prior: PriorMap, slam: "Slam") -> None:
    """The new source's images must have the map's size, and its camera (when it has a calibration, or one is
    given) the map's intrinsics; MapError naming both otherwise."""
    src = slam.source.camera
    m = prior.camera
    if (int(src.width), int(src.height)) != (int(m.width), int(m.height)):
        raise _refuse(prior.run_dir, f"its map was made from {m.width}x{m.height} images, this source's are "
                                     f"{src.width}x{src.height}: a map is reused by the same camera only")
    if slam.calibrator is not None:  # no calibration of the source's own: the map's camera is used
        return
    new, old = slam.camera, m
    a, b = np.array([new.fx, new.fy, new.cx, new.cy]), np.array([old.fx, old.fy, old.cx, old.cy])
    if not np.allclose(a, b, rtol=CAMERA_RTOL, atol=1e-3):
        raise _refuse(prior.run_dir, f"its map was made with another camera (fx={old.fx:g} fy={old.fy:g} "
                                     f"cx={old.cx:g} cy={old.cy:g}); this source's is fx={new.fx:g} fy={new.fy:g} "
                                     f"cx={new.cx:g} cy={new.cy:g} ({slam.camera_origin})")


__all__ = ["MapReuse", "MapReuseConfig", "PriorMap", "load_map", "map_config", "check_camera", "SEEK_CANDIDATES"]
