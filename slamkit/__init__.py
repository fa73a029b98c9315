"""slamkit: offline monocular visual SLAM with COLMAP's machinery, step by step."""

from .camera import Intrinsics
from .errors import SlamkitError
from .sources import open_source
from .types import Frame, Trajectory

__version__ = "0.1.0"

__all__ = ["Intrinsics", "SlamkitError", "Frame", "Trajectory", "open_source", "__version__"]
