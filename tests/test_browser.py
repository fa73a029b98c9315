"""The step-through notebook in a real browser: JupyterLab + headless Debian chromium driven by Playwright.

Opens ``02_step_through`` in JupyterLab on a loopback port, runs all cells (Run All must end on a populated
app), then uses the app as a person would: Draw matches, clip the map, Reset (the match picture, its label and
the clip range must go), Step three frames, drag the flow-threshold slider (the app must say the change is
pending until Reset), Reset, Run, Pause (the kernel must stay responsive during the run), Run to the end.
Inside the meshcat viewer's iframe it counts the three.js scene's points and keyframe frustums against the
app's map, checks that the current-frame marker sits at the end of the drawn path after the run (the final
bundle adjustment moved it) and inside the view, that the newest frames stay inside the view while the run
goes (paused mid-run: the view follows the camera) with the legend under the viewer, not over it, that the
legend lists only what is drawn, that the map's projected 5-95 % box covers at least half of the viewer with
the camera the app set, and compares screenshots of the 3D view before and after the run. No output may
show raw HTML text. Then the saved notebook (no widget state: `make lab`'s setting): opened by another server
from a fresh trust store (untrusted), then trusted; reopened without a kernel; converted offline; saved again
and reopened. In every cell with a 3D view or the app a picture is drawn, no image is broken, no 3D box stands
empty, no dead control is shown (the app's live place says once that its model is gone, then shows its picture
and status text with the final counts), and no maths shows as raw LaTeX. A second test does the same for
``01_quickstart`` executed headless.

Skipped, with the reason, when chromium (``/usr/bin/chromium``), Playwright (Python) or JupyterLab is not
installed. Screenshots go to the test's temporary folder (and to ``$SLAMKIT_SCREENSHOTS`` when set).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                 "--disable-dev-shm-usage", "--disable-background-networking", "--disable-component-update",
                 "--no-first-run", "--disable-sync"]
NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "02_step_through.ipynb"
PARAMS = {"max_frames": 60, "frame_skip": 2, "init_frames": 10, "loop_source": "synthetic:handheld?frames=60"}
"""A short run: 60 frames of the default sequence (long enough that Pause, clicked after frame 16, lands mid-run),
and 60 hand-held frames for the loop section, which never come back to a place and close no loop (the lesson's
closure on the city block, 820 frames into its two laps, and its numbers are checked by tests/test_notebooks.py
without a browser: minutes of CPU)."""

if not os.path.exists(CHROMIUM):
    pytest.skip(f"{CHROMIUM} not found (apt-get install -y chromium)", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright (Python) is not installed")
pytest.importorskip("jupyterlab", reason="jupyterlab is not installed")
nbformat = pytest.importorskip("nbformat")
psutil = pytest.importorskip("psutil")
PIL = pytest.importorskip("PIL.Image")

from conftest import meshcat_servers  # noqa: E402  (after the skips: psutil is a test extra)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_lab(tmp_path: Path, work: Path, data: str = "data") -> dict:
    """JupyterLab on a free loopback port serving ``work``, with an isolated config and data folder (``data``: a
    fresh one is a fresh trust store, where no notebook is trusted), widget state not saved (as `make lab`
    configures it) and every cell rendered (no windowing, so every output can be inspected)."""
    env = dict(os.environ, JUPYTER_CONFIG_DIR=str(tmp_path / "config"), JUPYTER_DATA_DIR=str(tmp_path / data),
               JUPYTERLAB_SETTINGS_DIR=str(tmp_path / "config" / "lab" / "user-settings"),
               JUPYTERLAB_WORKSPACES_DIR=str(tmp_path / "workspaces"), JUPYTER_RUNTIME_DIR=str(tmp_path / "runtime"))
    jupyter = [sys.executable, "-m", "jupyter"]
    subprocess.run(jupyter + ["labextension", "disable", "--level=user",
                              "@jupyterlab/apputils-extension:announcements"], env=env, check=True,
                   capture_output=True)
    settings = Path(env["JUPYTERLAB_SETTINGS_DIR"])
    for plugin, value in (("@jupyter-widgets/jupyterlab-manager/plugin", '{"saveState": false}'),
                          ("@jupyterlab/notebook-extension/tracker", '{"windowingMode": "none"}')):
        (settings / f"{plugin}.jupyterlab-settings").parent.mkdir(parents=True, exist_ok=True)
        (settings / f"{plugin}.jupyterlab-settings").write_text(value)
    port = _free_port()
    log = open(tmp_path / "jupyter.log", "a")
    proc = subprocess.Popen(jupyter + ["lab", "--no-browser", f"--port={port}", "--ip=127.0.0.1", "--allow-root",
                                       "--IdentityProvider.token=", "--ServerApp.password=",
                                       "--LabApp.expose_app_in_browser=True", f"--ServerApp.root_dir={work}"],
                            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=work)
    url = f"http://127.0.0.1:{port}"
    lab = dict(url=url, proc=proc, log=log, tmp=tmp_path, work=work, env=env, before=meshcat_servers())
    deadline = time.monotonic() + 90
    while True:
        try:
            urllib.request.urlopen(f"{url}/api/status", timeout=5)
            return lab
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                _stop_lab(lab)
                raise RuntimeError("jupyter lab did not start: " + (tmp_path / "jupyter.log").read_text()[-2000:])
            time.sleep(0.5)


def _stop_lab(lab: dict) -> None:
    lab["proc"].send_signal(signal.SIGTERM)  # kernels shut down cleanly; their meshcat servers exit
    try:
        lab["proc"].wait(timeout=30)
    except subprocess.TimeoutExpired:
        lab["proc"].kill()
    lab["log"].close()


@pytest.fixture
def lab(tmp_path):
    """JupyterLab on 127.0.0.1 with an isolated config and a copy of the notebook (parameters injected)."""
    work = tmp_path / "work"
    work.mkdir()
    nb = nbformat.read(NOTEBOOK, as_version=4)
    idx = next(i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", []))
    params = dict(PARAMS, out_dir=str(tmp_path / "out"))
    cell = nbformat.v4.new_code_cell("\n".join(f"{k} = {v!r}" for k, v in params.items()))
    cell.metadata["tags"] = ["injected-parameters"]
    nb.cells.insert(idx + 1, cell)
    nbformat.write(nb, work / NOTEBOOK.name)
    before = meshcat_servers()
    lab = _start_lab(tmp_path, work)
    try:
        yield lab
    finally:
        _stop_lab(lab)
    deadline = time.monotonic() + 15
    while (meshcat_servers() - before) and time.monotonic() < deadline:
        time.sleep(0.3)
    assert not (meshcat_servers() - before), "a meshcat server outlived JupyterLab's kernel"


SCENE_JS = """() => {
    const root = viewer.scene.getObjectByName("meshcat").getObjectByName("slamkit");
    if (!root) return {points: 0, groups: 0, frustums: 0};
    let points = 0, groups = 0, frustums = 0;
    const pts = root.getObjectByName("points");
    if (pts) pts.traverse(o => {
        if (o.type === "Points") { points += o.geometry.attributes.position.count; groups++; }
    });
    const kf = root.getObjectByName("keyframes");
    if (kf) kf.traverse(o => { if (o.type === "LineSegments") frustums += o.geometry.attributes.position.count / 16; });
    return {points, groups, frustums};
}"""


GEOMETRY_JS = """() => {
    const root = viewer.scene.getObjectByName("meshcat").getObjectByName("slamkit");
    const cam = viewer.camera;
    cam.updateMatrixWorld(true);
    const out = {camera: Array.from(cam.matrixWorld.elements), proj: Array.from(cam.projectionMatrix.elements),
                 aspect: cam.aspect, fov: cam.fov,
                 points: [], path: null, current: null, current_visible: false};
    if (!root) return out;
    root.updateMatrixWorld(true);
    const pts = root.getObjectByName("points");
    if (pts) pts.traverse(o => { if (o.type === "Points" && o.visible)
        out.points.push({m: Array.from(o.matrixWorld.elements),
                         p: Array.from(o.geometry.attributes.position.array)}); });
    const path = root.getObjectByName("path");
    if (path) path.traverse(o => { if (o.type === "LineSegments")
        out.path = {m: Array.from(o.matrixWorld.elements), p: Array.from(o.geometry.attributes.position.array)}; });
    const cur = root.getObjectByName("current");
    if (cur) cur.traverse(o => { if (o.type === "LineSegments") {
        out.current = Array.from(o.matrixWorld.elements);
        let v = true; for (let a = o; a; a = a.parent) v = v && a.visible;
        out.current_visible = v; } });
    return out;
}"""


def _mat(elements) -> np.ndarray:
    return np.array(elements, np.float64).reshape(4, 4).T  # three.js stores column-major


def _world(obj) -> np.ndarray:
    xyz = np.array(obj["p"], np.float64).reshape(-1, 3)
    M = _mat(obj["m"])
    return xyz @ M[:3, :3].T + M[:3, 3]


def _check_geometry(viewer_frame, frame_el) -> dict:
    """What a student sees after a run to the end: the marker at the end of the path, the map filling the view."""
    frame_el.scroll_into_view_if_needed()
    time.sleep(0.6)  # the viewer renders (and its camera moves) on the next animation frame
    g = _wait(lambda: (lambda g: g if g["points"] and g["path"] and g["current"] else None)(
        viewer_frame.evaluate(GEOMETRY_JS)), 30, "the map, the path and the current frame in the viewer")
    path_end = _world(g["path"])[-1]  # the last vertex of the last segment: the last posed frame
    marker = _mat(g["current"])[:3, 3]
    points = np.concatenate([_world(o) for o in g["points"]])
    extent = np.ptp(np.percentile(points, [5, 95], axis=0), axis=0).max()
    gap = float(np.linalg.norm(marker - path_end))
    assert g["current_visible"] and gap < 0.01 * extent, (gap, extent)  # at the final pose, not the pre-BA one
    view = np.linalg.inv(_mat(g["camera"]))  # world -> camera, from the camera's pose as the app set it

    def ndc(xyz):
        clip = np.c_[xyz, np.ones(len(xyz))] @ (_mat(g["proj"]) @ view).T
        front = clip[:, 3] > 0
        return clip[front, :2] / clip[front, 3:4], front

    # the map's box on screen: the 5-95 % range of the points (a few far ones aside) and the whole camera path
    on_screen, front = ndc(points)
    path_ndc, _ = ndc(_world(g["path"]))
    lo = np.minimum(np.percentile(on_screen, 5, axis=0), path_ndc.min(axis=0))
    hi = np.maximum(np.percentile(on_screen, 95, axis=0), path_ndc.max(axis=0))
    lo, hi = np.clip(lo, -1, 1), np.clip(hi, -1, 1)
    coverage = float(np.prod(hi - lo) / 4)  # NDC spans [-1, 1] on both axes
    info = {"marker_gap": gap, "extent": float(extent), "coverage": coverage, "aspect": g["aspect"],
            "camera": _mat(g["camera"])[:3, 3].round(3).tolist(), "in_front": float(front.mean()),
            "box": [lo.round(3).tolist(), hi.round(3).tolist()]}
    print("framing:", info)
    assert front.mean() > 0.95 and coverage >= 0.5, info
    # the current frame is inside the view (the legend is under the viewer, not over it)
    marker_ndc, marker_front = ndc(marker[None])
    assert marker_front.all() and np.abs(marker_ndc).max() < 1.0, marker_ndc
    return info


def _check_following(viewer_frame, frame_el, page) -> dict:
    """During a run (paused): the newest frame of the path, and the current frame when drawn, are inside
    the view as its camera is now, and the app's legend is under the viewer, not over it."""
    frame_el.scroll_into_view_if_needed()
    time.sleep(0.6)
    g = _wait(lambda: (lambda g: g if g["path"] else None)(viewer_frame.evaluate(GEOMETRY_JS)), 30, "the path")
    view = np.linalg.inv(_mat(g["camera"]))
    newest = [_world(g["path"])[-1]] + ([_mat(g["current"])[:3, 3]] if g["current"] and g["current_visible"] else [])
    clip = np.c_[np.array(newest), np.ones(len(newest))] @ (_mat(g["proj"]) @ view).T
    assert (clip[:, 3] > 0).all(), clip
    ndc = clip[:, :2] / clip[:, 3:4]
    viewer = frame_el.bounding_box()
    legend = page.locator(".slamkit-app .slamkit-legend").first.bounding_box()
    clear = legend["y"] >= viewer["y"] + viewer["height"] - 1 or legend["y"] + legend["height"] <= viewer["y"] + 1
    info = {"newest_ndc": ndc.round(3).tolist(), "legend_clear_of_viewer": clear}
    print("following:", info)
    assert np.abs(ndc).max() < 1.0 and clear, info
    return info


