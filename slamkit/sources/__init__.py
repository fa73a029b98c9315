"""Frame sources: one module per dataset layout, and :func:`open_source` to open any of them."""

from .base import FrameSource, ImageListSource
from .euroc import open_euroc
from .folder import open_folder
from .kitti import open_kitti
from .open import detect_layout, open_source
from .sevenscenes import open_sevenscenes
from .tum import open_tum
from .video import VideoSource, open_video

__all__ = [
    "FrameSource",
    "ImageListSource",
    "VideoSource",
    "detect_layout",
    "open_euroc",
    "open_folder",
    "open_kitti",
    "open_sevenscenes",
    "open_source",
    "open_tum",
    "open_video",
]
