"""The documentation's code: every ```python block of docs/ runs, page by page.

Blocks of one page share a namespace and run top to bottom, as a reader would paste
them. Pages with nothing to run are skipped.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
BLOCK = re.compile(r"^```python\n(.*?)^```", re.DOTALL | re.MULTILINE)
PAGES = sorted(p for p in DOCS.rglob("*.md") if BLOCK.search(p.read_text()))


def test_there_is_code_to_run():
    assert PAGES, "no ```python block found under docs/"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(DOCS)))
def test_page_code_runs(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # anything a block writes lands in a temporary directory
    namespace: dict = {"__name__": "__docs__"}
    for number, block in enumerate(BLOCK.findall(page.read_text()), start=1):
        try:
            exec(compile(block, f"{page.name}:block{number}", "exec"), namespace)
        except Exception as err:
            raise AssertionError(f"{page.name}, code block {number} failed: {err!r}") from err