def _live_viewer(page):
    """The app's live viewer page (the frame of the ``<object>`` in the app), once its viewer exists."""
    obj = page.locator(".slamkit-map-view object.slamkit-map").first
    obj.wait_for()
    url = obj.get_attribute("data")
    frame = _wait(lambda: next((f for f in page.frames if f.url == url and not f.is_detached()), None), 30,
                  "the live viewer's page")
    frame.wait_for_function("() => typeof viewer !== 'undefined'")
    return frame


def _save_and_stop_kernel(page, lab) -> Path:
    """Save the notebook from JupyterLab (no widget state: `make lab`'s setting) and shut its kernel down; the
    saved file."""
    path = lab["work"] / NOTEBOOK.name
    mtime = path.stat().st_mtime
    page.evaluate("() => window.jupyterapp.commands.execute('docmanager:save')")
    _wait(lambda: path.stat().st_mtime > mtime, 60, "the notebook saved")
    time.sleep(1.0)  # the file is complete
    assert "widget-state" not in path.read_text(), "widget state saved: the app would reopen as dead controls"
    page.evaluate("() => window.jupyterapp.serviceManager.sessions.shutdownAll()")
    _wait(lambda: not (meshcat_servers() - lab["before"]), 30, "the kernel's meshcat servers to stop")
    return path


