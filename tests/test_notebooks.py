"""Every notebook runs top to bottom, headless (nbclient), on the embedded default sequence, and its outputs
read as a student should see them (numbers against truth, no raw HTML, no stale app).

As papermill does, a cell overriding the ``parameters`` cell is inserted after it: a shorter run (40 frames)
and outputs in a temporary folder. A failing cell fails the test with the cell's source and traceback.
The viewer's meshcat server is started by the notebooks and must be gone when the kernel shuts down.
"""

from __future__ import annotations

import importlib.util
import re
import time
from pathlib import Path

import numpy as np
import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")
psutil = pytest.importorskip("psutil")

from conftest import meshcat_servers, notebook_stream  # noqa: E402  (after the skips: psutil is a test extra)

NOTEBOOKS = sorted(p for p in (Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb")
                   if p.stem != "03_ablation")  # executed with its own checks in tests/test_ablate.py

FAST = {"max_frames": 40, "frame_skip": 2, "init_frames": 10}
"""Overrides of the notebooks' parameters for a quick run (names a notebook does not use are harmless)."""


def inject_parameters(nb, values: dict) -> None:
    """Insert a cell setting ``values`` after the cell tagged ``parameters`` (papermill's convention)."""
    idx = next((i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", [])), None)
    assert idx is not None, "every notebook has a cell tagged 'parameters'"
    src = "\n".join(f"{k} = {v!r}" for k, v in values.items())
    cell = nbformat.v4.new_code_cell(src)
    cell.metadata["tags"] = ["injected-parameters"]
    nb.cells.insert(idx + 1, cell)


def test_notebooks_found():
    names = [p.name for p in NOTEBOOKS]
    assert names == ["01_quickstart.ipynb", "02_step_through.ipynb", "04_features_and_matching.ipynb",
                     "05_initialization_and_ba.ipynb", "06_map_reuse.ipynb"]


def test_every_notebook_says_what_it_teaches_and_how_long():
    for path in sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb")):
        first = nbformat.read(path, as_version=4).cells[0]
        assert first.cell_type == "markdown", path.name
        assert "teaches" in first.source and "How long" in first.source, path.name


def _outputs(nb) -> tuple[str, str]:
    """(stream text, text/plain results) of every code cell."""
    outs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    stream = notebook_stream(nb, "stdout") + "\n" + notebook_stream(nb, "stderr")
    plain = "\n".join(o.get("data", {}).get("text/plain", "") for o in outs if "data" in o)
    return stream, plain


def table_rows(plain: str) -> list[list[float]]:
    """The numeric rows of a DataFrame's text/plain output (index dropped), joining the blocks pandas wraps a
    wide table into (lines ending in a backslash)."""
    rows: dict[int, list[float]] = {}
    for m in re.finditer(r"^(\d+)((?:[ \t]+[-+0-9.e]+)+)[ \t]*\\?[ \t]*$", plain, re.M):
        rows.setdefault(int(m.group(1)), []).extend(float(v) for v in m.group(2).split())
    return [rows[k] for k in sorted(rows)]


def drawn_fraction(png: str) -> float:
    """The share of a base64 PNG's pixels that are coloured (not white, not grey): 0 for an empty picture."""
    import base64
    import io

    import numpy as np
    from PIL import Image as PILImage

    rgb = np.asarray(PILImage.open(io.BytesIO(base64.b64decode(png))).convert("RGB"), np.int16)
    return float(((rgb.max(axis=2) - rgb.min(axis=2)) > 40).mean())


def check_views_have_pictures(nb) -> int:
    """Every 3D view (a live meshcat view or a frozen one) is followed by a PNG picture of the map with something
    drawn in it, then the line saying the interactive view needs a trusted notebook: a notebook opened untrusted
    drops the view's HTML (object, iframe) but shows the PNG. Returns how many views were found."""
    views = 0
    for cell in nb.cells:
        outs = cell.get("outputs", []) if cell.cell_type == "code" else []
        for i, o in enumerate(outs):
            html = o.get("data", {}).get("text/html", "")
            if 'class="slamkit-map"' not in html and 'class="slamkit-snapshot"' not in html:
                continue
            views += 1
            picture, hint = (outs[i + 1:i + 3] + [{}, {}])[:2]
            assert "image/png" in picture.get("data", {}), (cell.source[:200], [list(x.get("data", {})) for x in outs])
            assert drawn_fraction(picture["data"]["image/png"]) > 0.01, cell.source[:200]  # a map, not "no map yet"
            assert "Trust Notebook" in hint.get("data", {}).get("text/plain", ""), cell.source[:200]
    return views


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path: Path, tmp_path: Path):
    nb = nbformat.read(path, as_version=4)
    inject_parameters(nb, dict(FAST, out_dir=str(tmp_path / "out")))
    before = meshcat_servers()
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()  # raises CellExecutionError naming the cell
    check_outputs(path.stem, nb, tmp_path / "out")
    # the kernel is gone: so is the meshcat server it started (no orphan holding ports)
    deadline = time.monotonic() + 10
    while (meshcat_servers() - before) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not (meshcat_servers() - before), "a meshcat server outlived its notebook kernel"


def check_bars_complete(nb) -> int:
    """Every text progress bar ends full: the last state of each bar (a bar's updates are joined by carriage
    returns, its close ends the line) reads 100 %. Returns the number of bars."""
    bars = 0
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        text = "".join(o.get("text", "") for o in cell.get("outputs", []) if o.output_type == "stream")
        for line in text.split("\n"):
            if "%|" in line:
                bars += 1
                last = [seg for seg in line.split("\r") if "%|" in seg][-1]
                assert "100%|" in last, (cell.source[:120], last)
    return bars


def check_outputs(stem: str, nb, out: Path) -> None:
    """What an executed notebook ``nb`` (``stem``: its name) shows, and what it wrote to ``out``, read as a student
    should see it: the numbers against truth, and every claim of its prose about a number against the output."""
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors
    text, plain = _outputs(nb)
    stderr = notebook_stream(nb, "stderr")
    assert "Warning" not in stderr, stderr[:1000]  # no stray warning in what a student reads
    # what a student reads: no raw HTML printed, no dataclass repr echoed, no empty keyframe reason
    for bad in ("<span", "<div", "ViewSettings(", "KEYFRAME ()", "matches=0 inliers=0"):
        assert bad not in text and bad not in plain, bad
    pngs = sum("image/png" in o.get("data", {}) for c in nb.cells for o in c.get("outputs", []))
    views = check_views_have_pictures(nb)
    bars = check_bars_complete(nb)
    # 02: mappers 2, loop, app.run 2; 06: the first walk, the second three ways
    assert bars == {"01_quickstart": 1, "02_step_through": 5, "06_map_reuse": 4}.get(stem, 0), bars
    # 02: the loop and kept map; 06: both walks in one view
    assert views == {"01_quickstart": 1, "02_step_through": 2, "06_map_reuse": 1}.get(stem, 0), views
    if stem in ("01_quickstart", "02_step_through"):
        assert (out / "trajectory_tum.txt").is_file() and (out / "sparse").is_dir()
        page = (out / "map.html").read_text()
        assert "<title>slamkit" in page and "slamkit-caption" in page
    if stem == "01_quickstart":
        assert "ATE RMSE" in text
        rmse_cm = float(re.search(r"ATE RMSE: ([0-9.]+) cm", text).group(1))
        assert rmse_cm < 1  # centimetres, after Sim(3) alignment: the reading says real footage gives "centimetres or more"
        described = float(re.search(r"RMSE ([0-9.e-]+) cm", text).group(1))  # the same number, the same unit
        assert described == pytest.approx(rmse_cm, rel=0.01, abs=0.006)
        # the live view kept a frozen copy of the map for the saved notebook
        html_out = "\n".join(o.get("data", {}).get("text/html", "") for c in nb.cells if c.cell_type == "code"
                              for o in c.get("outputs", []))
        assert 'class="slamkit-snapshot"' in html_out and "slamkit-legend" in html_out
        assert pngs >= 1
    if stem == "02_step_through":
        assert "first map:" in text and "keyframe decision" in text and "flow threshold now: 0.08" in text
        # the app is live in its last place only; its earlier places keep the picture and status of the moment it
        # left them: the stepping (a few frames in, below the sections that narrate them), then the 0.05 run's end
        live = [c for c in nb.cells if c.cell_type == "code"
                and any("application/vnd.jupyter.widget-view+json" in o.get("data", {}) for o in c.outputs)]
        assert len(live) == 1 and "app.reset()" in live[0].source, [c.source[:60] for c in live]
        moved = [c for c in nb.cells if c.cell_type == "code" and any(
            "The app moved to a later cell" in o.get("data", {}).get("text/plain", "") for o in c.outputs)]
        assert len(moved) == 2 and moved[0].source.startswith("config = SlamConfig()"), [c.source[:60] for c in moved]

        def app_frames(cell) -> tuple[int, int]:
            status = next(o["data"]["text/plain"] for o in cell.outputs if o.get("data", {}).get("text/plain", "")
                          .startswith("status:"))
            return tuple(int(v) for v in re.search(r"frames (\d+) of (\d+)", status).groups())

        stepped, total = app_frames(moved[0])
        assert 0 < stepped < total, (stepped, total)  # where the stepping cells left it, not the end
        assert app_frames(moved[1]) == (total, total) == app_frames(live[0])
        # the two mappers on the same frames: local mapping's counts per keyframe, both runs posed and accurate
        assert re.search(r"local mapping: \d+ points created, \d+ recent points culled, \d+ duplicates fused", text)
        table = next(c for c in nb.cells if c.cell_type == "code" and c.source.startswith("def compare(run)"))
        found = re.findall(r"^(colmap|local)\s+([0-9.]+)\s+(\d+)\s+(\d+)\s+([0-9.]+)$",
                           table.outputs[0]["data"]["text/plain"], re.M)
        rows = {r[0]: r[1:] for r in found}
        assert set(rows) == {"colmap", "local"}, table.outputs  # keyframes and points printed as integers
        assert all(float(r[0]) > 90 for r in rows.values()), rows
        # the reading's claims: every frame posed, ATEs within a millimetre, local mapping's map smaller; at every
        # keyframe hundreds of points created, recent ones culled and duplicates fused, covisible keyframes growing
        # up to 15
        assert all(float(r[0]) == 100.0 for r in rows.values()), rows
        assert abs(float(rows["colmap"][3]) - float(rows["local"][3])) < 0.1, rows
        assert int(rows["local"][1]) <= int(rows["colmap"][1]) and int(rows["local"][2]) < int(rows["colmap"][2])
        mapping = next(c for c in nb.cells if c.cell_type == "code" and "per_keyframe.append" in c.source)
        per_kf = table_rows(mapping.outputs[-1]["data"]["text/plain"])  # created, culled, fused, obs., covisible, ..
        assert len(per_kf) >= 5 and all(r[0] >= 100 for r in per_kf), per_kf
        assert sum(r[1] > 0 for r in per_kf) >= len(per_kf) - 1 and sum(r[2] > 0 for r in per_kf) >= len(per_kf) - 1
        covisible = [r[4] for r in per_kf]
        assert covisible == sorted(covisible) and max(covisible) <= 15, covisible
        # Run All ends on a populated app: the last cell ran the new settings to the end
        n_before, n_after = (int(v) for v in re.findall(r"0\.0[58]: (\d+)", text.split("keyframes with")[-1]))
        assert n_after >= 2 and "showing the saved run" in text
        assert n_after <= n_before  # what the text says: a higher flow threshold, fewer keyframes (whole runs)
        outs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
        matches_cell = next(c for c in nb.cells if c.cell_type == "code" and "draw_keyframe_matches" in c.source)
        assert any({"image/jpeg", "image/png"} & set(o.get("data", {})) for o in matches_cell.outputs)  # drawn here
        # the live views and the app's map are kept frozen in the saved notebook, legend included
        snapshots = [o for o in outs if 'class="slamkit-snapshot"' in o.get("data", {}).get("text/html", "")]
        assert len(snapshots) >= 2 and all("slamkit-legend" in o["data"]["text/html"] for o in snapshots)
        # the loop-closure section: the city block driven twice drifts by metres over the first lap; the first
        # closure joins the camera back at the start (the end of lap 1 looking down the first street, or lap 2) to a
        # keyframe of the lap's start, brings the two frames back to their true distance and cuts the ATE of the
        # frames before it by 30 % or more; the two cells name the same frames
        assert "LOOP CLOSED with the keyframe of frame" in text and "loop closures so far: 1" in text
        m = re.search(r"the loop closed at frame (\d+) \(lap \d\) with the keyframe of frame (\d+) \(lap 1\)", text)
        assert m, "a closure joining a keyframe to one of the first lap"
        query, candidate = int(m.group(1)), int(m.group(2))
        assert query - candidate >= 300  # frames (0.5 m each): the camera came back round the block
        assert abs(query - 470) <= 50  # the introduction's "about 470 frames round a city block"
        assert f"LOOP CLOSED with the keyframe of frame {candidate} " in text
        g = re.search(r"ground truth: frame (\d+) \(the last one before the closure at frame (\d+)\) and frame (\d+) "
                      r"are ([0-9.e+-]+) m apart; the map put them ([0-9.e+-]+) m apart before the closure, "
                      r"([0-9.e+-]+) m after", text)
        assert g, "the loop closure's gaps against ground truth"
        assert (int(g.group(1)), int(g.group(2)), int(g.group(3))) == (query - 1, query, candidate)
        truth, gap_before, gap_after = (float(v) for v in g.groups()[3:])
        assert abs(gap_before - truth) > 1.0  # a visible drift: metres (measured: 26.4 m for 27.8)
        assert abs(gap_after - truth) < 0.2 * abs(gap_before - truth)  # closed
        a = re.search(r"ATE over the \d+ frames before the closure: ([0-9.e+-]+) m before the correction, "
                      r"([0-9.e+-]+) m after", text)
        assert a and float(a.group(2)) <= 0.7 * float(a.group(1)), a and a.groups()
    if stem == "04_features_and_matching":
        assert "epipolar inliers" in plain and "orb" in plain and "sift" in plain and pngs >= 4
        # rows of the table: index, features, keypoints 1 / 2, matches, epipolar inliers, inlier ratio, ...
        rows = re.findall(r"^\d+\s+(orb|sift)\s+(\d+) / (\d+)\s+(\d+)\s+(\d+)\s+([0-9.]+)", plain, re.M)
        assert [r[0] for r in rows] == ["orb", "sift"], plain
        assert all(int(r[4]) / int(r[3]) == pytest.approx(float(r[5]), abs=1e-3) for r in rows)
        ratios = [float(r[5]) for r in rows]
        assert ratios and min(ratios) > 0.7  # most matches agree with the ground-truth epipolar geometry
        # the reading: "SIFT's agree more closely (a smaller median distance)"; the times are not compared (load)
        median = {m.group(1): float(m.group(2)) for m in
                  re.finditer(r"^\d+\s+(orb|sift)\s+\d+ / \d+\s+\d+\s+\d+\s+[0-9.]+\s+([0-9.]+)", plain, re.M)}
        assert median["sift"] < median["orb"], median
        # the flow-score reading: keyframes come at a steady rhythm and "the matches stay far above the 50 the rule
        # asks for, so it is the flow threshold that decides"
        kfs = [int(v) for v in re.search(r"keyframes: \[([0-9, ]+)\]", text).group(1).split(",")]
        assert len(kfs) >= 4 and max(np.diff(kfs)) <= 2 * min(np.diff(kfs))
        table = text.split("flow score  matches")[1]
        matches = [int(r[-1]) for r in re.findall(r"^\s*(\d+)\s+(\d+)\s+([0-9.]+)\s+(\d+)$", table, re.M)]
        assert len(matches) >= 10 and min(matches) >= 2 * 50, matches
        if importlib.util.find_spec("torch") is None:
            assert "skipped: learned features need torch: pip install" in text
    if stem == "06_map_reuse":
        posed = re.search(r"second walk: (\d+) of (\d+) frames posed", text)
        assert posed and int(posed.group(1)) >= 0.98 * int(posed.group(2)), text
        loaded = re.search(r"the map after it: (\d+) keyframes, (\d+) points \(loaded: (\d+), (\d+)\)", text)
        assert loaded and loaded.group(1) == loaded.group(3) and loaded.group(2) == loaded.group(4)  # nothing added
        under, own = (float(v) for v in re.search(r"under the first run's alignment: RMSE ([0-9.]+) cm over \d+ "
                                                   r"frames \(the first walk's own ATE: ([0-9.]+) cm\)", text).groups())
        assert under < max(3 * own, 1.0)  # "of the order of the first walk's own ATE (millimetres)"
        view = re.search(r"in the view: (\d+) map points, (\d+) keyframes, .* the second walk's (\d+) frames", text)
        assert view and int(view.group(1)) > 1000 and int(view.group(3)) == int(posed.group(2))
        table = next(c for c in nb.cells if c.cell_type == "code" and c.source.startswith("runs = {"))
        plain = table.outputs[-1]["data"]["text/plain"]
        rows = {name: [float(v) for line in re.findall(rf"^{name}\s+(.*?)\s*\\?$", plain, re.M) for v in line.split()]
                for name in ("localize-only", "mapping", "no map")}  # the blocks pandas wraps the table into, joined
        assert all(len(r) == 4 for r in rows.values()), plain
        assert all(r[0] >= 98 for r in rows.values()), rows  # posed %
        assert rows["localize-only"][1] == 0 and rows["mapping"][1] > 0  # keyframes added
        assert rows["localize-only"][2] < 1.0 and rows["mapping"][2] < 1.0  # cm under the first run's alignment
        assert rows["no map"][2] > 10 * max(rows["mapping"][2], 0.1)  # "off by tens of centimetres"
        assert all(r[3] < 1.0 for r in rows.values())  # a good shape after its own Sim(3)
    if stem == "05_initialization_and_ba":
        assert "inliers of E in front of both cameras" in text and pngs >= 2
        rot = float(re.search(r"relative rotation error ([0-9.]+) deg", text).group(1))
        assert rot < 1.0  # degrees, against the exact ground truth
        perturbed, adjusted = (float(v) for v in re.search(r"median reprojection error ([0-9.]+) px -> ([0-9.]+) px",
                                                            text).groups())
        assert adjusted < 0.5 * perturbed  # bundle adjustment brings the perturbed map back
        # the readings' claims, against what the cells print
        angle, reproj = (float(v) for v in re.search(r"median triangulation angle ([0-9.]+) deg; median two-view "
                                                      r"reprojection error ([0-9.]+) px", text).groups())
        assert reproj <= 1.2  # "around a pixel or below"
        table = next(c for c in nb.cells if c.cell_type == "code" and "for gap in" in c.source)
        gaps = {int(r[0]): r[1:] for r in table_rows(table.outputs[0]["data"]["text/plain"])}  # gap -> inliers, angle, ..
        assert sorted(gaps) == [2, 5, 10, 20, 40] and all(len(v) == 4 for v in gaps.values()), gaps
        inl, ang, rot, trans = (dict((g, v[i]) for g, v in gaps.items()) for i in range(4))
        assert ang[2] < 1 and trans[2] > 10 and inl[2] < 50  # a fraction of a degree, tens of degrees, a handful
        assert all(rot[g] < 1 and trans[g] < 5 for g in (10, 20))  # an accurate pose
        assert rot[40] > 5 and trans[40] > 30 and inl[40] >= 100  # wrong, despite a hundred or more inliers
        assert 0.1 < inl[40] / inl[5] < 0.35  # "about a fifth of the 5-frame pair's inliers"
        assert perturbed > 1.5 and adjusted < 0.8  # "from a few pixels back to about half a pixel"
        moved = [float(v) for v in re.search(r"points ([0-9.]+) -> ([0-9.]+) map units", text).groups()]
        assert 0.05 < moved[1] / moved[0] < 0.9  # "only part of the way back"
        finish = next(c for c in nb.cells if c.cell_type == "code" and "slam.finish()" in c.source)
        med = re.search(r"median reprojection error \(px\)\s+([0-9.]+)\s+([0-9.]+)",
                        finish.outputs[0]["data"]["text/plain"])
        assert abs(adjusted - float(med.group(1))) < 0.2  # "the level of the unperturbed map"
        assert abs(float(med.group(2)) - float(med.group(1))) < 0.1  # "little changes" with finish()
        # self-calibration: the unknown camera's focal length within 1 % after the run, a forward-only one weak
        err = float(re.search(r"error against the true focal length: ([-+0-9.]+) %", text).group(1))
        assert abs(err) < 1.0
        last = re.search(r"60 frames: f = ([0-9.]+) px .*± ([0-9.]+) % .*the error is ([-+][0-9.]+) % .*(inside|outside) "
                         r"the ±", text)
        assert last, text
        # the ± printed is the run's (2 sd), and "inside" is true of the numbers printed
        first_frames = re.search(r"first frames: f=([0-9.]+) px ± ([0-9.]+) %", text)
        assert first_frames and first_frames.group(2) == last.group(2) and first_frames.group(1) == last.group(1)
        assert last.group(4) == ("inside" if abs(float(last.group(3))) <= float(last.group(2)) else "outside")
        assert abs(err) < abs(float(last.group(3)))  # the run's bundle adjustment refines it "towards the truth"
        weak = next(line for line in text.splitlines() if "weak, not a measurement" in line)
        assert "±" not in weak and not weak.rstrip().endswith(":")  # no interval on a weak estimate, a reason
        forward = next(c for c in nb.cells if c.cell_type == "code" and 'synthetic:forward' in c.source)
        assert notebook_stream(nbformat.v4.new_notebook(cells=[forward]), "stdout").startswith("no estimate")  # "(as here)"
