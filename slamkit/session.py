"""Sessions: everything a :class:`~slamkit.pipeline.Slam` needs to continue a run, in open formats.

A session is a folder of COLMAP binary models, JSON and ``.npz`` arrays (read with ``allow_pickle=False``;
no pickle anywhere). ``slam.save(DIR)`` writes one to ``DIR/session/`` beside the run outputs;
:func:`save_session` writes one on its own. :func:`load_session` (``Slam.resume``) rebuilds the Slam, which
continues at the next frame exactly as the uninterrupted run would::

    session.json            format version, source identity and spec, config, pipeline counters, frame
                            records (without poses), step errors, segments, keyframe bookkeeping, the
                            initializer's window, the local map and the bundle-adjustment counter
    state.npz               per-frame relative poses (N, 4, 4), the local map (point ids, positions,
                            descriptors), the last tracked point ids, the initializer's buffered features and
                            window matches, the PnP correspondences of the tracked frames (final pose refinement),
                            the rotation phase's previous frame (its features: a pan's next rotation reference)
    segment_XX/model/       the segment's pycolmap Reconstruction (COLMAP binary, ``pycolmap.Reconstruction(d)``)
    segment_XX/arrays.npz   keyframe features (keypoints, descriptors, scores, sizes), colours, thumbnails,
                            relocalization signatures, the features of frames ``finish()`` tracks again, and the
                            correspondence graph as image pairs in insertion order with their matches

Besides the model, three things a COLMAP model does not hold are restored so that the continuation is
bit-identical (checked by ``tests/test_session.py``): the order in which frames were registered
(``Reconstruction.normalize`` averages camera centres in that order), the largest 3D point id ever given
(new points get the ids they would have had), and the ``CorrespondenceGraph``, replayed pair by pair in the
order that reproduces every keypoint's correspondence list (the triangulator reads them in that order; the
order is recovered from the lists themselves). ``ObservationManager`` rebuilds its statistics from the model
and the graph; ``IncrementalTriangulator`` clears its caches on every call and keeps only the set of tracks
modified since the last bundle adjustment (non-empty between initialization and the first keyframe), which
is saved and restored.

Interruption: :func:`slamkit.interrupt.deferred_interrupt` (re-exported here) holds Ctrl-C, SIGTERM and SIGHUP
back until the current SLAM step is complete, so the state is always that of whole frames and can be saved.

Before anything is read, :func:`slamkit.io.saved.check_session` checks the files against the sizes and
checksums recorded when the session was saved, and the COLMAP binaries, JSON and ``.npz`` files against their
formats: a truncated or damaged file is a SessionError naming it, never a hang inside pycolmap's reader.
Then the source proves it is the one the run read (issue 50, :func:`check_frames_read`): its kind and identity,
and every processed frame measured again against the fingerprint taken when the run read it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import tempfile
import time
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np
import pycolmap

from .camera import Intrinsics
from .config import SlamConfig
from .errors import ConfigError, SessionError, SlamkitError  # noqa: F401 - SessionError lived here
from .features import Features, FrameFeatures
from .interrupt import deferred_interrupt  # noqa: F401 - re-exported: it lived here
from .io.atomic import atomic_dir
from .io.run_dir import SESSION_MARKER, check_output, out_dir_lock, write_manifest
from .io.saved import check_session
from .local_map import LocalMap
from .loop_verification import ConsistentGroup
from .map import CAMERA_ID, Keyframe, SlamMap, graph_pairs, max_point3D_id
from .run_camera import clamped, with_radial
from .map import max_point3D_id as _max_point3D_id  # noqa: F401  (its name here before it moved to map)
from .source_proof import check_frames_read, check_source as _check_source, source_identity  # noqa: F401
from .stages.initializer import InitializerWindow
from .state import FrameRecord, RecentPoints, Segment, SlamState

if TYPE_CHECKING:  # pragma: no cover
    from .pipeline import Slam

FORMAT = "slamkit-session"
VERSION = 1
SESSION_FILE = "session.json"
SESSION_DIR = "session"
"""Name of the session folder inside a saved run folder."""

STRUCTURAL_FIELDS = ("features", "matcher", "frame_skip", "camera")
"""Config fields the saved state depends on: a resumed run cannot change them (the intrinsics are part of the
saved map: its points were triangulated with them)."""

_STATE_SAVED_AS = {"cursor": "_cursor", "points_at_last_keyframe": "_points_at_last_keyframe",
                   "consecutive_lost": "_consecutive_lost", "init_message": "_init_message"}
"""Keys of :class:`~slamkit.state.SlamState` scalars in ``session.json["state"]`` that differ from the field
names: the names they had as Slam attributes, so sessions written before the state was a value still load.
Every other scalar field is saved under its own name, so a new counter in the state survives a resume."""


# ----------------------------------------------------------------------------------------------- saving
def save_session(slam: "Slam", out_dir: str | Path) -> Path:
    """Write ``slam``'s session to ``out_dir`` (replaced atomically); returns the folder."""
    out_dir = check_output(out_dir, "session", [getattr(slam, "source_spec", None), slam.source], flag="out_dir")
    with out_dir_lock(out_dir, flag="out_dir", what="session folder"), atomic_dir(out_dir, kind="session") as tmp:
        write_session(slam, tmp)
        write_manifest(tmp, SESSION_MARKER)  # sizes and checksums, checked before it is read
    return out_dir