def _snapshot_scenes(page, min_views: int) -> list[dict]:
    """The scene of every frozen map (``iframe.slamkit-snapshot``) on the page, each scrolled into view."""
    frames = page.locator("iframe.slamkit-snapshot")
    _wait(lambda: frames.count() >= min_views, 60, f"{min_views} frozen maps")
    scenes = []
    for i in range(frames.count()):
        el = frames.nth(i)
        if not el.is_visible():
            continue
        el.scroll_into_view_if_needed()
        frame = _wait(lambda: el.element_handle().content_frame(), 30, "the frozen map's page")
        frame.wait_for_function("() => typeof viewer !== 'undefined'", timeout=60_000)
        scenes.append(_wait(lambda: (lambda sc: sc if sc["points"] else None)(frame.evaluate(SCENE_JS)), 30,
                            "the frozen map's points"))
    return scenes


def _check_saved_without_kernel(browser, page, lab, saved: Path, final: dict) -> None:
    """The saved notebook with no kernel: as ``nbconvert --to html`` in chromium from file://, and reopened in
    JupyterLab. No view may be an error page or empty: each live view shows its frozen map (or says it needs
    the kernel), the frozen maps hold points and keyframes; the app, saved without widget state, comes back as
    its picture and status (:func:`_check_cells`), with no dead controls."""
    nb = nbformat.read(saved, as_version=4)
    assert "application/vnd.jupyter.widget-state+json" not in nb.metadata.get("widgets", {}), "widget state saved"
    # JupyterLab, reopened (the notebook trusted: it was run here): the maps frozen in the outputs, the app as
    # its picture and status
    page.reload()
    page.wait_for_function("() => window.jupyterapp && window.jupyterapp.shell.currentWidget", timeout=90_000)
    page.locator(".jp-OutputArea-output").first.wait_for(timeout=60_000)
    time.sleep(2.0)
    cells = _check_cells(page, saved, trusted=True, tag="reopened")
    scenes = _snapshot_scenes(page, 2)
    assert all(sc["points"] > 100 and sc["frustums"] >= 3 for sc in scenes), scenes
    # the app as it was when saved (after the clicks above), in its status text under its live place
    assert page.get_by_text(f"keyframes {final['keyframes']} · points {final['points']}").count() >= 1, final
    print("reopened in JupyterLab, frozen maps:", scenes, "cells:", cells)
    out = lab["tmp"] / "html"
    subprocess.run([sys.executable, "-m", "jupyter", "nbconvert", "--to", "html", str(saved), "--output-dir",
                    str(out)], check=True, capture_output=True, env=lab["env"])
    static = browser.new_page(viewport={"width": 1500, "height": 1100})
    try:
        static.goto((out / saved.with_suffix(".html").name).as_uri())
        scenes = _snapshot_scenes(static, 2)  # the loop closure's view and the app's map in the last cell
        assert len(scenes) >= 2 and all(sc["points"] > 100 and sc["frustums"] >= 3 for sc in scenes), scenes
        for i in range(static.locator("object.slamkit-map").count()):  # dead live views: their fallback only
            assert static.locator("object.slamkit-map").nth(i).evaluate("o => !o.contentDocument")
        print("nbconvert html, frozen maps:", scenes)
    finally:
        static.close()


