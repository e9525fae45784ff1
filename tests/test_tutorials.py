"""The tutorials (docs/tutorials/*.py, notebooks kept as jupytext scripts) run top to
bottom in a Jupyter kernel, as a learner would run them, and print nothing to stderr
(no warning a learner would take for a fault)."""

from __future__ import annotations

from pathlib import Path

import jupytext
import pytest
from nbclient import NotebookClient

TUTORIALS = sorted((Path(__file__).resolve().parents[1] / "docs" / "tutorials").glob("*.py"))


def test_there_are_tutorials_and_the_site_lists_each_one():
    nav = (TUTORIALS[0].parents[2] / "mkdocs.yml").read_text()
    index = (TUTORIALS[0].parent / "index.md").read_text()
    assert len(TUTORIALS) >= 5
    for path in TUTORIALS:
        assert f"tutorials/{path.name}" in nav, f"{path.name} is not in mkdocs.yml's nav"
        assert f"]({path.name})" in index, f"{path.name} is not in docs/tutorials/index.md"


@pytest.mark.parametrize("path", TUTORIALS, ids=lambda path: path.stem)
def test_tutorial_runs_top_to_bottom(path: Path, monkeypatch):
    # The kernel inherits this process's environment: a test that imported EnvPool here
    # left MPLBACKEND=Agg, which would keep the notebooks' figures from being shown.
    monkeypatch.delenv("MPLBACKEND", raising=False)
    notebook = jupytext.read(path)
    client = NotebookClient(
        notebook,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},  # run where the site runs it
    )
    client.execute()  # raises CellExecutionError, naming the cell, on any error
    stderr = [
        output["text"]
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.outputs
        if output.get("name") == "stderr"
    ]
    assert not stderr, f"{path.name} printed to stderr:\n" + "\n".join(stderr)
    figures = sum(
        "image/png" in output.get("data", {})
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.outputs
    )
    assert figures >= 1, f"{path.name} draws no figure"
