"""docs/scripting.ipynb runs headless (nbclient) against the simulated bench, with short
parameters, and shows what the simulated world holds (issue 17)."""

from __future__ import annotations

import re
from pathlib import Path

import nbformat
from nbclient import NotebookClient

from feedbench.sim_backends.world import world_truth

NOTEBOOK = Path(__file__).parents[1] / "docs" / "scripting.ipynb"
SHORT = """chirp_duration_s = 2.0
chirp_repetitions = 2
friction_feeds_mm_min = [25, 50, 100, 200, 400, 800, 1500]
friction_settle_s = 0.3"""
"""Injected after the notebook's ``parameters`` cell (as papermill does)."""


def test_the_notebook_runs_and_shows_its_numbers_plots_and_report(tmp_path):
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    at = next(i for i, cell in enumerate(notebook.cells)
              if "parameters" in cell.metadata.get("tags", ()))
    notebook.cells.insert(at + 1, nbformat.v4.new_code_cell(SHORT))
    NotebookClient(notebook, timeout=300, kernel_name="python3",
                   resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [out for cell in notebook.cells if cell.cell_type == "code"
               for out in cell.outputs]
    text = "".join(out.get("text", "") for out in outputs)
    truth = world_truth({})
    f_t, f_r = map(float, re.search(r"f_t = (\S+) Hz, f_r = (\S+) Hz", text).groups())
    assert abs(f_t - truth["f_t_hz"]) < 0.02 * truth["f_t_hz"]  # 61.37 Hz within 2 %
    assert abs(f_r - truth["f_r_hz"]) < 0.03 * truth["f_r_hz"]  # 74.89 Hz within 3 %
    for direction in ("positive", "negative"):
        F_c = float(re.search(rf"{direction}: F_c = (\S+) N", text).group(1))
        assert abs(F_c - truth["friction"][direction]["F_c"]) < 0.02 * 44.2  # within 0.9 N
    assert "complete" in text
    assert sum("image/png" in out.get("data", {}) for out in outputs) == 2  # inline plots
    link = notebook.cells[-1].outputs[0]["data"]["text/markdown"]
    report = tmp_path / re.search(r"\]\((.+)\)", link).group(1)
    assert report.name == "report.html" and report.stat().st_size > 50_000
