"""Reading and writing files: trajectories (TUM, KITTI) and atomic writes."""

from .atomic import atomic_dir, atomic_write_bytes, atomic_write_text
from .trajectory import read_kitti, read_trajectory, read_tum, write_kitti, write_tum

__all__ = [
    "atomic_dir", "atomic_write_bytes", "atomic_write_text",
    "read_kitti", "read_trajectory", "read_tum", "write_kitti", "write_tum",
]
