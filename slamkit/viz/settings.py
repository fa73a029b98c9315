"""What the map view shows and how: :class:`ViewSettings` (changed at any time by ``MapView.configure``)."""

from __future__ import annotations

from dataclasses import dataclass

from .scene import DISPLAY_EXTENT, hex_to_rgb255

PARTS = ("points", "keyframes", "path", "current", "directions")
"""The parts of the map that can be shown or hidden (a ``show_<part>`` field each)."""


@dataclass(frozen=True)
class ViewSettings:
    """What the map view shows and how (all of it can change at any time with :meth:`MapView.configure`)."""

    background: str = "#ffffff"
    """Background colour, '#rrggbb'."""
    show_points: bool = True
    show_keyframes: bool = True
    """Keyframe frustums."""
    show_path: bool = True
    """The camera path through every posed frame."""
    show_current: bool = True
    """The current (tracked, non-key) frame's frustum, in blue."""
    show_directions: bool = False
    """A viewing-direction vector (optical axis) from every keyframe."""
    frustum_scale: float = 1.0
    """Frustum size as a multiple of 1/40 of the map extent."""
    point_size: float = 1.0
    """Point size as a multiple of 1/120 of the map extent (in the viewer: 0.05 of its 6 units)."""
    track_point: int = -1
    """Draw lines from this 3D point id to every keyframe observing it (-1 = none)."""
    clip: tuple[int, int] | None = None
    """(first, last) keyframe image ids, inclusive: only points, cameras and tracks introduced between them."""

    def validate(self) -> "ViewSettings":
        hex_to_rgb255(self.background)
        if not self.frustum_scale > 0 or not self.point_size > 0:
            raise ValueError("frustum_scale and point_size must be > 0")
        if self.clip is not None and (len(self.clip) != 2 or self.clip[0] > self.clip[1]):
            raise ValueError(f"clip must be (first, last) with first <= last, got {self.clip!r}")
        return self

    def visibility(self) -> dict[str, bool]:
        """Part of the map -> shown, in the order of :data:`PARTS`."""
        return {name: bool(getattr(self, f"show_{name}")) for name in PARTS}

    def in_clip(self, keyframe_id: int) -> bool:
        """Whether a keyframe (or the point group it introduced) is inside the clip range."""
        return self.clip is None or self.clip[0] <= keyframe_id <= self.clip[1]

    def frustum_depth(self, map_extent: float) -> float:
        """Depth of the keyframe frustums, map units."""
        return map_extent / 40.0 * self.frustum_scale

    @property
    def point_size_units(self) -> float:
        """Size of the map points in viewer units (point sizes ignore the scale of the view's transform)."""
        return DISPLAY_EXTENT / 120.0 * self.point_size


__all__ = ["ViewSettings", "PARTS"]
