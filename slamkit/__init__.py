"""slamkit: offline monocular visual SLAM with COLMAP's machinery, step by step."""

from .camera import Intrinsics
from .errors import SlamkitError
from .types import Frame, Trajectory

__version__ = "0.1.0"

__all__ = ["Intrinsics", "SlamkitError", "Frame", "Trajectory", "__version__"]