def write_session(slam: "Slam", folder: str | Path) -> None:
    """Write the session files into ``folder`` (created if needed; not atomic by itself — :func:`save_session`
    and :func:`slamkit.io.save_run` call it inside a temporary folder). ``session.json`` is written last.

    A finished run (:meth:`Slam.finish`: final global BA, frames tracked again) is saved as it was just
    before ``finish()`` (:func:`unfinished_snapshot`), marked ``"finished": true``: resumed with more frames
    it continues exactly as an uninterrupted longer run; resumed as it is, ``finish()`` runs again on load.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    snapshot = getattr(slam, "unfinished_session", None) if slam.finished else None
    if snapshot is not None:
        for rel, data in snapshot.items():
            if rel != SESSION_FILE:
                (folder / rel).parent.mkdir(parents=True, exist_ok=True)
                (folder / rel).write_bytes(data)
        meta = json.loads(snapshot[SESSION_FILE])
        (folder / SESSION_FILE).write_text(json.dumps({**meta, "finished": True}, indent=1))
        return
    _write_state_files(slam, folder)


def unfinished_snapshot(slam: "Slam") -> dict[str, bytes]:
    """The session files of ``slam`` as they are now (relative path -> bytes): taken by :meth:`Slam.finish`
    before its final BA, written by :func:`write_session` in place of the finished state. Costs one session's
    size in memory, nothing on disk (a run folder still holds one session)."""
    with tempfile.TemporaryDirectory(prefix="slamkit-session-") as tmp:
        _write_state_files(slam, Path(tmp))
        return {p.relative_to(tmp).as_posix(): p.read_bytes() for p in sorted(Path(tmp).rglob("*")) if p.is_file()}


def _write_state_files(slam: "Slam", folder: Path) -> None:
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] = {
        "format": FORMAT, "version": VERSION, "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "source": {**source_identity(slam.source), "spec": getattr(slam, "source_spec", None)},
        "config": slam.config.to_dict(),
        **_state_to(slam.state, arrays, folder),
        "bundle_adjuster": slam.bundle_adjuster.state(),
        "initializer": _window_to(slam.initializer.window, arrays),
        "self_calibration": slam.calibrator.state() if getattr(slam, "calibrator", None) is not None else None,
        "camera_dist": list(slam.camera.dist),  # a given camera's k1 estimated in the run (calibrate_radial)
        "pose_refiner": _refiner_to(slam.pose_refiner, arrays),
        "rotation_phase": _rotation_phase_to(slam.rotation_phase, arrays),
    }
    np.savez(folder / "state.npz", **arrays)
    (folder / SESSION_FILE).write_text(json.dumps(meta, indent=1, default=_json_default))


def _state_to(state: SlamState, arrays: dict, folder: Path) -> dict:
    """The state's fields as session.json entries (arrays into ``arrays``, segments into their folders)."""
    meta: dict[str, Any] = {"state": {}}
    for f in dataclasses.fields(state):
        name, value = f.name, getattr(state, f.name)
        if name == "records":
            meta["records"] = _records_to(value, arrays)
        elif name == "segments":
            meta["segments"] = [_write_segment(seg, folder / f"segment_{seg.id:02d}") for seg in value]
        elif name == "segment":
            meta["current_segment"] = value.id if value is not None else None
        elif name == "local_map":
            meta["local_map"] = _local_map_to(value, arrays) if value is not None else None
        elif name == "last_ids":
            if value is not None:
                arrays["last_ids"] = np.asarray(value)
        elif name in ("timings", "errors"):
            meta[name] = {str(k): v for k, v in value.items()}
        elif name == "loop_groups":
            meta[name] = [{"keyframes": sorted(int(k) for k in g.keyframes), "consistency": int(g.consistency)}
                          for g in value]
        elif name in ("loop_closures", "map_merges"):
            meta[name] = [dict(c) for c in value]
        elif value is None or isinstance(value, (bool, int, float, str)):
            meta["state"][_STATE_SAVED_AS.get(name, name)] = value
        else:  # a new kind of field: give it a format here, it must not be lost silently
            raise TypeError(f"session: SlamState.{name} ({type(value).__name__}) has no session format")
    return meta


