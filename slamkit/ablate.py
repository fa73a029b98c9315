"""Ablation sweeps: every combination of a parameter grid on every source, run in parallel, one row per run.

>>> grid = parse_grid(["flow_threshold=0.02,0.05,0.1", "init_frames=10,20"])          # doctest: +SKIP
>>> df = sweep(["synthetic:handheld?frames=60"], grid, "runs/ablation", repeats=2)    # doctest: +SKIP

Where runs execute is the ``executor``: ``"local"`` (default; a process pool over all cores), ``"serial"``
(in this process) or a ``dask.distributed.Client`` (``Client("tcp://HOST:PORT")``) — the same tasks, the
same seeds (repeat ``r`` uses ``SlamConfig.seed = r``), the same rows. Every finished run is written at once
as one small JSON under ``OUT/runs/`` (atomically, by this process as results arrive), so a crashed or
interrupted sweep started again with the same arguments redoes only what is missing. A run that fails
(bad source, a crash inside SLAM, a conflicting combination) never raises: its row has ``status="failed"``
and the ``error``; a run lost with its worker (a killed process) is ``status="lost"`` and is not persisted,
so the next sweep redoes it.

On a dask cluster every worker needs slamkit (``pip install slamkit``) and the sources at the same paths
(or ``synthetic:`` sources); results come back to this process, which writes them, so workers need no
shared file system.
"""

from __future__ import annotations

import hashlib
import io
import itertools
import json
import math
import multiprocessing
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import pycolmap

from .config import ALIASES, SlamConfig
from .errors import ConfigError, OutputError, SlamkitError, check_number
from .eval import ate, rpe
from .io import atomic_write_bytes, atomic_write_text
from .io.run_dir import check_output, out_dir_lock
from .io.run import _ground_truth as gt_of_run
from .pipeline import Slam

__all__ = ["Grid", "parse_grid", "Task", "plan", "run_one", "sweep", "load_results", "markdown_table",
           "RESULT_COLUMNS"]

STATUS_OK, STATUS_FAILED, STATUS_LOST = "ok", "failed", "lost"
NOTHING_POSED = "no frame was posed, so no map was made"
"""The ``error`` of a failed row whose run went through its frames and posed none (``slamkit run`` exits 3)."""

RESULT_COLUMNS = [
    "status", "error", "ate_rmse_m", "ate_keyframes_rmse_m", "rpe_rmse_m", "ate_matched", "frames", "frames_posed",
    "fraction_posed", "keyframes", "points3D", "points_per_image", "reprojection_error_px", "segments",
    "wall_time_s", "fps", "initialization_s", "seconds_per_frame",
]
"""Columns of a result row after the source, the grid's parameters, ``seed`` and ``repeat`` (plus
``t_<stage>_s`` per pipeline stage, ``key`` and ``cached``)."""


# ------------------------------------------------------------------------------------------------ grid

@dataclass(frozen=True)
class Grid:
    """Parameter values to combine: ``{name: (value, ...)}`` in order, names as
    :meth:`SlamConfig.with_overrides` accepts them (short names or dotted paths), values typed."""

    params: tuple[tuple[str, tuple[Any, ...]], ...]

    @property
    def names(self) -> list[str]:
        return [k for k, _ in self.params]

    def combinations(self) -> list[dict[str, Any]]:
        """Every combination, the last parameter varying fastest."""
        if not self.params:
            return [{}]
        names = self.names
        return [dict(zip(names, values)) for values in itertools.product(*(v for _, v in self.params))]

    def __len__(self) -> int:
        return math.prod(len(v) for _, v in self.params) if self.params else 1

    def to_dict(self) -> dict[str, list]:
        return {k: list(v) for k, v in self.params}


def _config_value(cfg, name: str) -> Any:

    if name == "features":  # a feature pipeline name (xfeat-lighterglue) also sets the matcher: keep the name
        return cfg.feature_pipeline
    obj = cfg
    for part in ALIASES.get(name, name).split("."):
        obj = getattr(obj, part)
    return obj