TWIN_JS = """() => Array.from(document.querySelectorAll('.jp-OutputArea-output img, .output_png img, img'))
    .filter(i => i.src.startsWith('data:image/png') && i.naturalWidth > 0)
    .map(i => [i.naturalWidth, i.naturalHeight])"""
"""Width and height of every PNG image shown (the app's static twin among them)."""


def _check_autosave_cycle(browser, page, lab, saved: Path, final: dict) -> None:
    """The notebook reopened without a kernel and saved again (what autosave writes: the same file as Ctrl+S),
    then reopened once more and converted offline with nbconvert: the app's static twin — a picture of the map
    and the frame panel, and the status text with the final counts — is still there, with no widget state at
    all; and no maths is left as raw LaTeX."""
    mtime = saved.stat().st_mtime
    page.evaluate("() => window.jupyterapp.commands.execute('docmanager:save')")
    _wait(lambda: saved.stat().st_mtime > mtime, 60, "the notebook saved again without a kernel")
    nb = nbformat.read(saved, as_version=4)
    state = nb.metadata.get("widgets", {}).get("application/vnd.jupyter.widget-state+json", {})
    print("widget models after the autosave-like save:", len(state.get("state", {})))
    nb.metadata.pop("widgets", None)  # what autosave leaves, whatever this JupyterLab kept
    nbformat.write(nb, saved)
    app_cell = next(c for c in nb.cells if c.cell_type == "code" and "app.reset()" in c.source)  # its live place
    kinds = [set(o.get("data", {})) for o in app_cell.outputs]
    assert any("image/png" in k for k in kinds), kinds
    status = "\n".join(o["data"]["text/plain"] for o in app_cell.outputs
                       if set(o.get("data", {})) == {"text/plain"})
    assert status.startswith("status: ") and f"frames {final['frames']} of " in status, status
    assert f"keyframes {final['keyframes']} · points {final['points']}" in status, status
    page.reload()
    page.wait_for_function("() => window.jupyterapp && window.jupyterapp.shell.currentWidget", timeout=90_000)
    page.locator(".jp-OutputArea-output").first.wait_for(timeout=60_000)
    status_el = page.get_by_text(status.splitlines()[0]).first
    status_el.wait_for(timeout=60_000)
    pngs = _wait(lambda: page.evaluate(TWIN_JS), 30, "the PNG outputs")
    assert any(w >= 800 and h >= 300 for w, h in pngs), pngs  # the twin's picture (960 x 368)
    status_el.scroll_into_view_if_needed()
    page.screenshot(path=str(lab["tmp"] / "autosaved_reopened.png"))
    _keep_screenshot(lab["tmp"] / "autosaved_reopened.png")
    out = lab["tmp"] / "html-autosaved"
    subprocess.run([sys.executable, "-m", "jupyter", "nbconvert", "--to", "html", str(saved), "--output-dir",
                    str(out)], check=True, capture_output=True, env=lab["env"])
    static = browser.new_page(viewport={"width": 1500, "height": 1100})
    try:
        static.route("http*://**", lambda route: route.abort()
                     if not route.request.url.startswith("http://127.0.0.1") else route.continue_())  # offline
        static.goto((out / saved.with_suffix(".html").name).as_uri())
        static.get_by_text(status.splitlines()[0]).first.wait_for(timeout=30_000)
        text = static.evaluate("() => document.body.innerText")  # what a reader sees: no raw LaTeX
        raw = [t for t in ("$$", "$\\", "\\frac", "\\operatorname", "\\Delta", "\\top", "_{") if t in text]
        assert not raw, raw
        pngs = _wait(lambda: static.evaluate(TWIN_JS), 30, "the PNG outputs in the offline HTML")
        assert any(w >= 800 and h >= 300 for w, h in pngs), pngs
        static.screenshot(path=str(lab["tmp"] / "autosaved_nbconvert.png"))
        _keep_screenshot(lab["tmp"] / "autosaved_nbconvert.png")
    finally:
        static.close()