def _refiner_to(refiner, arrays: dict) -> list[dict]:
    """The PnP correspondences the final pose refinement will use (``stages.pose_refinement``)."""
    entries, xy, ids = refiner.state()
    _put_list(arrays, "refine_xy", xy)
    _put_list(arrays, "refine_ids", ids)
    return entries


def _rotation_phase_to(phase, arrays: dict) -> dict:
    """The rotation phase's previous frame (``RotationPhase.state``): a lost frame's second rotation reference."""
    previous = phase.state()
    return {"previous": _frame_features_to([previous] if previous is not None else [], "rotation_previous", arrays)}


def _window_to(window: InitializerWindow, arrays: dict) -> dict:
    _put_list(arrays, "init_matches", list(window.matches.values()))
    return {"frames": _frame_features_to(window.frames, "init_frames", arrays),
            "history": _frame_features_to(window.history, "init_history", arrays),
            "matches": [list(k) for k in window.matches]}


def _write_segment(seg, folder: Path) -> dict:
    slam_map: SlamMap = seg.slam_map
    rec = slam_map.reconstruction
    (folder / "model").mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(folder / "model"))
    arrays: dict[str, np.ndarray] = {}
    kfs = list(slam_map.keyframes.values())
    pairs, matches = graph_pairs(slam_map)
    arrays["graph_pairs"] = np.asarray(pairs, np.int64).reshape(-1, 2)
    _put_list(arrays, "graph_matches", matches)
    sig_ids = list(seg.signatures)
    _put_list(arrays, "signatures", [seg.signatures[i] for i in sig_ids])
    arrays["recent_points"] = seg.recent_points.as_array()
    meta = {
        "id": seg.id,
        "frames": [int(i) for i in seg.frames],
        "relocalizations": int(seg.relocalizations),
        "extra": {f.name: getattr(seg, f.name) for f in dataclasses.fields(seg)
                  if f.name not in ("id", "slam_map", "frames", "initial_frames", "signatures", "relocalizations",
                                    "recent_points")
                  and isinstance(getattr(seg, f.name), (bool, int, float, str, type(None)))},
        "signature_image_ids": [int(i) for i in sig_ids],
        "recent_point_steps": int(seg.recent_points.steps),
        "keyframes": [{"image_id": kf.image_id, "frame_index": kf.frame_index, "timestamp": kf.timestamp}
                      for kf in kfs],
        "keyframe_features": _features_to([(kf.features, kf.keypoints, kf.colors, kf.thumbnail, None) for kf in kfs],
                                          "kf", arrays),
        "initial_frames": _frame_features_to(seg.initial_frames, "initial", arrays),
        "registration_order": [int(i) for i in rec.reg_frame_ids()],
        "max_point3D_id": max_point3D_id(rec),
        "modified_points3D": sorted(int(i) for i in slam_map.triangulator.get_modified_points3D()),
        "next_image_id": int(slam_map.next_image_id),
        "pending": slam_map.pending_image_ids,
        "triangulation": slam_map.triangulation.todict(),
        "camera": slam_map.camera.to_dict(),
    }
    np.savez(folder / "arrays.npz", **arrays)
    return meta


# ----------------------------------------------------------------------------------------------- loading
def find_session(path: str | Path) -> Path | None:
    """The session folder of ``path``: ``path`` itself when it holds ``session.json``, or ``path/session``."""
    path = Path(path)
    for candidate in (path, path / SESSION_DIR):
        if (candidate / SESSION_FILE).is_file():
            return candidate
    return None