def parse_grid(spec: Sequence[str] | str | Mapping[str, Any]) -> Grid:
    """``["flow_threshold=0.02,0.05", "init_frames=10,20"]`` (or one string of such items separated by
    spaces, or a mapping ``{name: values}``) -> :class:`Grid`, every value checked and converted with
    :meth:`SlamConfig.with_overrides`. ConfigError naming the parameter for an unknown name, a value of
    the wrong type or out of range, a repeated name or an item without ``=``."""

    if isinstance(spec, str):
        spec = spec.split()
    if isinstance(spec, Mapping):
        items = [(str(k), list(v) if isinstance(v, (list, tuple)) else [v]) for k, v in spec.items()]
    else:
        items = []
        for item in spec:
            if "=" not in item:
                raise ConfigError(f"grid item {item!r}: expected NAME=V1,V2,... (e.g. flow_threshold=0.02,0.05)")
            name, values = item.split("=", 1)
            vals = [v.strip() for v in values.split(",") if v.strip()]
            if not vals:
                raise ConfigError(f"grid item {item!r}: no values after '='")
            items.append((name.strip(), vals))
    base = SlamConfig()
    params, seen = [], set()
    for name, values in items:
        if name in seen:
            raise ConfigError(f"grid parameter {name!r} given twice")
        if name == "seed":
            raise ConfigError("grid parameter 'seed': seeds come from --repeats (repeat r uses seed r)")
        seen.add(name)
        typed = []
        for v in values:
            try:
                typed.append(_config_value(base.with_overrides(**{name: v}), name))
            except ConfigError as e:
            
                raise ConfigError(f"grid parameter {name}={v!r}: {e} (short names: {', '.join(ALIASES)})") from None
        params.append((name, tuple(dict.fromkeys(typed))))
    return Grid(tuple(params))


# ------------------------------------------------------------------------------------------------ tasks

@dataclass(frozen=True)
class Task:
    """One run of a sweep: a source, the parameter values and the seed (= repeat index)."""

    source: str
    overrides: tuple[tuple[str, Any], ...]
    repeat: int

    @property
    def seed(self) -> int:
        return self.repeat

    @property
    def key(self) -> str:
        """Stable file name of this run's result: readable prefix + hash of (source, overrides, seed)."""
        blob = json.dumps([self.source, sorted(self.overrides), self.seed], sort_keys=True, default=str)
        digest = hashlib.sha1(blob.encode()).hexdigest()[:12]
        label = "_".join(f"{k.split('.')[-1]}={v}" for k, v in self.overrides)
        safe = "".join(c if c.isalnum() or c in "=._-" else "-" for c in label)[:80]
        return f"{safe}_s{self.seed}_{digest}" if safe else f"s{self.seed}_{digest}"


MAX_RUNS = 1_000_000
"""The most runs one sweep may plan (sources x combinations x repeats), checked before the list is made."""


def plan(sources: Iterable[str], grid: Grid, repeats: int = 1) -> list[Task]:
    """Every (source, combination, repeat) of the sweep, in order."""
    check_number(repeats, "repeats", f"[1, {MAX_RUNS}]", integer=True)
    sources = [str(s) for s in sources]
    if not sources:
        raise ConfigError("no sources to sweep")
    if len(sources) * len(grid) * repeats > MAX_RUNS:
        raise ConfigError(f"the sweep has {len(sources)} source(s) x {len(grid)} combination(s) x {repeats} "
                          f"repeat(s) = {len(sources) * len(grid) * repeats} runs, more than {MAX_RUNS}")
    return [Task(s, tuple(combo.items()), r)
            for s in sources for combo in grid.combinations() for r in range(repeats)]


def _ground_truth(slam):

    return gt_of_run(slam)


