"""Rigid-body and two-view helpers, now in :mod:`slamkit.kernels.geometry` (pure numpy, issue 48's kernels
layer); their names stay importable from here."""

from __future__ import annotations

from .kernels.geometry import (flow_score, invert_pose, normalize_quaternion, parallax_deg, pose_from_rows,
                               pose_from_tum, quaternion_from_rotation, rotation_angle_deg, rotation_from_quaternion,
                               tum_from_pose)

__all__ = ["flow_score", "invert_pose", "normalize_quaternion", "parallax_deg", "pose_from_rows", "pose_from_tum",
           "quaternion_from_rotation", "rotation_angle_deg", "rotation_from_quaternion", "tum_from_pose"]
