"""The documentation's code: every ```python block of docs/ runs, page by page.

Blocks of one page share a namespace and run top to bottom, as a reader would paste
them. A block titled as a file (```python title="script.py"```) is a whole script: it
runs on its own as ``python script.py``, as a reader would save and run it. A block
followed directly by a ```text title="Output" block must print exactly that text.
Pages with nothing to run are skipped.
"""

from __future__ import annotations

import contextlib
import gc
import io
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
BLOCK = re.compile(
    r'^```python\n(?P<code>.*?)^```\n(?:\n?^```text title="Output"\n(?P<output>.*?)^```\n)?',
    re.DOTALL | re.MULTILINE,
)
SCRIPT = re.compile(
    r'^```python title="(?P<name>[\w-]+\.py)"\n(?P<code>.*?)^```\n'
    r'(?:\n?^```text title="Output"\n(?P<output>.*?)^```\n)?',
    re.DOTALL | re.MULTILINE,
)
PAGES = sorted(p for p in DOCS.rglob("*.md") if BLOCK.search(p.read_text()))
SCRIPTS = [
    (page, match)
    for page in sorted(DOCS.rglob("*.md"))
    for match in SCRIPT.finditer(page.read_text())
]


def _lines(text: str) -> list[str]:
    return [line.rstrip() for line in text.strip("\n").splitlines()]


@pytest.mark.parametrize(
    ("page", "script"), SCRIPTS, ids=lambda x: x["name"] if isinstance(x, re.Match) else ""
)
def test_page_scripts_run_as_scripts(page, script, tmp_path):
    path = tmp_path / script["name"]
    path.write_text(script["code"])
    try:
        done = subprocess.run(
            [sys.executable, path.name], cwd=tmp_path, capture_output=True, text=True,
            timeout=300,
        )  # fmt: skip
    except subprocess.TimeoutExpired as err:
        raise AssertionError(f"{page.name}: {path.name} did not end in 5 minutes") from err
    assert done.returncode == 0, f"{page.name}: {path.name} failed:\n{done.stderr[-3000:]}"
    if script["output"] is not None:
        assert _lines(done.stdout) == _lines(script["output"]), (
            f"{page.name}: {path.name} printed something else than its Output block"
        )


def test_there_is_code_to_run():
    assert PAGES, "no ```python block found under docs/"


def test_output_blocks_follow_code():
    text = '```python\nprint(1)\n```\n\n```text title="Output"\n1\n```\n```python\nx = 2\n```\n'
    found = [(m["code"], m["output"]) for m in BLOCK.finditer(text)]
    assert found == [("print(1)\n", "1\n"), ("x = 2\n", None)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(DOCS)))
def test_page_code_runs(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # anything a block writes lands in a temporary directory
    # The page runs as a module of its own, as a reader's script would (dataclasses and
    # pickling look their module up in sys.modules).
    module = types.ModuleType("__docs__")
    monkeypatch.setitem(sys.modules, "__docs__", module)
    namespace = module.__dict__
    for number, match in enumerate(BLOCK.finditer(page.read_text()), start=1):
        printed = io.StringIO()
        try:
            with contextlib.redirect_stdout(printed):
                exec(compile(match["code"], f"{page.name}:block{number}", "exec"), namespace)
        except Exception as err:
            raise AssertionError(f"{page.name}, code block {number} failed: {err!r}") from err
        if match["output"] is not None:
            assert _lines(printed.getvalue()) == _lines(match["output"]), (
                f"{page.name}, code block {number} printed something else than its Output block"
            )
    # Finalise what the page built now, not at interpreter exit (see composing.md).
    namespace.clear()
    gc.collect()


def _hooks():
    sys.path.insert(0, str(DOCS))
    try:
        import hooks
    finally:
        sys.path.remove(str(DOCS))
    return hooks


def test_maths_becomes_mathml_outside_code_only():
    hooks = _hooks()
    page = (
        "A policy $\\pi_\\theta(a \\mid s)$ and $G_t$; it costs $5 and $ 3 $.\n\n"
        "`echo $HOME` and `$x$` stay code.\n\n```bash\nexport A=$B$C\n```\n\n"
        "$$\nJ(\\theta) = \\sum_t r_t\n$$\n"
    )
    html = hooks.on_page_markdown(page)
    assert html.count('display="inline"') == 2  # the policy and G_t, nothing else
    # inline maths starting a line stays in its paragraph (a bare <math> there is a block)
    import markdown

    rendered = markdown.markdown(hooks.on_page_markdown("The policy\n$\\pi$ acts.\n"))
    assert rendered.startswith("<p>The policy") and rendered.count("<p>") == 1, rendered
    assert html.count('display="block"') == 1
    for kept in ("$5 and $ 3 $", "`echo $HOME`", "`$x$`", "export A=$B$C"):
        assert kept in html, kept
    # every page of the site: no $...$ left unrendered in running text
    for path in sorted(DOCS.rglob("*.md")):
        rendered = hooks.CODE.split(hooks.on_page_markdown(path.read_text()))
        prose = "".join(part for i, part in enumerate(rendered) if i % 2 == 0)
        assert not hooks.INLINE_MATH.search(prose), path.name


def test_a_tutorials_html_gets_mathml_and_links_to_built_pages():
    hooks = _hooks()
    rendered = (  # what mkdocs-jupyter makes of a Markdown cell, a code cell and an output
        "<p>$$\nJ(\\theta) = \\sum_a \\pi_a r_a\n$$</p>\n"
        '<p>see the <a href="../theory.md#the-objective">theory</a>, <a href="other.py">'
        'notebook 2</a> and <a href="https://example.org/x.md">elsewhere</a>; '
        "$a &lt; b$ costs $5 and $ 3 $</p>"
        '<pre><span>x = "$a$"</span></pre><pre>cost: $1 and $2</pre>'
        '<div class="clipboard-copy-txt" id="cell-4">plt.plot(label=r"$\\sqrt{N}$")</div>'
    )
    html = hooks.notebook_html(rendered, "tutorials")
    assert html.count('display="block"') == 1
    assert html.count('display="inline"') == 1  # a < b, unescaped for latex2mathml
    assert "<mo>&#x0003C;</mo>" in html
    assert 'href="../../theory/#the-objective"' in html  # the page is tutorials/name/
    assert 'href="../../tutorials/other/"' in html
    assert 'href="https://example.org/x.md"' in html
    for kept in ("$5 and $ 3 $", 'x = "$a$"', "cost: $1 and $2", 'label=r"$\\sqrt{N}$"'):
        assert kept in html, kept