def load_session(path: str | Path, source=None, config: SlamConfig | dict | str | None = None,
                 callbacks=None, cls=None) -> "Slam":
    """Rebuild the Slam saved in ``path`` (a session folder or a run folder holding ``session/``).

    source: the frame source (or spec); None opens the spec the session recorded. It must be the source the
        session was recorded on (same kind, name, frame count, frame ids and timestamps, camera, and every frame
        processed so far the image the run read: :func:`check_frames_read`): else SessionError, before any
        frame is processed.
    config: None = the saved config; a dict = overrides of the saved config (``SlamConfig.with_overrides``
        keys: the explicit way to change a parameter); a SlamConfig (or preset name) must equal the saved one.
        ``features``, ``matcher`` and ``frame_skip`` cannot change (ConfigError).
    """
    if cls is None:  # the session layer does not import the pipeline built on it
        raise TypeError("load_session needs the Slam class (cls=); use Slam.resume(path)")
    folder = find_session(path)
    if folder is None:
        raise SessionError(f"{path}: no session found (expected {Path(path) / SESSION_DIR / SESSION_FILE}; "
                           "a run saved with slam.save() or `slamkit run --out` has one)")
    check_session(folder)  # sizes, checksums and formats first: a damaged file never reaches pycolmap's reader
    try:
        meta = json.loads((folder / SESSION_FILE).read_text())
    except (OSError, ValueError) as e:
        raise SessionError(f"{folder / SESSION_FILE}: cannot be read ({e})") from None
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise SessionError(f"{folder / SESSION_FILE}: not a slamkit session of version {VERSION} "
                           f"(format {meta.get('format')!r}, version {meta.get('version')!r})")
    try:
        saved_config = SlamConfig.from_dict(meta["config"])
    except (KeyError, TypeError, AttributeError) as e:  # ConfigError (a bad value) names the value itself
        raise _unreadable(folder, e) from None
    cfg = _resolve_config(saved_config, config, folder)
    if source is None:
        source = meta["source"].get("spec")
        if source is None:
            raise SessionError(f"{folder}: the session does not record how to open its source "
                               f"({meta['source']['name']!r}); pass source=")
    slam = cls(source, cfg, callbacks)
    _check_source(meta["source"], slam.source, folder)
    if meta["source"].get("spec") and getattr(slam, "source_spec", None) is None:
        slam.source_spec = meta["source"]["spec"]
    try:
        cursor = int(meta["state"]["_cursor"])
    except (KeyError, TypeError, ValueError) as e:
        raise _unreadable(folder, e) from None
    if cursor > len(slam.indices):
        raise ConfigError(f"{folder}: the session processed {cursor} frames but this configuration selects "
                          f"{len(slam.indices)} (max_frames={cfg.max_frames}); raise max_frames")
    try:
        proven = check_frames_read(meta, slam.source, slam.indices, folder)  # before one frame is processed
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise _unreadable(folder, e) from None
    with _npz(folder / "state.npz") as arrays:
        try:
            _restore(slam, meta, arrays, folder)
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:  # edited by hand, or older
            raise _unreadable(folder, e) from None
    for rec in slam.state.records:  # a session of an older slamkit: the fingerprints frames.csv held, now proven
        if not rec.sha256 and rec.index in proven:
            rec.read_from(proven[rec.index])
    if not slam.done:
        if slam.finished:  # saved after finish() without the state before it (sessions of older versions)
            raise SessionError(
                f"{folder}: this run was saved after its final bundle adjustment without the state before it, "
                f"so it cannot be extended to {len(slam.indices)} frames as a longer run would be; run it again "
                f"over all frames instead (slamkit run SOURCE --max-frames {len(slam.indices)} --out NEW_FOLDER)")
        slam.finished = False  # more frames to come (max_frames raised): finish() runs at the end
    elif meta.get("finished") and not slam.finished:
        slam.finish()  # the saved run was finished: the same final BA and re-tracking again
    return slam


def _unreadable(folder: Path, e: BaseException) -> SessionError:
    what = f"entry {e.args[0]!r} is missing" if isinstance(e, KeyError) else f"{type(e).__name__}: {e}"
    return SessionError(f"{folder / SESSION_FILE}: not a session this slamkit can read ({what}); it was edited "
                        "or written by another version — start a new run (slamkit run SOURCE --out NEW_FOLDER)")


