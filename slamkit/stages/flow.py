"""Optical-flow score between matched points (seed §3.2); the function lives in :mod:`slamkit.kernels.geometry`
(the initializer and the pipeline share it) and is re-exported here."""

from __future__ import annotations

from ..kernels.geometry import flow_score

__all__ = ["flow_score"]
