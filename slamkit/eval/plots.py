"""Plots of evaluations and ablations (matplotlib, Agg backend): only this module imports matplotlib, and
nothing in the core imports this module (``slamkit.eval.report`` and ``slamkit.ablate`` import it lazily).

Figures are ``matplotlib.figure.Figure`` objects rendered by Agg (no pyplot: no global figure state, no
window, and a notebook's own backend is left alone). Every function draws one figure, writes it as PNG to ``path`` and returns the path.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Sequence

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from ..io import atomic_write_bytes

__all__ = ["plot_trajectory_views", "plot_error_over_time", "plot_timings", "plot_effects"]

_DPI = 110


def _save(fig, path: str | os.PathLike) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI, bbox_inches="tight")
    return atomic_write_bytes(Path(path), buf.getvalue())


def view_axes(xyz: np.ndarray) -> tuple[tuple[int, int, str], tuple[int, int, str]]:
    """((i, j, title) of the top view, (i, j, title) of the side view) for positions ``xyz`` (N, 3): "up" is
    the axis along which they spread least (the ground plane holds the two others), so a car, a walk through
    a room and a synthetic scene with z up are all seen from above, whatever their world frame."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    up = int(np.argmin(np.ptp(xyz, axis=0))) if len(xyz) else 2
    a, b = (k for k in range(3) if k != up)
    return (a, b, f"top view ({'xyz'[a]}, {'xyz'[b]})"), (a, up, f"side view ({'xyz'[a]}, {'xyz'[up]})")