def _resolve_config(saved: SlamConfig, config, folder: Path) -> SlamConfig:
    if config is None:
        return saved
    if isinstance(config, dict):
        cfg = saved.with_overrides(**config)
    else:
        cfg = SlamConfig.preset(config) if isinstance(config, str) else config.validate()
        diff = _config_diff(saved.to_dict(), cfg.to_dict())
        if diff:
            raise ConfigError(f"{folder}: the config differs from the session's in {', '.join(diff)}; pass "
                              "config=None to continue with the saved one, or a dict of the values to override")
    for name in STRUCTURAL_FIELDS:
        if getattr(cfg, name) != getattr(saved, name):
            raise ConfigError(f"{folder}: {name} cannot change when resuming (session: {getattr(saved, name)!r}, "
                              f"given: {getattr(cfg, name)!r}); the saved map and frame records depend on it")
    return cfg


def _config_diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(a) | set(b)):
        if isinstance(a.get(k), dict) and isinstance(b.get(k), dict):
            out += _config_diff(a[k], b[k], f"{prefix}{k}.")
        elif a.get(k) != b.get(k):
            out.append(f"{prefix}{k} ({a.get(k)!r} -> {b.get(k)!r})")
    return out


def _restore(slam: "Slam", meta: dict, arrays: dict, folder: Path) -> None:
    slam.state = _state_from(meta, arrays, folder, slam.camera)
    slam.bundle_adjuster.restore(meta["bundle_adjuster"])
    cal = meta.get("self_calibration")
    if cal is not None and slam.calibrator is not None:  # the estimate goes on from where it was
        slam.calibrator.restore(cal)
        if slam.calibrator.focal is not None:
            seg = slam.state.segment or slam.state.main_segment  # its map holds the principal point in use
            cam = seg.slam_map.camera if seg is not None else slam.camera
            slam._use_camera(with_radial(clamped(slam.camera, slam.calibrator.focal, cam.cx, cam.cy),
                                         slam.calibrator.k1))
    elif slam.calibrator is None and meta.get("camera_dist") not in (None, list(slam.camera.dist)):
        slam._use_camera(dataclasses.replace(slam.camera, dist=tuple(float(v) for v in meta["camera_dist"])))
    slam.loop_closer.rebuild(slam.state.segments)  # derived from the keyframes: the same bags, the same scores
    if meta.get("pose_refiner") is not None:  # sessions saved before it: the earlier frames keep tracked poses
        slam.pose_refiner.restore(meta["pose_refiner"], _get_list(arrays, "refine_xy"), _get_list(arrays, "refine_ids"))
    rmeta = meta.get("rotation_phase")  # sessions saved before issue 50: none (the keyframe alone then)
    if rmeta is not None:
        previous = _frame_features_from(rmeta["previous"], "rotation_previous", arrays)
        slam.rotation_phase.restore(previous[0] if previous else None)
    imeta = meta["initializer"]
    slam.initializer.restore(InitializerWindow(
        _frame_features_from(imeta["frames"], "init_frames", arrays),
        _frame_features_from(imeta["history"], "init_history", arrays),
        {(int(a), int(b)): m for (a, b), m in zip(imeta["matches"], _get_list(arrays, "init_matches"))}))


def _state_from(meta: dict, arrays: dict, folder: Path, camera: Intrinsics) -> SlamState:
    """The :class:`SlamState` that :func:`_state_to` wrote, field by field."""
    saved = {**meta.get("extra", {}), **meta["state"]}  # version-1 sessions hold _init_message in "extra"
    values: dict[str, Any] = {}
    for f in dataclasses.fields(SlamState):
        name = f.name
        if name == "records":
            values[name] = _records_from(FrameRecord, meta["records"], arrays)
        elif name == "segments":
            values[name] = [_read_segment(camera, smeta, folder / f"segment_{smeta['id']:02d}")
                            for smeta in meta["segments"]]
        elif name == "local_map":
            values[name] = _local_map_from(meta["local_map"], arrays)
        elif name == "last_ids":
            values[name] = arrays.get("last_ids")
        elif name == "timings":
            values[name] = dict(meta["timings"])
        elif name == "errors":
            values[name] = {int(k): v for k, v in meta.get("errors", {}).items()}
        elif name == "loop_groups":  # sessions saved before loop closing have none
            values[name] = tuple(ConsistentGroup(frozenset(g["keyframes"]), int(g["consistency"]))
                                 for g in meta.get(name, []))
        elif name in ("loop_closures", "map_merges"):  # sessions saved before loop closing have none
            values[name] = [dict(c) for c in meta.get(name, [])]
        elif name != "segment" and _STATE_SAVED_AS.get(name, name) in saved:
            values[name] = saved[_STATE_SAVED_AS.get(name, name)]
    state = SlamState(**values)
    cur = meta["current_segment"]
    state.segment = state.segments[cur] if cur is not None else None
    return state