CELLS_JS = """() => Array.from(document.querySelectorAll('.jp-Notebook .jp-Cell.jp-CodeCell')).map(c => {
    const imgs = Array.from(c.querySelectorAll('.jp-OutputArea-output img'));
    return {png: imgs.filter(i => i.src.startsWith('data:image/png') && i.naturalWidth > 0).length,
            broken: imgs.filter(i => i.complete && i.naturalWidth === 0).length,
            frozen: c.querySelectorAll('iframe.slamkit-snapshot').length,
            empty_boxes: Array.from(c.querySelectorAll('.slamkit-map-box')).filter(b =>
                b.getBoundingClientRect().height > 40 && !b.querySelector('object, iframe')).length,
            widget_errors: (c.innerText.match(/Error displaying widget/g) || []).length,
            controls: c.querySelectorAll('.widget-button, .widget-slider, .widget-dropdown').length,
            text: c.innerText};
})"""
"""Per code cell as the page shows it: PNG pictures, broken images, frozen 3D views, 3D boxes standing empty,
widget errors, widget controls and the text."""


def _check_cells(page, saved: Path, trusted: bool, tag: str) -> list[dict]:
    """Every cell of the notebook open in ``page`` (the file ``saved``) with a 3D view or the app shows a
    picture (a PNG drawn), no broken image and no empty 3D box; a 3D view has the line on trusting the
    notebook and, ``trusted``, its frozen 3D view too; the app shows no controls (there is no kernel to run
    them) and at most its one "model not found" line at its live place. Returns what each such cell shows."""
    nb = nbformat.read(saved, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    _wait(lambda: page.locator(".jp-Notebook .jp-Cell").count() == len(nb.cells), 60, "every cell on the page")
    for k in range(len(nb.cells)):  # JupyterLab renders a long notebook's outputs as they come into view
        page.locator(".jp-Notebook .jp-Cell").nth(k).scroll_into_view_if_needed()
        time.sleep(0.2)
    shown, previous = None, None
    for _ in range(30):  # until what is shown stops changing (multi-megabyte outputs take seconds)
        shown = page.evaluate(CELLS_JS)
        counts = [(c["png"], c["frozen"], c["widget_errors"]) for c in shown]
        if counts == previous and len(shown) == len(code):
            break
        previous = counts
        time.sleep(2.0)
    assert len(shown) == len(code), (len(shown), len(code))
    page.screenshot(path=str(saved.parent / f"{saved.stem}-{tag}.png"))
    _keep_screenshot(saved.parent / f"{saved.stem}-{tag}.png")
    found = []
    for cell, seen in zip(code, shown):
        html = "".join(o.get("data", {}).get("text/html", "") for o in cell.outputs)
        view = 'class="slamkit-map"' in html or 'class="slamkit-snapshot"' in html
        live_app = any("application/vnd.jupyter.widget-view+json" in o.get("data", {}) for o in cell.outputs)
        moved_app = any("The app moved" in o.get("data", {}).get("text/plain", "") for o in cell.outputs)
        assert seen["broken"] == 0 and seen["empty_boxes"] == 0, (tag, cell.source[:80], seen)
        if not (view or live_app or moved_app):
            continue
        info = {k: v for k, v in seen.items() if k != "text"} | {"cell": cell.source.splitlines()[0][:40]}
        found.append(info)
        assert seen["png"] >= 1, (tag, info)  # the map (or the app) as a picture
        assert seen["controls"] == 0 and seen["widget_errors"] <= int(live_app), (tag, info)
        if view:
            assert "Trust Notebook" in seen["text"], (tag, info)
            assert (seen["frozen"] >= 1) == trusted, (tag, info)  # untrusted: the iframe is dropped
        if live_app or moved_app:
            assert "status:" in seen["text"] and "frames " in seen["text"], (tag, info)
    assert found, "no cell with a 3D view or the app"
    print(tag, found)
    return found


def _check_untrusted_after_restart(browser, lab, saved: Path) -> dict:
    """The saved notebook opened by another JupyterLab server (a restart: no kernel of the run is left) with a
    fresh trust store (untrusted, as a notebook someone else ran), then trusted with ``jupyter trust`` and
    opened again."""
    work = lab["tmp"] / "work-reopened"
    work.mkdir()
    saved = Path(shutil.copy(saved, work / saved.name))
    other = _start_lab(lab["tmp"], work, data="data-fresh")
    page = browser.new_page(viewport={"width": 1500, "height": 1100})
    try:
        page.goto(f"{other['url']}/lab/tree/{saved.name}")
        page.wait_for_function("() => window.jupyterapp && window.jupyterapp.shell.currentWidget", timeout=90_000)
        page.locator(".jp-OutputArea-output").first.wait_for(timeout=60_000)
        time.sleep(3.0)
        untrusted = _check_cells(page, saved, trusted=False, tag="untrusted")
        subprocess.run([sys.executable, "-m", "jupyter", "trust", str(saved)], check=True, capture_output=True,
                       env=other["env"])
        page.reload()
        page.wait_for_function("() => window.jupyterapp && window.jupyterapp.shell.currentWidget", timeout=90_000)
        page.locator(".jp-OutputArea-output").first.wait_for(timeout=60_000)
        time.sleep(3.0)
        trusted = _check_cells(page, saved, trusted=True, tag="trusted")
    finally:
        page.close()
        _stop_lab(other)
    return {"untrusted": untrusted, "trusted": trusted}


def _keep_screenshot(path: Path) -> None:
    if os.environ.get("SLAMKIT_SCREENSHOTS"):
        Path(os.environ["SLAMKIT_SCREENSHOTS"]).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(os.environ["SLAMKIT_SCREENSHOTS"]) / path.name)