def plot_trajectory_views(gt_xyz: np.ndarray, est_xyz: np.ndarray, errors: np.ndarray, path: str | os.PathLike,
                          title: str = "", gt_full_xyz: np.ndarray | None = None) -> Path:
    """Top and side views (:func:`view_axes`) of the aligned estimate (``est_xyz`` (N, 3) metres, coloured by
    ``errors`` (N,) metres, shown in cm) over the ground truth (``gt_xyz`` (N, 3), matched; ``gt_full_xyz``
    (M, 3) drawn faintly when given). Axes in metres, equal scale."""
    fig = Figure(figsize=(12, 5.2), layout="constrained")
    axes = fig.subplots(1, 2)
    err_cm = np.asarray(errors) * 100.0
    vmax = float(np.percentile(err_cm, 98)) if len(err_cm) else 1.0
    sc = None
    ref = gt_full_xyz if gt_full_xyz is not None and len(gt_full_xyz) else gt_xyz
    for ax, (i, j, name) in zip(axes, view_axes(ref)):
        if gt_full_xyz is not None and len(gt_full_xyz):
            ax.plot(gt_full_xyz[:, i], gt_full_xyz[:, j], color="0.8", lw=1, label="ground truth (all)")
        ax.plot(gt_xyz[:, i], gt_xyz[:, j], color="0.25", lw=1.5, ls="--", label="ground truth")
        ax.plot(est_xyz[:, i], est_xyz[:, j], color="0.6", lw=0.8, zorder=2)
        sc = ax.scatter(est_xyz[:, i], est_xyz[:, j], c=err_cm, cmap="plasma", s=12, vmin=0, vmax=max(vmax, 1e-9),
                        zorder=3, label="estimate (Sim(3)-aligned)")
        if len(est_xyz):
            ax.plot(*est_xyz[0, [i, j]], marker="o", color="green", ms=8, zorder=4, ls="", label="start")
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
        if j == 1 and name.startswith("side"):
            ax.invert_yaxis()  # a camera-like world frame (y down): up is up on the page
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(name)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    if sc is not None:
        fig.colorbar(sc, ax=axes, label="position error [cm]", shrink=0.85)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_error_over_time(t: np.ndarray, errors: np.ndarray, path: str | os.PathLike, *,
                         keyframe_t: np.ndarray | None = None, rpe_t: np.ndarray | None = None,
                         rpe_errors: np.ndarray | None = None, title: str = "") -> Path:
    """ATE per frame over time (seconds from the first frame; ``errors`` metres, drawn in cm) with the RMSE
    and the keyframes marked, and (when given) the RPE per frame pair below."""
    rows = 2 if rpe_t is not None and rpe_errors is not None and len(rpe_t) else 1
    fig = Figure(figsize=(11, 3.2 * rows), layout="constrained")
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)
    t0 = float(t[0]) if len(t) else 0.0
    ax = axes[0, 0]
    e = np.asarray(errors) * 100
    ax.plot(np.asarray(t) - t0, e, color="tab:blue", lw=1.2, label="ATE per frame")
    if len(e):
        rmse = float(np.sqrt(np.mean(e**2)))
        ax.axhline(rmse, color="tab:red", ls="--", lw=1, label=f"RMSE {rmse:.2f} cm")
    if keyframe_t is not None:
        for k, tk in enumerate(np.asarray(keyframe_t) - t0):
            ax.axvline(tk, color="0.7", lw=0.6, zorder=0, label="keyframe" if k == 0 else None)
    ax.set_ylabel("position error [cm]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    if rows == 2:
        ax2 = axes[1, 0]
        ax2.plot(np.asarray(rpe_t) - t0, np.asarray(rpe_errors) * 100, color="tab:orange", lw=1)
        ax2.set_ylabel("RPE (1 frame) [cm]")
        ax2.set_ylim(bottom=0)
        ax2.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_timings(timings_s: dict[str, float], frames: int, path: str | os.PathLike, title: str = "") -> Path:
    """Per-stage time: total seconds (bar) and milliseconds per frame (label)."""
    items = sorted(((k, float(v)) for k, v in timings_s.items() if v > 0), key=lambda kv: -kv[1])
    fig = Figure(figsize=(8, 0.45 * max(len(items), 3) + 1.2), layout="constrained")
    ax = fig.subplots()
    if items:
        names, secs = zip(*items)
        total = sum(secs)
        y = np.arange(len(names))
        ax.barh(y, secs, color=matplotlib.colormaps["tab10"](np.arange(len(names)) % 10))
        ax.set_yticks(y, names)
        ax.invert_yaxis()
        for yi, s in zip(y, secs):
            per = f", {1e3 * s / frames:.1f} ms/frame" if frames else ""
            ax.text(s, yi, f" {s:.2f} s ({100 * s / total:.0f} %{per})", va="center", fontsize=8)
        ax.set_xlim(0, max(secs) * 1.45)
    ax.set_xlabel("seconds (whole run)")
    ax.set_title(title or "time per pipeline stage")
    ax.grid(axis="x", alpha=0.3)
    return _save(fig, path)


def plot_effects(df, params: Sequence[str], path: str | os.PathLike,
                 metrics: Sequence[tuple[str, str, float]] = (("ate_rmse_m", "ATE RMSE [cm]", 100.0),
                                                             ("fraction_posed", "frames posed [%]", 100.0),
                                                             ("fps", "frames / s", 1.0))) -> Path:
    """One column per parameter, one row per metric: the metric (mean over the other parameters and the
    repeats, error bars = std) against the parameter's values, one line per source."""
    ok = df[df["status"] == "ok"]
    params = [p for p in params if p in ok]
    metrics = [m for m in metrics if m[0] in ok]
    fig = Figure(figsize=(3.8 * max(len(params), 1), 2.7 * max(len(metrics), 1)), layout="constrained")
    axes = fig.subplots(max(len(metrics), 1), max(len(params), 1), squeeze=False, sharex="col")
    for c, p in enumerate(params):
        values = list(dict.fromkeys(df[p].tolist()))
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        xs = sorted(values) if numeric else values
        for r, (col, label, scale) in enumerate(metrics):
            ax = axes[r, c]
            for src, g in ok.groupby("source", sort=False):
                stats = g.groupby(p)[col].agg(["mean", "std"]).reindex(xs)
                x = xs if numeric else np.arange(len(xs))
                ax.errorbar(x, stats["mean"] * scale, yerr=stats["std"].fillna(0) * scale, marker="o", capsize=3,
                            label=_short(str(src)))
            if not numeric:
                ax.set_xticks(np.arange(len(xs)), [str(v) for v in xs])
            elif len(xs) > 2 and min(xs) > 0 and max(xs) / min(xs) >= 8:
                ax.set_xscale("log")
                ax.set_xticks(xs, [f"{v:g}" for v in xs])
            if r == len(metrics) - 1:
                ax.set_xlabel(p)
            if c == 0:
                ax.set_ylabel(label)
            ax.grid(alpha=0.3)
    if params and metrics and ok["source"].nunique() > 1:
        axes[0, 0].legend(fontsize=7)
    fig.suptitle("effect of each parameter (mean over the other parameters and repeats)")
    return _save(fig, path)


def _short(s: str, n: int = 28) -> str:
    return s if len(s) <= n else "…" + s[-(n - 1):]
