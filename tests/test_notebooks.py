"""Every notebook runs top to bottom, headless (nbclient), on the embedded default sequence.

As papermill does, a cell overriding the ``parameters`` cell is inserted after it: a shorter run (40 frames)
and outputs in a temporary folder. A failing cell fails the test with the cell's source and traceback.
The viewer's meshcat server is started by the notebooks and must be gone when the kernel shuts down.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")
psutil = pytest.importorskip("psutil")

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


def meshcat_servers() -> set[int]:
    out = set()
    for p in psutil.process_iter(["cmdline"]):
        cmd = p.info["cmdline"] or []
        if any(str(a).endswith("_meshcat_server.py") for a in cmd):
            out.add(p.pid)
    return out


def test_notebooks_found():
    names = [p.name for p in NOTEBOOKS]
    assert "01_quickstart.ipynb" in names and "02_step_through.ipynb" in names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path: Path, tmp_path: Path):
    nb = nbformat.read(path, as_version=4)
    inject_parameters(nb, dict(FAST, out_dir=str(tmp_path / "out")))
    before = meshcat_servers()
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()  # raises CellExecutionError naming the cell
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors
    text = "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
                     if o.output_type == "stream")
    assert (tmp_path / "out" / "trajectory_tum.txt").is_file() and (tmp_path / "out" / "sparse").is_dir()
    assert (tmp_path / "out" / "map.html").is_file()
    if path.stem == "01_quickstart":
        assert "ATE RMSE" in text
        rmse = float(text.split("ATE RMSE: ")[1].split(" m")[0])
        assert rmse < 0.05  # metres, after Sim(3) alignment, on the synthetic room
        assert any("image/png" in o.get("data", {}) for c in nb.cells for o in c.get("outputs", []))
    if path.stem == "02_step_through":
        assert "initialized" in text and "keyframe decision" in text and "flow threshold now: 0.08" in text
    # the kernel is gone: so is the meshcat server it started (no orphan holding ports)
    deadline = time.monotonic() + 10
    while (meshcat_servers() - before) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not (meshcat_servers() - before), "a meshcat server outlived its notebook kernel"