def _no_raw_html(page) -> None:
    texts = page.locator(".jp-OutputArea-output").all_text_contents()
    bad = [t for t in texts if "<span" in t or "<div" in t or "ViewSettings(" in t]
    assert not bad, bad[:2]


def _summary(page) -> dict:
    def num(sel):
        t = page.locator(f".slamkit-summary {sel}").first.text_content()
        return int(t)
    return {k: num(f".{k}") for k in ("frames", "keyframes", "points", "scene-points", "scene-keyframes")}


def _wait(predicate, timeout: float, what: str, interval: float = 0.25):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _shot(page, frame_el, path: Path) -> np.ndarray:
    frame_el.scroll_into_view_if_needed()
    time.sleep(0.6)  # the viewer renders on the next animation frame
    frame_el.screenshot(path=str(path))
    if os.environ.get("SLAMKIT_SCREENSHOTS"):
        Path(os.environ["SLAMKIT_SCREENSHOTS"]).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(os.environ["SLAMKIT_SCREENSHOTS"]) / path.name)
    return np.asarray(PIL.open(path).convert("RGB"), np.float32)


def test_step_through_notebook_in_chromium(lab):
    tmp = lab["tmp"]
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1500, "height": 1100})
            page.set_default_timeout(60_000)
            page.goto(f"{lab['url']}/lab/tree/{NOTEBOOK.name}")
            page.wait_for_function("() => window.jupyterapp && window.jupyterapp.shell.currentWidget"
                                   " && window.jupyterapp.shell.currentWidget.sessionContext"
                                   " && window.jupyterapp.shell.currentWidget.sessionContext.session"
                                   " && window.jupyterapp.shell.currentWidget.sessionContext.session.kernel",
                                   timeout=90_000)
            page.wait_for_function("() => window.jupyterapp.shell.currentWidget.sessionContext.session.kernel"
                                   ".connectionStatus === 'connected'", timeout=90_000)
            page.evaluate("() => window.jupyterapp.commands.execute('notebook:run-all-cells')")
            # the last cell reruns the app with the pending flow threshold: Run All ends on a populated app
            page.get_by_text("keyframes with flow threshold 0.05:").first.wait_for(timeout=240_000)
            app = page.locator(".slamkit-app").first
            app.wait_for()
            populated = _wait(lambda: (lambda s: s if s["frames"] == PARAMS["max_frames"] else None)(_summary(page)),
                              30, "the populated app")
            assert populated["keyframes"] >= 3 and populated["points"] > 300
            _no_raw_html(page)
            assert page.get_by_text("no loop closed in the 60 frames of synthetic:handheld").count() == 1
            map_frame_el = page.locator(".slamkit-map-view object.slamkit-map").first
            map_frame_el.wait_for()
            viewer_frame = _live_viewer(page)
            geometry = {"run_all": _check_geometry(viewer_frame, map_frame_el)}

            # --- Draw matches and a clip range, then Reset: both belong to the discarded run and must go
            page.locator("button.slamkit-matches-button").first.click()
            _wait(lambda: "observe the same 3D points" in (page.locator(".slamkit-match-label").first.text_content()
                                                          or ""), 30, "the keyframe matches")
            match_img = page.locator("img.slamkit-match-image").first
            _wait(lambda: match_img.evaluate("e => e.naturalWidth") > 0, 30, "the match picture")
            page.locator(".slamkit-clip input[type=checkbox]").first.check()
            page.locator("button.slamkit-reset-button").first.click()
            _wait(lambda: _summary(page)["frames"] == 0, 60, "the reset")
            _wait(lambda: match_img.evaluate("e => e.naturalWidth") == 0, 30, "the match picture to be cleared")
            assert (page.locator(".slamkit-match-label").first.text_content() or "").strip() == ""
            assert not page.locator(".slamkit-clip input[type=checkbox]").first.is_checked()
            assert _summary(page)["frames"] == 0

            # --- Step: three frames, one per click
            step = page.locator("button.slamkit-step-button").first
            for i in range(1, 4):
                step.click()
                _wait(lambda: _summary(page)["frames"] == i, 60, f"frame {i} after Step")

            # --- the flow threshold slider, dragged: pending until Reset, and the UI says so
            slider = page.locator(".slamkit-flow-threshold").first
            slider.scroll_into_view_if_needed()
            handle = slider.locator(".noUi-handle").first
            box = handle.bounding_box()
            page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
            page.mouse.down()
            page.mouse.move(box["x"] + box["width"] / 2 + 60, box["y"] + box["height"] / 2, steps=8)
            page.mouse.up()
            pending = page.locator(".slamkit-pending-text").first
            pending.wait_for(timeout=30_000)
            text = pending.text_content()
            m = re.search(r"flow threshold ([0-9]+\.[0-9]+) → ([0-9]+\.[0-9]+)", text)
            assert m and "takes effect on Reset" in text, text
            running, new_threshold = float(m.group(1)), float(m.group(2))
            assert running == 0.08 and new_threshold > running  # the notebook's last cells ran with 0.08
            step.click()  # the running config is untouched: still stepping with the old threshold
            _wait(lambda: _summary(page)["frames"] == 4, 60, "frame 4")
            assert m.group(0) in page.locator(".slamkit-pending-text").first.text_content()

            # --- Reset: applies it and starts over
            page.locator("button.slamkit-reset-button").first.click()
            _wait(lambda: _summary(page)["frames"] == 0 and page.locator(".slamkit-pending-text").count() == 0,
                  60, "the reset")
            viewer_frame = _live_viewer(page)  # the reset replaced the finished run's frozen map: a new page
            empty = viewer_frame.evaluate(SCENE_JS)
            assert empty == {"points": 0, "groups": 0, "frustums": 0}, empty
            before = _shot(page, map_frame_el, tmp / "map_before_run.png")

            # --- Run, Pause while running (the kernel answers between frames), Run to the end
            run = page.locator("button.slamkit-run-button").first
            run.click()
            _wait(lambda: run.text_content().strip() == "Pause", 30, "the Pause label")
            _wait(lambda: _summary(page)["frames"] >= 16, 120, "frames while running")
            run.click()  # Pause
            _wait(lambda: run.text_content().strip() == "Run", 30, "the run to pause")
            time.sleep(1.0)  # let the last frame's widget updates arrive
            paused_at = _summary(page)["frames"]
            assert paused_at < PARAMS["max_frames"], "Pause came too late to test it"
            time.sleep(2.0)
            assert _summary(page)["frames"] == paused_at  # paused: no more frames
            middle = _shot(page, map_frame_el, tmp / "map_paused.png")
            geometry["paused"] = _check_following(_live_viewer(page), map_frame_el, page)
            run.click()
            _wait(lambda: _summary(page)["frames"] == PARAMS["max_frames"], 120, "the run to finish")
            _wait(lambda: run.text_content().strip() == "Run", 30, "the Run label after the end")
            time.sleep(1.0)
            s = _summary(page)
            assert s["keyframes"] >= 4 and s["points"] > 300
            assert f"{new_threshold:.3f} (flow threshold)" in page.locator(".slamkit-step").first.text_content()

            # --- the three.js scene holds the map: points and keyframe frustums
            viewer_frame = _live_viewer(page)  # the end of the run froze the map into the view: a new page
            scene = _wait(lambda: (lambda sc: sc if sc["points"] == s["points"] else None)(
                viewer_frame.evaluate(SCENE_JS)), 30, "the viewer to receive the map")
            assert scene["points"] == s["points"] == s["scene-points"]
            assert scene["frustums"] == s["keyframes"] == s["scene-keyframes"]
            after = _shot(page, map_frame_el, tmp / "map_after_run.png")
            geometry["run_to_the_end"] = _check_geometry(viewer_frame, map_frame_el)
            legend = page.locator(".slamkit-app .slamkit-legend").first.text_content()
            assert "points by height" in legend and "current frame" in legend, legend
            assert "loop closure" not in legend and "selected track" not in legend, legend  # neither is drawn
            _no_raw_html(page)

            # --- the rendered view changed
            assert before.shape == after.shape
            diff_run = np.abs(after - before).mean(axis=2)
            assert (diff_run > 30).mean() > 0.005, "the 3D view did not change after the run"
            diff_more = np.abs(after - middle).mean(axis=2)
            assert (diff_more > 30).mean() > 0.0005, "the 3D view did not change after the paused part"
            # the page itself, for a look
            app.scroll_into_view_if_needed()
            page.screenshot(path=str(tmp / "page.png"), full_page=False)
            if os.environ.get("SLAMKIT_SCREENSHOTS"):
                shutil.copy(tmp / "page.png", Path(os.environ["SLAMKIT_SCREENSHOTS"]) / "page.png")
            (tmp / "scene.json").write_text(json.dumps({"summary": s, "scene": scene, "geometry": geometry}))
            print("geometry:", geometry)

            # --- Save, stop the kernel, reopen: every 3D view shows a map, the app its widgets
            saved = _save_and_stop_kernel(page, lab)
            _check_untrusted_after_restart(browser, lab, saved)
            _check_saved_without_kernel(browser, page, lab, saved, s)
            _check_autosave_cycle(browser, page, lab, saved, s)
        finally:
            browser.close()


