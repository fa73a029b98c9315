"""The notebook app's widgets and their layout (ipywidgets), without behaviour.

:class:`AppWidgets` builds every control of :class:`~slamkit.viz.app.SlamApp` as an attribute (``w_*``: the
run's settings and actions, ``v_*``: the 3D view's settings, ``f_*`` / ``m_*``: the frame view and the
keyframe matches) and lays them out in :attr:`AppWidgets.widget`; the app connects them to its actions. The
feature pipelines offered and the values the controls show for a configuration are here too.
"""

from __future__ import annotations

import html
import math

import ipywidgets as W
from IPython.display import display

from ..config import SlamConfig, feature_pipeline_status
from ..features.learned import INSTALL_HINT, torch_available
from .explain import legend_html
from .settings import ViewSettings

LABELS = {
    "source": "source",
    "frame_skip": "frame skip",
    "max_frames": "max frames",
    "init_frames": "initialization frames",
    "flow_threshold": "flow threshold",
    "min_tracked_matches": "min tracked matches",
    "features": "features",
}
"""Control name -> its label in the pending-changes line."""


def feature_options(config: SlamConfig) -> tuple[list[str], dict[str, str]]:
    """The features dropdown: the feature pipelines that can run here (``orb``, ``sift``, and ``xfeat``,
    ``xfeat-lighterglue``, ``aliked-lightglue``, ``superpoint-superglue`` when the learned extra and their
    weight files are there), plus the config's own; and the others with why not."""
    status = feature_pipeline_status(config.weights_dir)
    options = [name for name, why in status.items() if why is None]
    if config.feature_pipeline not in options:
        options.append(config.feature_pipeline)
    return options, {name: why for name, why in status.items() if why is not None}


def unavailable_html(unavailable: dict[str, str]) -> str:
    """The note under the features dropdown: the install hint without torch, else each pipeline's reason."""
    if not unavailable:
        return ""
    if not torch_available():
        head = f"learned features ({', '.join(unavailable)}): {INSTALL_HINT}"
        return f'<span class="slamkit-features-note" style="color:#666">{html.escape(head)}</span>'
    items = "".join(f"<li><b>{html.escape(k)}</b>: {html.escape(v)}</li>" for k, v in unavailable.items())
    return (f'<details class="slamkit-features-note" style="color:#666"><summary>not available here: '
            f'{html.escape(", ".join(unavailable))}</summary><ul>{items}</ul></details>')


def config_values(config: SlamConfig, source_len: int) -> dict:
    """The values the controls show for a config (``source_len``: frames in the data source)."""
    n_max = max(1, math.ceil(source_len / config.frame_skip))
    return {
        "frame_skip": config.frame_skip,
        "max_frames": min(config.max_frames or n_max, n_max),
        "init_frames": config.initializer.init_frames,
        "flow_threshold": config.keyframes.flow_threshold,
        "min_tracked_matches": config.keyframes.min_tracked_matches,
        "features": config.feature_pipeline,
    }


