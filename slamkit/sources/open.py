"""Open any supported sequence from a path or a spec string, detecting its layout.

Specs:
    ``PATH``            layout detected (see :func:`detect_layout`)
    ``tum:PATH``, ``kitti:PATH``, ``7scenes:PATH``, ``euroc:PATH``, ``video:PATH``, ``folder:PATH``
                        layout given explicitly
    ``default``, ``synthetic:...``
                        the synthetic generator (:mod:`slamkit.sources.synthetic`)
"""

from __future__ import annotations

import inspect
import os
import re
from pathlib import Path
from typing import Callable

from ..camera import Intrinsics
from ..errors import ConfigError, SourceError, missing_reason
from .base import CAMERA_IN_SPEC, FrameSource
from .euroc import open_euroc
from .folder import has_glob, open_folder
from .kitti import open_kitti
from .sevenscenes import _COLOR, _SEQ, open_sevenscenes
from .synthetic import open_synthetic
from .tum import open_tum
from .video import VIDEO_EXTENSIONS, open_video

OPENERS: dict[str, Callable[..., FrameSource]] = {
    "tum": open_tum,
    "kitti": open_kitti,
    "7scenes": open_sevenscenes,
    "euroc": open_euroc,
    "video": open_video,
    "folder": open_folder,
}
"""Layout name -> opener ``(path, *, frame_skip, max_frames, ...)``."""

_PREFIX = re.compile(r"^(tum|kitti|7scenes|sevenscenes|euroc|video|folder|synthetic):(.*)$", re.S)


def detect_layout(path: str | Path) -> str:
    """The layout of an existing path: a key of :data:`OPENERS`.

    A file with a video extension -> ``video``; a folder with ``rgb.txt`` -> ``tum``; with ``sequences/``
    or ``image_0``..``image_3`` -> ``kitti``; with ``seq-XX`` folders or
    ``frame-*.color.*`` files -> ``7scenes``; with ``mav0/`` or ``cam0/data.csv`` -> ``euroc``; any other
    folder -> ``folder``. Raises SourceError for a missing path or a file that is not a video.
    """
    p = Path(path).expanduser()
    if not p.exists():
        raise SourceError(f"{p} {missing_reason(p) or 'does not exist'}")
    if not p.is_dir() and not p.is_file():
        raise SourceError(f"{p} is neither a folder nor a video file; give a folder of images, a dataset folder "
                          "or a video")
    if p.is_file():
        if p.suffix.lower() in VIDEO_EXTENSIONS:
            return "video"
        raise SourceError(f"{p} is a file but not a video (known video extensions: {', '.join(VIDEO_EXTENSIONS)})"
                          "; give a folder of images or a dataset folder")
    if (p / "rgb.txt").is_file():
        return "tum"
    if (p / "sequences").is_dir() or any((p / f"image_{i}").is_dir() for i in range(4)):
        return "kitti"  # without calib.txt too: open_kitti then says it is missing
    if (p / "mav0").is_dir() or (p / "cam0" / "data.csv").is_file() or p.name == "mav0":
        return "euroc"
    children = list(p.iterdir())
    if any(c.is_dir() and _SEQ.match(c.name) for c in children) or any(_COLOR.match(c.name) for c in children):
        return "7scenes"
    return "folder"


def _check_kwargs(layout: str, opener: Callable, kw: dict) -> None:
    accepted = [n for n, prm in inspect.signature(opener).parameters.items()
                if prm.kind in (prm.KEYWORD_ONLY, prm.POSITIONAL_OR_KEYWORD) and n != "path" and n != "spec"]
    unknown = sorted(set(kw) - set(accepted))
    if unknown:
        raise ConfigError(f"{layout} sources do not take {', '.join(map(repr, unknown))} "
                          f"(accepted: {', '.join(accepted)})")


def open_source(spec: str | Path, *, frame_skip: int = 1, max_frames: int | None = None,
                camera: Intrinsics | float | str | None = None, **kw) -> FrameSource:
    """Open a frame source from a path or spec string (see the module docstring).

    Args:
        spec: a path (layout detected), ``layout:PATH``, ``default`` or ``synthetic:...``.
        frame_skip, max_frames: keep every ``frame_skip``-th frame, at most ``max_frames``.
        camera: intrinsics used instead of the source's own, applied before the source is opened (so a
            TUM-layout folder whose name does not say freiburg1/2/3 opens): an :class:`Intrinsics`, a focal
            length in pixels, or a ``--camera`` text ``"F"`` / ``"FX,FY,CX,CY[,K1,K2,P1,P2[,K3]]"``; for TUM
            also ``"fr1"``/``"fr2"``/``"fr3"`` (passed as ``calibration``). Without it a ``camera.txt``
            beside the images is read when present (:mod:`~slamkit.sources.calibration`). An empty text
            means none (``SlamConfig.camera``'s default). Not for synthetic sources (ConfigError).
        **kw: options of the layout's opener (e.g. ``sequence="07"`` for KITTI, ``fps=10`` for folders);
            an option the layout does not take raises ConfigError.

    Raises SourceError for a missing path, an empty folder or a folder where no image matched.
    """
    text = str(spec)
    if isinstance(camera, str) and not camera.strip():
        camera = None
    if text == "default" or text.startswith("synthetic:"):
        if camera is not None:
            raise ConfigError(CAMERA_IN_SPEC)
        _check_kwargs("synthetic", open_synthetic, kw)
        return _with_spec(open_synthetic(text, frame_skip=frame_skip, max_frames=max_frames, **kw), text,
                          frame_skip, camera, kw)
    m = _PREFIX.match(text) if not isinstance(spec, Path) else None
    if m is not None:
        layout = "7scenes" if m.group(1) == "sevenscenes" else m.group(1)
        path = Path(m.group(2)).expanduser()
        if not m.group(2):
            raise SourceError(f"spec {text!r} names no path after '{m.group(1)}:'")
    else:
        layout, path = None, Path(text).expanduser()
    if not os.path.exists(path) and has_glob(path.name) and layout in (None, "folder"):
        kw.setdefault("pattern", path.name)
        path, layout = path.parent, "folder"
    if not os.path.exists(path):  # False for any path the OS refuses (too long a name, a symlink loop, ...)
        raise SourceError(f"{path} {missing_reason(path) or 'does not exist'}")
    if layout is None:
        layout = detect_layout(path)
    opener = OPENERS[layout]
    if camera is not None:
        kw["calibration" if layout == "tum" else "camera"] = camera
    _check_kwargs(layout, opener, kw)
    return _with_spec(opener(path, frame_skip=frame_skip, max_frames=max_frames, **kw), text, frame_skip, camera, kw)


def _with_spec(source: FrameSource, text: str, frame_skip: int, camera, kw: dict) -> FrameSource:
    """``source`` with ``source.spec = text`` when ``open_source(text)`` reopens it (its frames, or more of them
    with ``max_frames``): recorded in a saved run, so ``slamkit run --resume`` and ``slamkit export`` find it."""
    if frame_skip == 1 and camera is None and not kw:
        source.spec = text
    return source
