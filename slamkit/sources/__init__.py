"""Frame sources: one module per dataset layout, and :func:`open_source` to open any of them."""

from .base import FrameSource, ImageListSource

__all__ = ["FrameSource", "ImageListSource"]