def run_one(source_spec: str, overrides: Mapping[str, Any] | Iterable[tuple[str, Any]] = (),
            seed: int = 0, run_dir: str | os.PathLike | None = None) -> dict:
    """Run SLAM on ``source_spec`` with ``overrides`` and ``seed``; the result row as a JSON-able dict.

    Never raises for a failing run: a source that does not open, a configuration that does not validate or
    an exception inside SLAM give ``status="failed"`` with ``error`` (type and message), and so does a run
    that posed no frame (``error``: :data:`NOTHING_POSED` and why). The source is opened as ``slamkit run``
    opens it (:func:`~slamkit.run_camera.open_for_config`): what ``run`` refuses fails here in the same
    words. ATE (Sim(3), all frames and keyframes, metres) and RPE (1 frame, metres) are computed when the
    source has ground truth; when they cannot be (too few posed frames), they are NaN and ``error`` says why.
    ``run_dir``: also save the run folder there (:meth:`Slam.save`)."""
    overrides = dict(overrides)
    row: dict[str, Any] = {"source": str(source_spec), **overrides, "seed": int(seed), "status": STATUS_OK,
                           "error": ""}
    for c in RESULT_COLUMNS[2:]:
        row[c] = math.nan
    t0 = time.perf_counter()
    try:

        pycolmap.logging.minloglevel = 2
    
        cfg = SlamConfig().with_overrides(**overrides, seed=int(seed))
        slam = Slam(str(source_spec), cfg)  # opened as `slamkit run` opens it: the same checks, the same words
        slam.run()
        if run_dir is not None:
            slam.save(run_dir)
        s = slam.summary()
        row.update(frames=s["frames"], frames_posed=s["frames_posed"], fraction_posed=s["fraction_posed"],
                   keyframes=s["keyframes"], points3D=s["points3D"], points_per_image=s["points_per_image"],
                   reprojection_error_px=s["mean_reprojection_error_px"], segments=len(s["segments"]),
                   wall_time_s=s["wall_time_s"], fps=s["fps"], initialization_s=s["initialization_s"],
                   seconds_per_frame=s["seconds_per_frame"])
        for stage, sec in s["timings_s"].items():
            row[f"t_{stage}_s"] = float(sec)
        gt = _ground_truth(slam)
        if not s["frames_posed"]:  # `slamkit run` exits 3 for it: no map is not a result
            row["status"] = STATUS_FAILED
            row["error"] = NOTHING_POSED + (f": {s['not_initialized_reason']}" if s.get("not_initialized_reason")
                                            else "")
        elif gt is None or len(gt) == 0:
            row["error"] = "no ground truth: ATE not computed"
        else:

            try:
                a = ate(gt, slam.trajectory())
                row["ate_rmse_m"], row["ate_matched"] = a.rmse, a.n_matched
                row["rpe_rmse_m"] = rpe(gt, slam.trajectory()).translation.rmse
                kf = slam.trajectory(keyframes_only=True)
                if len(kf) >= 3:
                    row["ate_keyframes_rmse_m"] = ate(gt, kf).rmse
            except SlamkitError as e:
                row["error"] = f"ATE not computed: {e}"
    except Exception as e:  # noqa: BLE001 - a failing run is a row, never an exception
        row["status"] = STATUS_FAILED
        row["error"] = f"{type(e).__name__}: {e}"
    row["run_time_s"] = time.perf_counter() - t0
    return _jsonable(row)


def _run_task(task: Task) -> dict:
    """Worker entry point (module-level so process pools and dask can pickle it)."""
    row = run_one(task.source, dict(task.overrides), task.seed)
    row["repeat"] = task.repeat
    row["key"] = task.key
    return row


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "item") and callable(x.item):  # numpy scalars
        return x.item()
    return x


# ------------------------------------------------------------------------------------------------ sweep

def _result_path(out_dir: Path, task: Task) -> Path:
    return out_dir / "runs" / f"{task.key}.json"


def _read_cached(path: Path) -> dict | None:
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # missing or unreadable (never half-written: writes are atomic): run again
    return row if isinstance(row, dict) and row.get("status") in (STATUS_OK, STATUS_FAILED) else None


def _lost_row(task: Task, error: BaseException) -> dict:
    row = {"source": task.source, **dict(task.overrides), "seed": task.seed, "status": STATUS_LOST,
           "error": f"{type(error).__name__}: {error}", "repeat": task.repeat, "key": task.key}
    return _jsonable(row)


def _is_dask_client(executor) -> bool:
    return type(executor).__module__.startswith("distributed") and hasattr(executor, "submit")