def test_quickstart_executed_opens_untrusted_and_after_a_restart(tmp_path):
    """01_quickstart executed headless (a short run), as a notebook mailed to a classmate: opened in JupyterLab from
    a fresh trust store (untrusted: its 3D view's HTML is dropped), every 3D view still shows the map as a picture
    with the line on trusting the notebook, no broken image, no empty box; trusted with ``jupyter trust`` and
    opened again after a server restart, the frozen 3D view is there too."""
    nbclient = pytest.importorskip("nbclient")
    from test_notebooks import FAST, inject_parameters

    work = tmp_path / "work"
    work.mkdir()
    path = NOTEBOOK.parent / "01_quickstart.ipynb"
    nb = nbformat.read(path, as_version=4)
    inject_parameters(nb, dict(FAST, out_dir=str(tmp_path / "out")))
    nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                            resources={"metadata": {"path": str(work)}}).execute()
    saved = work / path.name
    nbformat.write(nb, saved)
    before = meshcat_servers()
    lab = _start_lab(tmp_path, work)
    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
            try:
                page = browser.new_page(viewport={"width": 1500, "height": 1100})
                page.goto(f"{lab['url']}/lab/tree/{saved.name}")
                page.wait_for_function("() => window.jupyterapp && window.jupyterapp.shell.currentWidget",
                                       timeout=90_000)
                page.locator(".jp-OutputArea-output").first.wait_for(timeout=60_000)
                time.sleep(3.0)
                untrusted = _check_cells(page, saved, trusted=False, tag="untrusted")
                page.close()
                subprocess.run([sys.executable, "-m", "jupyter", "trust", str(saved)], check=True,
                               capture_output=True, env=lab["env"])
                _stop_lab(lab)
                lab = _start_lab(tmp_path, work)  # the server restarted; the same trust store
                page = browser.new_page(viewport={"width": 1500, "height": 1100})
                page.goto(f"{lab['url']}/lab/tree/{saved.name}")
                page.wait_for_function("() => window.jupyterapp && window.jupyterapp.shell.currentWidget",
                                       timeout=90_000)
                page.locator(".jp-OutputArea-output").first.wait_for(timeout=60_000)
                time.sleep(3.0)
                trusted = _check_cells(page, saved, trusted=True, tag="trusted-after-restart")
            finally:
                browser.close()
    finally:
        _stop_lab(lab)
    assert len(untrusted) == len(trusted) == 1  # the map's cell
    deadline = time.monotonic() + 15
    while (meshcat_servers() - before) and time.monotonic() < deadline:
        time.sleep(0.3)
    assert not (meshcat_servers() - before), "a meshcat server outlived JupyterLab's kernel"