class AppWidgets:
    """The app's widgets, built by :meth:`_build_widgets` and laid out in ``widget``."""

    frame_width: int

    def _build_widgets(self, config: SlamConfig, source_spec: str, source_len: int, out_dir,
                       view_settings: ViewSettings, map_html: str) -> None:
        """Every control for ``config`` on a source of ``source_len`` frames; ``map_html``: the 3D viewer."""
        self._build_run_controls(config, source_spec, source_len, out_dir)
        self._build_view_controls(view_settings)
        self._build_frame_view()
        self.map_html = W.HTML(map_html)
        self.widget = self._layout()

    def _build_run_controls(self, cfg: SlamConfig, source_spec: str, source_len: int, out_dir) -> None:
        vals = config_values(cfg, source_len)
        style = {"description_width": "150px"}
        wide = W.Layout(width="420px")
        self.w_source = W.Text(value=source_spec, description="data source", style=style, layout=wide,
                               placeholder="default, or a dataset folder / video path", continuous_update=False)
        self.w_default = W.Button(description="default sequence", tooltip="the embedded synthetic sequence",
                                  layout=W.Layout(width="160px"))
        self.w_skip = W.IntSlider(value=vals["frame_skip"], min=1, max=10, description="frame skip", style=style,
                                  layout=wide, continuous_update=False)
        self.w_max = W.IntSlider(value=vals["max_frames"], min=1, max=max(1, math.ceil(source_len / cfg.frame_skip)),
                                 description="max frames", style=style, layout=wide, continuous_update=False)
        self.w_init = W.IntSlider(value=vals["init_frames"], min=2, max=60, description="initialization frames",
                                  style=style, layout=wide, continuous_update=False)
        self.w_flow = W.FloatSlider(value=vals["flow_threshold"], min=0.0, max=0.3, step=0.005,
                                    readout_format=".3f", description="flow threshold", style=style, layout=wide,
                                    continuous_update=False)
        self.w_matches = W.IntSlider(value=vals["min_tracked_matches"], min=5, max=500,
                                     description="min tracked matches", style=style, layout=wide,
                                     continuous_update=False)
        options, unavailable = feature_options(cfg)
        self.w_features = W.Dropdown(options=options, value=vals["features"], description="features", style=style,
                                     layout=wide)
        self.w_features_note = W.HTML(unavailable_html(unavailable), layout=W.Layout(max_width="640px"))
        self.w_out = W.Text(value=str(out_dir), description="output folder", style=style, layout=wide)
        self._build_buttons()
        self.w_help = W.HTML()
        self.w_pending = W.HTML(layout=W.Layout(min_height="22px"))
        self.w_status = W.HTML(layout=W.Layout(min_height="22px"))

    def _build_buttons(self) -> None:
        bl = W.Layout(width="96px")
        self.b_step = W.Button(description="Step", tooltip="process one frame", icon="step-forward", layout=bl)
        self.b_run = W.Button(description="Run", tooltip="run until paused or done", icon="play", layout=bl,
                              button_style="success")
        self.b_reset = W.Button(description="Reset", tooltip="apply the settings and start over", icon="refresh",
                                layout=bl, button_style="warning")
        self.b_save = W.Button(description="Save", tooltip="save map and trajectory to the output folder",
                               icon="save", layout=bl)
        self.b_load = W.Button(description="Load", tooltip="show the run saved in the output folder",
                               icon="folder-open", layout=bl)
        self.b_html = W.Button(description="Export HTML", tooltip="the 3D view as one HTML file (output folder)",
                               icon="file", layout=W.Layout(width="120px"))
        self.w_export_format = W.Dropdown(options=[("COLMAP (gsplat, 3DGS)", "colmap"), ("nerfstudio", "nerfstudio")],
                                          value="colmap", layout=W.Layout(width="190px"))
        self.b_export = W.Button(description="Export dataset", icon="cubes", layout=W.Layout(width="140px"),
                                 tooltip="save the run, then write it as a Gaussian-splatting / NeRF dataset "
                                         "(every posed frame) to <output folder>-<format>")

    def _build_view_controls(self, vs: ViewSettings) -> None:
        vstyle = {"description_width": "110px"}
        vl = W.Layout(width="330px")
        self.v_bg = W.ColorPicker(value=vs.background, description="background", concise=False, style=vstyle,
                                  layout=vl)
        self.v_path = W.Checkbox(value=vs.show_path, description="path", indent=False, layout=W.Layout(width="80px"))
        self.v_kf = W.Checkbox(value=vs.show_keyframes, description="keyframes", indent=False,
                               layout=W.Layout(width="100px"))
        self.v_cur = W.Checkbox(value=vs.show_current, description="current frame", indent=False,
                                layout=W.Layout(width="120px"))
        self.v_pts = W.Checkbox(value=vs.show_points, description="points", indent=False,
                                layout=W.Layout(width="80px"))
        self.v_dirs = W.Checkbox(value=vs.show_directions, description="viewing directions", indent=False,
                                 layout=W.Layout(width="150px"))
        self.v_fscale = W.FloatLogSlider(value=vs.frustum_scale, base=10, min=-1, max=1, step=0.05,
                                         description="frustum scale", style=vstyle, layout=vl,
                                         continuous_update=False)
        self.v_psize = W.FloatLogSlider(value=vs.point_size, base=10, min=-1, max=1, step=0.05,
                                        description="point size", style=vstyle, layout=vl, continuous_update=False)
        self.v_track = W.Dropdown(options=[("none", -1)], value=-1, description="track a point", style=vstyle,
                                  layout=vl, tooltip="the map points seen by most images, longest track first")
        self.v_track_info = W.HTML()
        self.v_clip_on = W.Checkbox(value=False, description="clip to keyframes", indent=False,
                                    layout=W.Layout(width="160px"))
        self.v_clip = W.IntRangeSlider(value=(0, 1), min=0, max=1, description="", layout=W.Layout(width="300px"),
                                       continuous_update=False)
        self.b_camera = W.Button(description="Reset camera", icon="crosshairs", layout=W.Layout(width="150px"),
                                 tooltip="frame the whole map again")
        self.v_units = W.HTML()
        self.v_color = W.Dropdown(options=[("height", "height"), ("image colours", "image")], value=vs.color_by,
                                  description="point colour", style=vstyle, layout=vl)
        self.v_legend = W.HTML(legend_html())

    def _build_frame_view(self) -> None:
        self.f_kf = W.Image(format="jpeg", layout=W.Layout(width="240px"))
        self.f_kf_label = W.HTML()
        self.f_cur = W.Image(format="jpeg", layout=W.Layout(width=f"{self.frame_width}px"))
        self.f_step = W.HTML()
        self.f_summary = W.HTML()
        self.m_kf1 = W.Dropdown(description="keyframes", options=[], layout=W.Layout(width="200px"),
                                style={"description_width": "70px"})
        self.m_kf2 = W.Dropdown(options=[], layout=W.Layout(width="110px"))
        self.b_matches = W.Button(description="Draw matches", icon="random", layout=W.Layout(width="160px"),
                                  tooltip="the keypoints the two keyframes share through 3D points")
        self.m_image = W.Image(format="jpeg", layout=W.Layout(width="640px", display="none"))  # shown once drawn
        self.m_label = W.HTML()

    def _layout(self) -> W.VBox:
        """Controls on top; the 3D map (with its settings) beside the frames; summary and matches below.
        CSS classes name the parts a browser test looks for."""
        controls = W.VBox([
            W.HBox([self.w_source, self.w_default]), self.w_skip, self.w_max, self.w_init, self.w_flow,
            self.w_matches, self.w_help, self.w_features, self.w_features_note, self.w_out,
            W.HBox([self.b_step, self.b_run, self.b_reset, self.b_save, self.b_load, self.b_html]),
            W.HBox([self.w_export_format, self.b_export]),
            self.w_pending, self.w_status,
        ])
        settings = W.VBox([
            W.HBox([self.v_bg, self.b_camera]),
            W.HBox([self.v_pts, self.v_kf, self.v_path, self.v_cur, self.v_dirs]),
            W.HBox([self.v_fscale, self.v_psize]),
            self.v_color,
            W.HBox([self.v_track, self.v_track_info]),
            W.HBox([self.v_clip_on, self.v_clip]),
            self.v_units,
        ])
        frame = W.VBox([W.HTML("<b>last keyframe</b>"), self.f_kf, self.f_kf_label, W.HTML("<b>current frame</b>"),
                        self.f_cur], layout=W.Layout(width=f"{self.frame_width + 20}px"))
        map_box = W.VBox([self.map_html, self.v_legend, settings], layout=W.Layout(flex="0 1 auto", min_width="420px"))
        widget = W.VBox([
            controls,
            W.HBox([map_box, frame]),
            self.f_step, self.f_summary,
            W.HBox([self.m_kf1, self.m_kf2, self.b_matches]), self.m_label, self.m_image,
        ])
        widget.add_class("slamkit-app")
        for w, cls in ((self.b_step, "slamkit-step-button"), (self.b_run, "slamkit-run-button"),
                       (self.b_reset, "slamkit-reset-button"), (self.w_flow, "slamkit-flow-threshold"),
                       (self.w_pending, "slamkit-pending"), (self.map_html, "slamkit-map-view"),
                       (self.b_matches, "slamkit-matches-button"), (self.m_image, "slamkit-match-image"),
                       (self.m_label, "slamkit-match-label"), (self.v_clip_on, "slamkit-clip")):
            w.add_class(cls)
        return widget

    def _ipython_display_(self) -> None:
        display(self.widget)

    def _close_widgets(self) -> None:
        """Close every widget of the app (their comms), containers last."""
        for w in list(vars(self).values()):
            if isinstance(w, W.Widget) and not isinstance(w, W.Box):
                w.close()
        _close_boxes(self.widget)


def _close_boxes(widget) -> None:
    for child in getattr(widget, "children", ()):
        _close_boxes(child)
    widget.close()


__all__ = ["AppWidgets", "LABELS", "feature_options", "unavailable_html", "config_values"]