def check_sweep_args(out_dir: str | os.PathLike, workers: int | None, *, flag_out: str = "out_dir",
                     flag_workers: str = "workers", sources: Iterable = ()) -> Path:
    """Refuse a negative worker count and a sweep folder that may not be written, before any run
    (ConfigError / OutputError naming the option): a file, a folder of other files than a sweep, a run
    folder or anything inside one, a source (:func:`slamkit.io.run_dir.check_output`)."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or not 0 <= workers <= 1024):
        raise ConfigError(f"{flag_workers} {workers}: must be 0 (runs in this process) or a number of local "
                          "processes from 1 to 1024 (default: all cores)")
    return check_output(out_dir, "sweep", sources, flag=flag_out)


def sweep(sources: Iterable[str] | str, grid: Grid | Sequence[str] | Mapping[str, Any], out_dir: str | os.PathLike,
          executor=None, *, repeats: int = 1, workers: int | None = None, retry_failed: bool = False,
          on_result: Callable[[dict], None] | None = None, write_outputs: bool = True):
    """Run every (source, grid combination, repeat) and return the results as a pandas DataFrame.

    ``executor``: None or ``"local"`` (process pool of ``workers`` processes, default all cores),
    ``"serial"`` (this process), a ``dask.distributed.Client``, or any ``concurrent.futures.Executor``.
    Results already in ``OUT/runs/`` are reused (``cached=True``); failed ones are run again only with
    ``retry_failed``. ``on_result(row)`` is called for every row, cached ones first (progress bars).
    Writes ``OUT/results.csv``, ``results.parquet`` (when pyarrow is installed), ``results.md`` and
    ``effects.png`` (one panel per parameter) unless ``write_outputs`` is False.
    """


    if isinstance(sources, str):
        sources = [sources]
    if not isinstance(grid, Grid):
        grid = parse_grid(grid)
    out_dir = check_sweep_args(out_dir, workers, sources=sources)
    tasks = plan(sources, grid, repeats)
    with out_dir_lock(out_dir, flag="out_dir", what="sweep folder"):  # one sweep writes a folder at a time
        return _sweep(out_dir, tasks, grid, repeats, executor, workers, retry_failed, on_result, write_outputs)


def _sweep(out_dir: Path, tasks: list[Task], grid: Grid, repeats: int, executor, workers: int | None,
           retry_failed: bool, on_result: Callable[[dict], None] | None, write_outputs: bool):
    try:
        (out_dir / "runs").mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{out_dir}: sweep folder cannot be created ({e.strerror or e})") from e
    atomic_write_text(out_dir / "sweep.json", json.dumps(
        {"sources": list(dict.fromkeys(t.source for t in tasks)), "grid": _jsonable(grid.to_dict()),
         "repeats": repeats}, indent=2))

    rows: dict[str, dict] = {}
    todo: list[Task] = []
    for task in tasks:
        cached = _read_cached(_result_path(out_dir, task))
        if cached is not None and not (retry_failed and cached["status"] == STATUS_FAILED):
            cached["cached"] = True
            rows[task.key] = cached
            if on_result:
                on_result(cached)
        else:
            todo.append(task)

    def finished(task: Task, row: dict) -> None:
        if row["status"] != STATUS_LOST:
            atomic_write_text(_result_path(out_dir, task), json.dumps(row, indent=1, allow_nan=True))
        row["cached"] = False
        rows[task.key] = row
        if on_result:
            on_result(row)

    if todo:
        _execute(todo, executor, workers, finished)

    df = pd.DataFrame([rows[t.key] for t in tasks])
    front = ["source", *grid.names, "seed", "repeat"]
    df = df[[c for c in front if c in df] + [c for c in df.columns if c not in front]]
    if write_outputs:
        write_results(df, out_dir, grid.names)
    return df


def _execute(todo: list[Task], executor, workers: int | None, finished: Callable[[Task, dict], None]) -> None:
    if executor == "serial":
        for task in todo:
            finished(task, _run_task(task))
        return
    if executor is None or executor == "local":

        n = max(1, min(workers or os.cpu_count() or 1, len(todo)))
        pool = ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"))
        try:
            _collect(pool, todo, finished)
        except BaseException:  # interrupted: stop the running runs now (finished ones are saved already)
            _stop_workers(pool)
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()
        return
    if isinstance(executor, str):
        raise ConfigError(f"executor {executor!r}: use 'local', 'serial', a dask Client or an Executor "
                          "(for a cluster address, slamkit.ablate.connect(ADDRESS))")
    _collect(executor, todo, finished)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate the pool's processes (the runs in flight): a sweep stopped by a signal exits in seconds,
    not after its longest run. Their results were not written, so the same command runs them again."""
    terminate = getattr(pool, "terminate_workers", None)  # Python 3.14+
    if terminate is not None:
        terminate()
        return
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        if proc.is_alive():
            proc.terminate()
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        proc.join(timeout=5)


def _collect(executor, todo: list[Task], finished: Callable[[Task, dict], None]) -> None:
    """Submit every task and hand each result over as soon as it arrives (persisted by ``finished``)."""
    completed = as_completed
    if _is_dask_client(executor):
        from distributed import as_completed as completed  # the dask extra: imported only for a cluster

        futures = {executor.submit(_run_task, t, key=f"slamkit-run-{t.key}", pure=False): t for t in todo}
    else:
        futures = {executor.submit(_run_task, t): t for t in todo}
    try:
        for fut in completed(list(futures)):
            task = futures[fut]
            try:
                row = fut.result()
            except Exception as e:  # noqa: BLE001 - the worker died (KilledWorker, BrokenProcessPool): not the run's fault
                row = _lost_row(task, e)
            finished(task, row)
    except BaseException:  # interrupted: drop what has not run yet (a dask cluster would go on otherwise)
        if _is_dask_client(executor):
            executor.cancel(list(futures))
        raise


