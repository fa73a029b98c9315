"""The notebook app: controls, the 3D map, the frame view and the running summary, as ipywidgets.

:class:`SlamApp` owns a :class:`~slamkit.pipeline.Slam` and a :class:`~slamkit.viz.meshcat_view.MapView`.
Widgets never touch the running pipeline's configuration: they edit a copy, shown as *pending* until
**Reset** starts over with it. Buttons call only pipeline methods (``step``, ``reset``, ``save``) and the
views' drawing methods. The widgets and their layout are built by :class:`~slamkit.viz.app_widgets.AppWidgets`;
this module is what they do.

- **Step** processes one frame; **Run** steps until paused or done in an asyncio task that yields to the
  kernel after every frame (``await asyncio.sleep(0)``), so the notebook and the Pause button stay live;
  **Reset** applies the pending settings (and source) and starts over.
- The map view is redrawn after keyframes (only what changed is sent); the current frame moves every step.
- The same methods work without a browser: ``app.step()``, ``app.run(n)``, ``app.reset()`` (notebooks
  executed headless, tests).

>>> app = SlamApp("default", SlamConfig().with_overrides(max_frames=120))   # doctest: +SKIP
>>> app                                                                     # the widgets
>>> app.step(); app.result.timings                                          # one frame, by hand
"""

from __future__ import annotations

import asyncio
import contextlib
import html
import math
import traceback
from pathlib import Path

import numpy as np

from ..config import SlamConfig
from ..errors import OutputError, SlamkitError
from ..exporter import export
from ..pipeline import Slam, StepResult
from ..run_camera import open_for_config
from . import frame_view as fv
from .app_widgets import LABELS, AppWidgets, config_values
from .app_widgets import feature_options, unavailable_html as _unavailable_html  # noqa: F401 (their old home)
from .explain import camera_html, flow_help_html, legend_html, scale_html
from .kept_files import is_slamkit_map as _is_slamkit_map, keeping_unsaved_files
from .meshcat_view import MapView, legend_html as view_legend_html
from .settings import ViewSettings
from .static_twin import MOVED_TEXT, StaticTwin

DEFAULT_SOURCE = "default"
"""The embedded synthetic sequence (exact ground truth)."""


