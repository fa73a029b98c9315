"""What the map view shows and how: :class:`ViewSettings` (changed at any time by ``MapView.configure``)."""

from __future__ import annotations

from dataclasses import dataclass

from .scene import hex_to_rgb255

POINT_FRACTION = 0.015
"""Default point diameter: 1.5 % of the median distance from a map point to its nearest camera (at that
distance a point spans about 1 % of a 640-pixel-wide image with a 60-degree field of view; in the
overview, 3 to 6 pixels)."""

COLOR_MODES = ("height", "image")
"""How map points are coloured: by their height in the view (the walls of a room, the facades of a street read
from above) or in their image colours."""

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
    """Frustum depth as a multiple of 1/40 of the map's extent (the 5-95 % box of points and cameras), in map
    units: a monocular map's unit is arbitrary (not a metre) until it is aligned to ground truth."""
    color_by: str = "height"
    """Map point colours: ``"height"`` (low dark blue → high yellow, the 5-95 % range of the map's heights in the
    view, z up) or ``"image"`` (the colour of the pixel they were triangulated from)."""
    point_size: float = 1.0
    """Point diameter as a multiple of :data:`POINT_FRACTION` of the median distance from a map point to its
    nearest camera, map units (so points look alike on any map, whatever its scale)."""
    track_point: int = -1
    """Draw lines from this 3D point id to every keyframe observing it (-1 = none)."""
    clip: tuple[int, int] | None = None
    """(first, last) keyframe image ids, inclusive: only points, cameras and tracks introduced between them."""

    def validate(self) -> "ViewSettings":
        hex_to_rgb255(self.background)
        if self.color_by not in COLOR_MODES:
            raise ValueError(f"color_by must be one of {', '.join(COLOR_MODES)}, got {self.color_by!r}")
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

    def point_diameter(self, view_depth: float) -> float:
        """Diameter of the map points, map units, for a median point-to-nearest-camera distance ``view_depth``
        (map units)."""
        return POINT_FRACTION * view_depth * self.point_size


__all__ = ["ViewSettings", "PARTS", "POINT_FRACTION", "COLOR_MODES"]