def _read_segment(camera: Intrinsics, smeta: dict, seg_folder: Path) -> Segment:
    with _npz(seg_folder / "arrays.npz") as seg_arrays:
        slam_map = _restore_map(camera, smeta, seg_arrays, seg_folder)
        sigs = _get_list(seg_arrays, "signatures")
        initial = _frame_features_from(smeta["initial_frames"], "initial", seg_arrays)
        recent = RecentPoints.from_array(seg_arrays["recent_points"] if "recent_points" in seg_arrays
                                         else np.empty((0, 4)), smeta.get("recent_point_steps", 0))
    seg = Segment(int(smeta["id"]), slam_map, frames=list(smeta["frames"]), initial_frames=initial,
                  signatures=dict(zip(smeta["signature_image_ids"], sigs)),
                  relocalizations=int(smeta["relocalizations"]), recent_points=recent)
    for k, v in smeta.get("extra", {}).items():
        setattr(seg, k, v)
    return seg


def _restore_map(camera: Intrinsics, meta: dict, arrays: dict, folder: Path) -> SlamMap:
    """A SlamMap equal to the saved one: the model rebuilt image by image in id order (frames registered in
    the saved order, points with their ids), the graph replayed, then observations and triangulator wired."""
    try:
        saved = pycolmap.Reconstruction(str(folder / "model"))
    except Exception as e:  # noqa: BLE001 - pycolmap raises plain RuntimeError/ValueError
        raise SessionError(f"{folder / 'model'}: COLMAP model cannot be read ({e})") from None
    tri = pycolmap.IncrementalTriangulatorOptions()
    tri.mergedict(meta["triangulation"])
    slam_map = SlamMap(Intrinsics.from_dict(meta["camera"]), tri)
    slam_map.reconstruction.camera(CAMERA_ID).params = saved.camera(CAMERA_ID).params  # refined, if any
    slam_map.refill(saved, sorted(saved.images), arrays["graph_pairs"].tolist(), _get_list(arrays, "graph_matches"),
                    meta["registration_order"], int(meta["max_point3D_id"]), meta["modified_points3D"])
    feats = _features_from(meta["keyframe_features"], "kf", arrays)
    for kmeta, (features, keypoints, colors, thumbnail, _) in zip(meta["keyframes"], feats):
        kf = Keyframe(int(kmeta["image_id"]), int(kmeta["frame_index"]), float(kmeta["timestamp"]), keypoints,
                      features, colors, thumbnail)
        slam_map.keyframes[kf.image_id] = kf
    slam_map.next_image_id = int(meta["next_image_id"])
    return slam_map


# ----------------------------------------------------------------------------------------------- arrays
def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, (tuple, set)):
        return list(x)
    raise TypeError(f"session: {type(x).__name__} is not JSON-serialisable")


