"""The tutorials (docs/tutorials/*.py, notebooks kept as jupytext scripts) run top to
bottom in a Jupyter kernel as the site is built (``mkdocs build``, which CI runs), as a
learner would run them; the build fails on an error in a cell, an output to stderr (a
warning a learner would take for a fault) or a notebook without a figure. These tests
check that the tutorials are listed and readable as notebooks, and that a build does
refuse such a notebook."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jupytext
import pytest

REPO = Path(__file__).resolve().parents[1]
TUTORIALS = sorted((REPO / "docs" / "tutorials").glob("*.py"))


def test_there_are_tutorials_and_the_site_lists_each_one():
    nav = (REPO / "mkdocs.yml").read_text()
    index = (TUTORIALS[0].parent / "index.md").read_text()
    assert len(TUTORIALS) >= 5
    for path in TUTORIALS:
        assert f"tutorials/{path.name}" in nav, f"{path.name} is not in mkdocs.yml's nav"
        assert f"]({path.name})" in index, f"{path.name} is not in docs/tutorials/index.md"


@pytest.mark.parametrize("path", TUTORIALS, ids=lambda path: path.stem)
def test_tutorial_is_a_notebook_of_valid_python(path: Path):
    notebook = jupytext.read(path)
    code = [cell.source for cell in notebook.cells if cell.cell_type == "code"]
    assert code and notebook.cells[0].cell_type == "markdown", f"{path.name}: title, then code"
    for i, source in enumerate(code):
        lines = [line for line in source.splitlines() if not line.lstrip().startswith(("%", "!"))]
        compile("\n".join(lines), f"{path.name}, code cell {i + 1}", "exec")


CLEAN = """\
# %% [markdown]
# # Clean

# %%
import matplotlib.pyplot as plt

print("to stdout")
plt.plot([0, 1])
plt.show()
"""

FAULTY = """\
# %% [markdown]
# # Faulty

# %%
import warnings

warnings.warn("a learner would take this for a fault")
"""


def test_the_site_build_refuses_a_tutorial_that_warns_or_draws_nothing(tmp_path):
    # The site's own build settings (the project's hooks, mkdocs-jupyter executing the
    # notebooks) on two small notebooks: one clean, one that warns and draws nothing.
    docs = tmp_path / "docs"
    (docs / "tutorials").mkdir(parents=True)
    (docs / "index.md").write_text("# Home\n")
    (docs / "tutorials" / "clean.py").write_text(CLEAN)
    (docs / "tutorials" / "faulty.py").write_text(FAULTY)
    (tmp_path / "mkdocs.yml").write_text(
        "site_name: t\nstrict: true\n"
        f"hooks: [{REPO / 'docs' / 'hooks.py'}]\n"
        "plugins:\n  - mkdocs-jupyter:\n"
        '      include: ["tutorials/*.py"]\n      execute: true\n'
        "      allow_errors: false\n      cache: false\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MPLBACKEND", "RL_PG_DOCS_EXECUTE")}
    built = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--site-dir", str(tmp_path / "site")],
        cwd=tmp_path, env={**env, "NO_MKDOCS_2_WARNING": "1"}, capture_output=True, text=True,
    )  # fmt: skip
    warnings = [line for line in built.stderr.splitlines() if line.startswith("WARNING")]
    assert built.returncode != 0, built.stderr[-3000:]
    assert any("tutorials/faulty.py printed to stderr" in line for line in warnings), warnings
    assert "a learner would take this for a fault" in built.stderr
    assert any("tutorials/faulty.py draws no figure" in line for line in warnings), warnings
    assert not any("clean.py" in line for line in warnings), warnings
    output = built.stdout + built.stderr
    assert "Aborted with 2 warnings in strict mode" in output, output[-3000:]