def connect(address: str):
    """A ``dask.distributed.Client`` for ``tcp://HOST:PORT`` (SlamkitError when dask is missing or the
    scheduler cannot be reached)."""
    try:
        from distributed import Client
    except ImportError:
        raise SlamkitError("--scheduler needs dask.distributed: pip install 'slamkit[dask]'") from None
    if not isinstance(address, str) or not address.strip():
        raise ConfigError(f"--scheduler {address!r}: expected a dask scheduler address, tcp://HOST:PORT")
    try:
        return Client(address, timeout="10s")
    except (OSError, TimeoutError) as e:
        raise SlamkitError(f"cannot reach the dask scheduler at {address}: {e}") from None
    except (ValueError, TypeError) as e:  # not an address (no port, unknown protocol, ...)
        raise ConfigError(f"--scheduler {address!r}: not a dask scheduler address, tcp://HOST:PORT ({e})") from None


# ------------------------------------------------------------------------------------------------ outputs

def load_results(out_dir: str | os.PathLike):
    """The DataFrame of every run JSON under ``OUT/runs`` (for a sweep still running or interrupted)."""

    rows = [r for p in sorted(Path(out_dir, "runs").glob("*.json")) if (r := _read_cached(p)) is not None]
    return pd.DataFrame(rows)


def _fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return ""
        return f"{v:.4g}"
    return str(v).replace("|", "\\|").replace("\n", " ")


def markdown_table(df, columns: Sequence[str] | None = None) -> str:
    """A GitHub markdown table of ``df`` (no tabulate needed)."""
    cols = [c for c in (columns or df.columns) if c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for _, r in df[cols].iterrows():
        lines.append("| " + " | ".join(_fmt(r[c]) for c in cols) + " |")
    return "\n".join(lines) + "\n"


def summarize(df, params: Sequence[str]):
    """Mean and std of ATE and the run statistics over repeats, one row per (source, parameter values)."""
    ok = df[df["status"] == STATUS_OK]
    keys = ["source", *params]
    if ok.empty:
        return ok
    metrics = [c for c in ("ate_rmse_m", "ate_keyframes_rmse_m", "fraction_posed", "keyframes", "points_per_image",
                           "reprojection_error_px", "fps") if c in ok]
    g = ok.groupby(keys, dropna=False, sort=False)
    out = g[metrics].mean()
    out["ate_std_m"] = g["ate_rmse_m"].std() if "ate_rmse_m" in metrics else math.nan
    out["runs"] = g.size()
    return out.reset_index()


def write_results(df, out_dir: str | os.PathLike, params: Sequence[str]) -> dict[str, Path]:
    """results.csv, results.parquet (if pyarrow), results.md and effects.png in ``out_dir``."""

    out_dir = Path(out_dir)
    paths = {"csv": atomic_write_text(out_dir / "results.csv", df.to_csv(index=False))}
    try:

        buf = io.BytesIO()
        df.to_parquet(buf, index=False)
        paths["parquet"] = atomic_write_bytes(out_dir / "results.parquet", buf.getvalue())
    except ImportError:
        pass
    show = ["source", *params, "seed", "status", "ate_rmse_m", "ate_keyframes_rmse_m", "fraction_posed",
            "keyframes", "points_per_image", "reprojection_error_px", "fps", "wall_time_s"]
    md = [f"# Ablation: {len(df)} runs\n", "## Every run\n", markdown_table(df, show)]
    summary = summarize(df, params)
    if len(summary) and df["repeat"].nunique() > 1:
        md += ["\n## Mean over repeats\n", markdown_table(summary)]
    failed = df[df["status"] != STATUS_OK]
    if len(failed):
        md += ["\n## Failed runs\n", markdown_table(failed, ["source", *params, "seed", "status", "error"])]
    if (df["status"] == STATUS_OK).any() and params:
        from .eval.plots import plot_effects  # matplotlib only when a sweep is plotted (cli imports this module)

        varied = [p for p in params if df[p].nunique(dropna=False) > 1] or list(params)
        paths["effects"] = plot_effects(df, varied, out_dir / "effects.png")
        md += ["\n## Effect of each parameter\n", "![effects](effects.png)\n"]
    paths["md"] = atomic_write_text(out_dir / "results.md", "\n".join(md))
    return paths