@contextlib.contextmanager
def _npz(path: Path) -> Iterator[dict]:
    try:
        with np.load(path, allow_pickle=False) as z:
            yield {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise SessionError(f"{path}: cannot be read ({type(e).__name__}: {e})") from None


def _put_list(arrays: dict, name: str, values: list) -> None:
    """Store a list of arrays (any shapes, one dtype, or None) as ``name__shape`` (K, ndim), -1 rows for None,
    and ``name__data`` (everything flattened and concatenated)."""
    present = [np.asarray(v) for v in values if v is not None]
    ndim = max((v.ndim for v in present), default=1)
    shapes = np.full((len(values), ndim), -1, np.int64)
    for k, v in enumerate(values):
        if v is not None:
            shapes[k] = np.asarray(v).shape
    arrays[f"{name}__shape"] = shapes
    arrays[f"{name}__data"] = np.concatenate([v.ravel() for v in present]) if present else np.empty(0)


def _get_list(arrays: dict, name: str) -> list:
    shapes, data = arrays[f"{name}__shape"], arrays[f"{name}__data"]
    out, at = [], 0
    for shape in shapes:
        if shape[0] < 0:
            out.append(None)
            continue
        n = int(np.prod(shape))
        out.append(data[at:at + n].reshape(tuple(int(s) for s in shape)).copy())
        at += n
    return out


_FEATURE_LISTS = ("raw_keypoints", "descriptors", "scores", "sizes", "keypoints", "colors", "thumbnail", "signature")


def _features_to(items: list[tuple], prefix: str, arrays: dict) -> list[dict]:
    """items: (Features, keypoints (N, 2) undistorted, colors (N, 3), thumbnail or None, signature or None)."""
    cols = {name: [] for name in _FEATURE_LISTS}
    meta = []
    for feats, kp, colors, thumb, sig in items:
        for name, v in zip(_FEATURE_LISTS, (feats.keypoints, feats.descriptors, feats.scores, feats.sizes, kp,
                                            colors, thumb, sig)):
            cols[name].append(v)
        meta.append({"binary": bool(feats.binary),
                     "image_size": list(feats.image_size) if feats.image_size is not None else None})
    for name, values in cols.items():
        _put_list(arrays, f"{prefix}_{name}", values)
    return meta


def _features_from(meta: list[dict], prefix: str, arrays: dict) -> list[tuple]:
    cols = {name: _get_list(arrays, f"{prefix}_{name}") for name in _FEATURE_LISTS}
    out = []
    for k, m in enumerate(meta):
        size = tuple(int(s) for s in m["image_size"]) if m["image_size"] is not None else None
        feats = Features(cols["raw_keypoints"][k], cols["descriptors"][k], cols["scores"][k], bool(m["binary"]),
                         cols["sizes"][k], size)
        out.append((feats, cols["keypoints"][k], cols["colors"][k], cols["thumbnail"][k], cols["signature"][k]))
    return out


def _frame_features_to(frames: list[FrameFeatures], prefix: str, arrays: dict) -> list[dict]:
    meta = _features_to([(f.features, f.keypoints, f.colors, f.thumbnail, f.signature) for f in frames], prefix,
                        arrays)
    return [{"index": int(f.index), "frame_id": int(f.frame_id), "timestamp": float(f.timestamp), **m}
            for f, m in zip(frames, meta)]


def _frame_features_from(meta: list[dict], prefix: str, arrays: dict) -> list[FrameFeatures]:
    return [FrameFeatures(int(m["index"]), int(m["frame_id"]), float(m["timestamp"]), feats, kp, colors, thumb, sig)
            for m, (feats, kp, colors, thumb, sig) in zip(meta, _features_from(meta, prefix, arrays))]


def _records_to(records: list, arrays: dict) -> dict:
    """Frame records as JSON columns, array fields (the relative pose) as ``records__<field>`` lists."""
    cols: dict[str, list] = {}
    names = [f.name for f in dataclasses.fields(records[0])] if records else []
    for name in names:
        values = [getattr(r, name) for r in records]
        if any(isinstance(v, np.ndarray) for v in values):
            _put_list(arrays, f"records__{name}", values)
            cols[name] = "array"
        else:
            cols[name] = [v.item() if isinstance(v, np.generic) else v for v in values]
    return {"count": len(records), "columns": cols}


def _records_from(record_cls, meta: dict, arrays: dict) -> list:
    cols = {name: (_get_list(arrays, f"records__{name}") if values == "array" else values)
            for name, values in meta["columns"].items()}
    return [record_cls(**{name: values[i] for name, values in cols.items()}) for i in range(meta["count"])]


def _local_map_from(meta: dict | None, arrays: dict) -> LocalMap | None:
    if meta is None:
        return None
    return LocalMap(arrays["local_map__ids"], arrays["local_map__xyz"], arrays["local_map__descriptors"],
                    bool(meta["binary"]), int(meta["ref_image_id"]), arrays["local_map__ref_ids"],
                    arrays["local_map__ref_xy"], [int(i) for i in meta["keyframe_ids"]])


def _local_map_to(lm, arrays: dict) -> dict:
    for name in ("ids", "xyz", "descriptors", "ref_ids", "ref_xy"):
        arrays[f"local_map__{name}"] = np.asarray(getattr(lm, name))
    return {"binary": bool(lm.binary), "ref_image_id": int(lm.ref_image_id),
            "keyframe_ids": [int(i) for i in lm.keyframe_ids]}