class SlamApp(AppWidgets):
    """Step-through SLAM in a notebook: controls, 3D map (meshcat), frame view and summary.

    source: ``"default"`` (embedded sequence) or a dataset path / spec for ``open_source``; config: the
    starting configuration; out_dir: where **Save** writes (and **Load** reads) a run; view: a MapView to
    draw into (by default one with its own loopback meshcat server, stopped by :meth:`close`).
    """

    def __init__(self, source: str = DEFAULT_SOURCE, config: SlamConfig | None = None,
                 out_dir: str | Path = "runs/notebook", view: MapView | None = None, map_height: int = 480,
                 frame_width: int = 400):
        self._sources: dict[str, object] = {}
        self.source_spec = str(source)
        config = (config or SlamConfig()).validate()
        self.slam = Slam(self._open(self.source_spec, config), config)
        self.view = view if view is not None else MapView()
        self._own_view = view is None
        self.frame_width = int(frame_width)
        self.map_height = int(map_height)
        self.results: list[StepResult] = []
        self.flow_pairs: tuple[np.ndarray, np.ndarray] = (np.empty((0, 2)), np.empty((0, 2)))
        self._reproj = float("nan")
        self._task: asyncio.Task | None = None
        self._running = False
        self._showing_run: Path | None = None
        self._auto_pair = True
        """The keyframe pair of "Draw matches" follows the latest two keyframes (until the user picks one)."""
        self.last_error: str | None = None
        """The traceback of the last error shown in the status line."""
        self.twin = StaticTwin(self, min_interval=5.0)
        """The plain outputs under the widgets (a picture and the status text) that a saved notebook keeps."""
        self._hooked = None
        self._shown = None
        """The display handle of the widgets' last place in the notebook (None until displayed)."""
        self._build_widgets(self.slam.config, self.source_spec, len(self.slam.source), out_dir, self.view.settings,
                            self.view.iframe_html(self.map_height, legend=False))
        self._connect()
        self._refresh_all()

    # ------------------------------------------------------------------ sources
    def _open(self, spec: str, config: SlamConfig | None = None):
        """The source ``spec`` opened as ``slamkit run`` opens it for ``config`` (once per spec and camera)."""
        config = config if config is not None else self.slam.config if hasattr(self, "slam") else SlamConfig()
        key = (spec, config.camera)
        if key not in self._sources:
            self._sources[key] = open_for_config(spec, config)
        return self._sources[key]

    # ------------------------------------------------------------------ widgets
    def _connect(self) -> None:
        """Buttons and controls to the app's actions (errors go to the status line)."""
        self.b_step.on_click(lambda _: self._guard(self.step))
        self.b_run.on_click(lambda _: self._guard(self.toggle_run))
        self.b_reset.on_click(lambda _: self._guard(self.reset))
        self.b_save.on_click(lambda _: self._guard(self.save))
        self.b_load.on_click(lambda _: self._guard(self.load))
        self.b_html.on_click(lambda _: self._guard(self.export_html))
        self.b_export.on_click(lambda _: self._guard(self.export_dataset))
        self.b_matches.on_click(lambda _: self._guard(self.draw_keyframe_matches))
        self.b_camera.on_click(lambda _: self._guard(self.view.reset_camera))
        self.w_default.on_click(lambda _: setattr(self.w_source, "value", DEFAULT_SOURCE))
        self.w_source.observe(lambda _: self._guard(self._source_changed), "value")
        self.w_skip.observe(lambda _: self._guard(self._update_max_frames), "value")
        for w in (self.m_kf1, self.m_kf2):
            w.observe(lambda _: self._pair_chosen(), "value")
        for w in (self.w_max, self.w_init, self.w_flow, self.w_matches, self.w_features):
            w.observe(lambda _: self._show_pending(), "value")
        for w in (self.v_bg, self.v_path, self.v_kf, self.v_cur, self.v_pts, self.v_dirs, self.v_fscale,
                  self.v_psize, self.v_track, self.v_clip_on, self.v_clip, self.v_color):
            w.observe(lambda _: self._guard(self._apply_view_settings), "value")

    def _guard(self, fn, *args):
        """Run a widget action; show errors in the status line instead of losing them in the kernel log;
        then redraw the static twin if the action changed the app (a button press runs outside any cell)."""
        try:
            return fn(*args)
        except SlamkitError as e:
            self._status(f"⚠ {e}", "#b00020")
        except Exception as e:  # noqa: BLE001 - shown to the user, with the traceback in the status tooltip
            self._status(f"⚠ {type(e).__name__}: {e}", "#b00020")
            self.last_error = traceback.format_exc()
        finally:
            if not self._running:
                self.twin.refresh(force=True)

    def _ipython_display_(self) -> None:
        """The widgets, then their static twin (a picture and the status text: plain outputs a saved,
        autosaved or exported notebook shows without widget state), redrawn after every cell that changed
        the app, every button press and every few seconds of a background run."""
        from IPython import get_ipython
        from IPython.display import display

        bundle = self.widget._repr_mimebundle_()
        bundle["text/plain"] = ("slamkit app (its controls need the running kernel; the picture and status "
                                "below are their static copy)")
        if self._shown is not None:  # the app moves to this cell: where it was keeps the state it had then
            self.twin.refresh(force=True)
            self.twin.detach()
            self._shown.update({"text/plain": MOVED_TEXT}, raw=True)
        self._shown = display(bundle, raw=True, display_id=True)
        self.twin.show()
        ip = get_ipython()
        if ip is not None and self._hooked is None:
            self._hooked = lambda *_: self.twin.refresh(force=True)
            ip.events.register("post_run_cell", self._hooked)

    def _status(self, text: str, color: str = "#333") -> None:
        self.status_text = text
        self.twin.dirty = True
        self.w_status.value = f'<span style="color:{color}">{html.escape(text)}</span>'

    status_text: str = ""
    """The status line as plain text (what ``w_status`` shows)."""

    # ------------------------------------------------------------------ pending settings
    def pending_config(self) -> SlamConfig:
        """The configuration the controls show (applied by :meth:`reset`); the running one is untouched."""
        n_max = self.w_max.max
        max_frames = None if self.w_max.value >= n_max else int(self.w_max.value)
        return self.slam.config.with_overrides(
            frame_skip=int(self.w_skip.value), max_frames=max_frames, init_frames=int(self.w_init.value),
            flow_threshold=float(self.w_flow.value), min_tracked_matches=int(self.w_matches.value),
            features=str(self.w_features.value))

    def pending_changes(self) -> dict[str, tuple]:
        """Setting -> (running value, pending value) for every control that differs from the running run."""
        out: dict[str, tuple] = {}
        if self.w_source.value.strip() != self.source_spec:
            out["source"] = (self.source_spec, self.w_source.value.strip())
        try:
            pending = self.pending_config()
        except SlamkitError as e:
            return dict(out, invalid=(str(e), ""))
        n = len(self._open(self.w_source.value.strip() or DEFAULT_SOURCE)) if "source" in out else len(
            self.slam.source)
        now, new = config_values(self.slam.config, len(self.slam.source)), config_values(pending, n)
        for k in now:
            if now[k] != new[k]:
                out[k] = (now[k], new[k])
        return out

    def _show_pending(self) -> None:
        changes = self.pending_changes()
        if not changes:
            self.w_pending.value = ""
            return
        items = ", ".join(f"{LABELS.get(k, k)} {a} → {b}" for k, (a, b) in changes.items())
        when = " The running pipeline keeps its settings until then." if self.slam.records else ""
        self.w_pending.value = (f'<span class="slamkit-pending-text" style="color:#b35900">⚠ changed: {items} '
                                f'— takes effect on Reset (press <b>Reset</b> to apply and start over).{when}</span>')

    def _source_changed(self) -> None:
        spec = self.w_source.value.strip() or DEFAULT_SOURCE
        try:
            self._open(spec)
        except SlamkitError as e:
            self._status(f"⚠ data source: {e}", "#b00020")
            return
        self._update_max_frames()

    def _update_max_frames(self) -> None:
        spec = self.w_source.value.strip() or DEFAULT_SOURCE
        try:
            n = len(self._open(spec))
        except SlamkitError:
            n = len(self.slam.source)
        at_max = self.w_max.value >= self.w_max.max
        new_max = max(1, math.ceil(n / int(self.w_skip.value)))
        if new_max > self.w_max.max:
            self.w_max.max = new_max
            if at_max:
                self.w_max.value = new_max
        else:
            self.w_max.value = min(self.w_max.value, new_max) if not at_max else new_max
            self.w_max.max = new_max
        self._show_pending()

    # ------------------------------------------------------------------ pipeline actions
    @property
    def result(self) -> StepResult | None:
        """The last step's result."""
        return self.slam.last_result

    def step(self) -> StepResult | None:
        """Process one frame and update the views (None when the sequence is done)."""
        if self.slam.done:
            self._finish()
            self._status(f"the run is finished ({len(self.slam.records)} frames): nothing left to step; Reset "
                         "starts over, Save writes the map and trajectory")
            return None
        result = self.slam.step()
        self.results.append(result)
        self.flow_pairs = fv.flow_lines(result)  # the tracker's own matches, carried by the result
        self._after_step(result)
        if self.slam.done:
            self._finish()
        return result

    def run(self, max_steps: int | None = None, progress: bool = False) -> list[StepResult]:
        """Step synchronously (``max_steps`` frames, or to the end); the widgets update as it goes. With
        ``progress``, a text progress bar (a saved notebook keeps it) counts the frames to the end of the run."""
        from .progress import progress_bar

        out, left = [], len(self.slam) - len(self.slam.records)
        todo = left if max_steps is None else min(left, max_steps)
        bar = progress_bar(todo, "frame", "app.run") if progress and todo > 0 else None
        while not self.slam.done and (max_steps is None or len(out) < max_steps):
            out.append(self.step())
            bar is not None and bar.update(1)
        bar is not None and bar.close()
        return out

    def toggle_run(self) -> None:
        """The Run / Pause button."""
        if self._running:
            self.pause()
        else:
            self.start()

    def start(self) -> asyncio.Task | None:
        """Run in the background of the kernel (an asyncio task, one frame per loop turn) until paused or done."""
        if self._running or self.slam.done:
            return self._task
        self._running = True
        self._set_run_button()
        self._status(f"running from frame {len(self.slam.records)} of {len(self.slam)}; Pause stops after the "
                     "current frame")
        try:
            loop = asyncio.get_running_loop()  # the kernel's loop (widget callbacks run inside it)
        except RuntimeError:
            loop = asyncio.get_event_loop()
        self._task = loop.create_task(self._run_loop())
        return self._task

    def pause(self) -> None:
        """Stop a background run after the current frame."""
        was_running = self._running
        self._running = False
        self._set_run_button()
        if was_running and not self.slam.done:
            self._status(f"paused after frame {len(self.slam.records) - 1}; Run goes on, Step does one frame")

    @property
    def running(self) -> bool:
        return self._running

    async def _run_loop(self) -> None:
        try:
            while self._running and not self.slam.done:
                self.step()
                self.twin.refresh()  # at most every few seconds
                await asyncio.sleep(0)  # the kernel handles widget messages (Pause, sliders) between frames
        except KeyboardInterrupt:  # "interrupt kernel": Slam.step finishes the frame first, so the state is whole
            self._status(f"⏸ interrupted after frame {len(self.slam.records) - 1}: the map so far is intact; Save "
                         "writes it with a session (Slam.resume continues it), Run goes on", "#b06000")
        except Exception as e:  # noqa: BLE001 - a background task has nobody else to tell
            self._status(f"⚠ run stopped: {type(e).__name__}: {e}; the frames before are kept, Save writes them",
                         "#b00020")
            self.last_error = traceback.format_exc()
        finally:
            self._running = False
            self._set_run_button()
            self._show_pending()
            self.twin.refresh(force=True)

    def _set_run_button(self) -> None:
        if self._running:
            self.b_run.description, self.b_run.icon, self.b_run.button_style = "Pause", "pause", "info"
        else:
            self.b_run.description, self.b_run.icon, self.b_run.button_style = "Run", "play", "success"
        self.b_step.disabled = self._running

    def reset(self) -> None:
        """Apply the pending settings (and data source) and start over."""
        self.pause()
        config = self.pending_config()
        spec = self.w_source.value.strip() or DEFAULT_SOURCE
        if spec != self.source_spec:
            callbacks = self.slam.callbacks
            self.slam = Slam(self._open(spec, config), config, callbacks=callbacks)
            self.source_spec = spec
        else:
            self.slam.reset(config)
        self.results.clear()
        self.flow_pairs = (np.empty((0, 2)), np.empty((0, 2)))
        self._reproj = float("nan")
        self._showing_run = None
        self._clear_run_views()
        self.view.update(self.slam)
        self._show_map(snapshot=False)
        self._refresh_all()
        self._status(f"reset: {len(self.slam)} frames of {self.source_spec} with the new settings")

    def _clear_run_views(self) -> None:
        """Forget what belonged to the discarded run: the keyframe-match picture and its label, the clip
        range, the tracked point; the match pair follows the newest keyframes again."""
        self.m_image.value = b""
        self.m_image.layout.display = "none"
        self.m_label.value = ""
        self._auto_pair = True
        with self._holding_view_events():
            self.v_clip_on.value = False
            self.v_clip.min, self.v_clip.max, self.v_clip.value = 0, 1, (0, 1)
            self.v_track.options, self.v_track.value = [("none", -1)], -1
            self.m_kf1.options, self.m_kf2.options = [], []
        self.view.configure(clip=None, track_point=-1)
        self.v_track_info.value = ""

    def _show_map(self, snapshot: bool) -> None:
        """The live 3D view in the app; with ``snapshot`` it also holds the current scene frozen, which a
        saved notebook (with its widget state) shows when no kernel serves the live view."""
        html_ = self.view.iframe_html(self.map_height, snapshot=snapshot, legend=False)  # the legend: v_legend
        if self.map_html.value != html_:
            self.map_html.value = html_

    def _finish(self) -> None:
        if not self.slam.finished:
            self.slam.finish()  # global BA: every pose moves; the view redraws the frames at their final poses
            self._reproj = self._reprojection_error()
            self.view.update(self.slam)
            self.view.reset_camera()
            self._show_map(snapshot=True)
            self._refresh_all()
            self._status("done: the last global bundle adjustment ran; Save writes the map and trajectory")

    def save(self, out_dir: str | Path | None = None) -> Path:
        """Save the current map and trajectory (``slam.save``) to the output folder. Files the last save did not
        write there (an exported ``map.html``, ``slamkit eval``'s report) are kept (:mod:`.kept_files`); a
        folder holding other files than a run's is refused, with the reason in the status line."""
        out = Path(out_dir or self.w_out.value)
        with keeping_unsaved_files(out) as kept:  # an earlier Export HTML (map.html) survives the save
            path = self.slam.save(out)
        also = f"; kept {', '.join(kept)} from before this save" if kept else ""
        self._status(f"saved to {path} (trajectory_tum.txt, sparse/, points.ply, summary.json, session/ to "
                     f"resume){also}")
        return path

    def load(self, run_dir: str | Path | None = None) -> None:
        """Show a saved run folder in the 3D view without rerunning it (Step / Run / Reset go back to live)."""
        run_dir = Path(run_dir or self.w_out.value)
        self.pause()
        stats = self.view.load_run(run_dir)
        self._showing_run = run_dir
        self._show_map(snapshot=True)
        self._refresh_view_controls()
        self.f_summary.value = fv.summary_html(self._summary(), self.view.scene_counts())
        self._status(f"showing the saved run {run_dir} ({stats.points} points, {stats.keyframes} keyframes); "
                     "Step, Run or Reset return to the live map")

    def export_html(self, path: str | Path | None = None) -> Path:
        """The 3D view as one standalone HTML file (default: ``<output folder>/map.html``). An existing file is
        replaced only when it is a map slamkit wrote (OutputError otherwise: the user's file is kept)."""
        path = Path(path or Path(self.w_out.value) / "map.html")
        if (path.exists() or path.is_symlink()) and not _is_slamkit_map(path):
            raise OutputError(f"{path}: exists and is not a map slamkit wrote, so it is kept; nothing was written — "
                              "give another file name")
        n = self._summary()
        run = self._showing_run if self._showing_run is not None else self.source_spec
        caption = (f"{run}: {n['frames']} frames, {n['keyframes']} keyframes, {n['points']} points; "
                   "drag to orbit, scroll to zoom")
        self.view.export_html(path, title=f"slamkit map: {run}", caption=caption)
        self._status(f"3D view exported to {path}")
        return path

    def export_dataset(self, format: str | None = None, out: str | Path | None = None) -> Path:
        """Save the run to the output folder, then write it as a Gaussian-splatting / NeRF dataset with every
        posed frame (:func:`slamkit.export`; ``format`` "colmap" or "nerfstudio", default the dropdown's) to
        ``out`` (default ``<output folder>-<format>``)."""
        fmt = format or self.w_export_format.value
        run_dir = self.save()
        out = Path(out or f"{run_dir}-{fmt}")
        self._status(f"exporting every posed frame as a {fmt} dataset to {out} ...")
        res = export(run_dir, out, format=fmt, frames="all", source=self.slam.source)
        self._status(f"{fmt} dataset written to {out}: {res.num_images} images, {res.num_points} points "
                     f"({res.camera_model} camera)")
        return out

    def close(self) -> None:
        """Stop a background run and the viewer's server (when this app started it)."""
        self.pause()
        if self._hooked is not None:
            from IPython import get_ipython

            ip = get_ipython()
            if ip is not None:
                ip.events.unregister("post_run_cell", self._hooked)
            self._hooked = None
        if self._own_view:
            self.view.close()
        self._close_widgets()

    # ------------------------------------------------------------------ views
    def _reprojection_error(self) -> float:
        m = self.slam.slam_map
        return m.mean_reprojection_error() if m is not None and m.num_points else float("nan")

    def _summary(self) -> dict:
        return fv.summary_numbers(self.slam, self._reproj)

    def _after_step(self, result: StepResult) -> None:
        live_again = self._showing_run is not None
        if live_again:
            self._showing_run = None
        if (result.is_keyframe or result.status == "initialized" or live_again
                or (self.slam.slam_map is not None and not self.view.shows(self.slam.slam_map))
                or (self.slam.slam_map is None and len(self.view.keyframe_ids))):
            if result.is_keyframe or result.status == "initialized":
                self._reproj = self._reprojection_error()
            self.view.update(self.slam)
            self._refresh_view_controls()
        else:
            self.view.show_current(None if result.cam_from_world is None else np.linalg.inv(result.cam_from_world))
        self._refresh_frames(result)
        self.f_summary.value = fv.summary_html(self._summary(), self.view.scene_counts())
        self._show_pending()
        self.twin.dirty = True
        if not self._running and not self.slam.done:
            self._status(f"stepped to frame {result.frame_index}: {result.status}"
                         + (" (keyframe)" if result.is_keyframe else ""))

    def _refresh_all(self) -> None:
        self.twin.dirty = True
        self._refresh_view_controls()
        self._refresh_frames(self.slam.last_result)
        self.f_summary.value = fv.summary_html(self._summary(), self.view.scene_counts())
        self._show_pending()

    def _refresh_frames(self, result: StepResult | None) -> None:
        slam = self.slam
        m = slam.slam_map
        kf_id = slam.last_keyframe if slam.segment is not None else -1
        if m is not None and kf_id not in m.keyframes and len(m.keyframes):
            kf_id = max(m.keyframes, key=lambda k: m.keyframes[k].frame_index)  # the newest keyframe of the map
        kf = m.keyframes.get(kf_id) if m is not None else None
        if kf is not None:
            thumb = kf.thumbnail
            if thumb is None:  # none kept (config.thumbnail_width = 0, or an initialization keyframe): the frame
                thumb = slam.source[int(slam.indices[kf.frame_index])].color
            self.f_kf.value = fv.encode_image(fv.fit_width(thumb, 240)[0])
            self.f_kf_label.value = (f'<span class="slamkit-keyframe">keyframe image id <b>{kf_id}</b> '
                                     f'(frame {kf.frame_index}, t={kf.timestamp:.3f} s; '
                                     f'{m.num_keyframes} keyframes in the map)</span>')
        else:
            self.f_kf.value = fv.encode_image(fv.placeholder("no keyframe yet", (240, 180)))
            self.f_kf_label.value = ("initializing: no map yet" if result is not None and m is None
                                     else "no keyframe in this map yet" if result is not None else "")
        frame = slam.last_frame
        if frame is not None and result is not None and frame.index == result.frame_index:
            ref, cur = self.flow_pairs
            img = fv.draw_flow(frame.color, ref, cur, width=self.frame_width)
            self.f_step.value = fv.step_html(result, slam.config, drawn=len(cur) if len(cur) else None)
        else:
            img = fv.placeholder("press Step or Run", (self.frame_width, self.frame_width * 3 // 4))
            self.f_step.value = fv.step_html(None, slam.config)
        self.f_cur.value = fv.encode_image(img)

    def _refresh_view_controls(self) -> None:
        """The track choices, the clip range and the keyframe pair follow the map; units of the sizes."""
        ids = self.view.keyframe_ids
        with self._holding_view_events():
            tracks = self.view.longest_tracks(30)
            options = [("none", -1)] + [(f"point {p}: seen by {n} images", p) for p, n in tracks]
            value = self.v_track.value if any(p == self.v_track.value for _, p in options) else -1
            if list(self.v_track.options) != options:
                self.v_track.options = options
            self.v_track.value = value
            if len(ids):
                lo, hi = int(ids[0]), int(ids[-1])
                was_full = self.v_clip.value[1] >= self.v_clip.max
                self.v_clip.max = max(hi, lo + 1)
                self.v_clip.min = lo
                if was_full or not self.v_clip_on.value:
                    self.v_clip.value = (lo, max(hi, lo + 1))
            opts = [int(i) for i in ids]
            if list(self.m_kf1.options) != opts:
                v1, v2 = self.m_kf1.value, self.m_kf2.value
                self.m_kf1.options = opts
                self.m_kf2.options = opts
                if opts:
                    latest = opts[max(0, len(opts) - 2)], opts[-1]
                    keep = not self._auto_pair and v1 in opts and v2 in opts
                    self.m_kf1.value, self.m_kf2.value = (v1, v2) if keep else latest
        self._refresh_help()

    def _refresh_help(self) -> None:
        """The keyframe rule with the running thresholds in pixels, and the 3D view's sizes in map units."""
        kf = self.slam.config.keyframes
        camera = getattr(self.slam, "camera", None) or self.slam.source.camera  # the config's intrinsics, if given
        describe = getattr(self.slam, "describe_camera", None)
        self.w_help.value = (flow_help_html(float(camera.fx), kf.flow_threshold, kf.min_tracked_matches)
                             + (camera_html(describe()) if describe is not None else ""))
        self.v_legend.value = legend_html(view_legend_html(self.view.legend_items()))
        sc = self.view.scale_numbers()
        self.v_units.value = (scale_html(sc["extent"], sc["frustum_depth"], sc["point_diameter"], sc["view_depth"])
                              if len(self.view.keyframe_ids) else "")

    def _pair_chosen(self) -> None:
        if not getattr(self, "_hold", False):
            self._auto_pair = False

    @contextlib.contextmanager
    def _holding_view_events(self):
        self._hold = True
        try:
            yield
        finally:
            self._hold = False

    def _apply_view_settings(self) -> None:
        if getattr(self, "_hold", False):
            return
        clip = tuple(int(v) for v in self.v_clip.value) if self.v_clip_on.value else None
        track = int(self.v_track.value if self.v_track.value is not None else -1)
        self.view.configure(background=self.v_bg.value, show_path=self.v_path.value, show_keyframes=self.v_kf.value,
                            show_current=self.v_cur.value, show_points=self.v_pts.value,
                            show_directions=self.v_dirs.value, frustum_scale=float(self.v_fscale.value),
                            point_size=float(self.v_psize.value), track_point=track, clip=clip,
                            color_by=str(self.v_color.value))
        self.v_track_info.value = (f"lines to the {self.view.scene_counts().get('track', 0)} keyframes that see it"
                                   if track >= 0 else "")
        self._refresh_help()
        self.f_summary.value = fv.summary_html(self._summary(), self.view.scene_counts())

    def view_settings(self) -> ViewSettings:
        return self.view.settings

    def draw_keyframe_matches(self, image_id1: int | None = None, image_id2: int | None = None) -> np.ndarray | None:
        """Draw the matches (shared 3D points) between two keyframes into the match image; returns it."""
        m = self.slam.slam_map
        a = int(image_id1 if image_id1 is not None else self.m_kf1.value or -1)
        b = int(image_id2 if image_id2 is not None else self.m_kf2.value or -1)
        if m is None or a not in m.keyframes or b not in m.keyframes:
            self.m_label.value = "choose two keyframes of the live map"
            return None
        k1, k2 = m.keyframes[a], m.keyframes[b]
        src = self.slam.source
        im1 = src[int(self.slam.indices[k1.frame_index])].color
        im2 = src[int(self.slam.indices[k2.frame_index])].color
        pairs = fv.keyframe_matches(m, a, b)
        img = fv.draw_matches(im1, k1.features.keypoints, im2, k2.features.keypoints, pairs, width=960)
        self.m_image.value = fv.encode_image(img)
        self.m_image.layout.display = None
        self.m_label.value = (f"keyframes {a} (frame {k1.frame_index}) and {b} (frame {k2.frame_index}): "
                              f"{len(pairs)} keypoints observe the same 3D points"
                              + (" (300 drawn)" if len(pairs) > 300 else ""))
        return img


__all__ = ["SlamApp", "DEFAULT_SOURCE"]

