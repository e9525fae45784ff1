"""MkDocs hook: tables generated from the code, so the docs cannot drift from it.

``{{ config_table("cartpole") }}`` in a page becomes the table of every field of the
cartpole recipe's config (flag, default, description), read from the dataclass and
its field docstrings, the same text ``--help`` prints; ``config_table("play", "Args")``
names a dataclass of a module of the application, ``rl_pg.app``. ``{{ shipped_agents() }}``
becomes the table of the agents shipped with rl_pg and the results their files carry.
A page's stored tables and values are written from their files (``docs/pages.py``), so
the site shows what the stored results hold even where a page was not refreshed.

``$$ ... $$`` blocks of LaTeX, and ``$...$`` inside a line, become MathML when the site
is built (latex2mathml): browsers render MathML themselves, so the maths needs no script
and no network. The tutorials (notebooks that mkdocs-jupyter renders to HTML itself) get
the same in their Markdown cells, and their links to other pages (written as relative
``.md`` files, which also work in Jupyter) point at the built pages.

The build is where the tutorials run (mkdocs-jupyter executes each one in a Jupyter
kernel, and an error in a cell fails it): a tutorial that also prints to stderr (a
warning a learner would take for a fault) or draws no figure is a warning here, which
the strict build turns into a failure. Their kernels log errors only: each would
otherwise warn, as it starts, that it talks to the build over unencrypted TCP (the
loopback, here).
"""

from __future__ import annotations

import atexit
import dataclasses
import html
import importlib
import logging
import os
import posixpath
import re
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

# TorchRL 0.14 warns, with a stack trace, about its own collectors' weight updaters on
# import; it says nothing about these docs, so the build does not print it.
warnings.filterwarnings(
    "ignore",
    message=r"Creating \w+ which inherits from WeightUpdaterBase",
    category=DeprecationWarning,
)

from rl_pg.app.flags import field_docs  # noqa: E402
from rl_pg.recipes import load  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the docs' own tooling
from pages import render  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PATTERN = re.compile(r'\{\{\s*config_table\("(\w+)"(?:,\s*"(\w+)")?\)\s*\}\}')
AGENTS = re.compile(r"\{\{\s*shipped_agents\(\)\s*\}\}")
DISPLAY_MATH = re.compile(r"^\$\$\n(.+?)\n\$\$$", re.MULTILINE | re.DOTALL)
# $...$ inside a line (no space after the opening or before the closing $), outside code.
INLINE_MATH = re.compile(r"(?<![\\$\w])\$(?=\S)([^$\n]+?)(?<=\S)\$(?![\w$])")
CODE = re.compile(r"(^```.*?^```$|`[^`\n]+`)", re.MULTILINE | re.DOTALL)
# In a notebook's HTML: code, outputs and the copy buttons' text are left as they are.
HTML_CODE = re.compile(
    r"(<pre[ >].*?</pre>|<code>.*?</code>|<script.*?</script>"
    r'|<div class="clipboard-copy-txt".*?</div>)',
    re.DOTALL,
)
HTML_DISPLAY_MATH = re.compile(r"<p>\$\$\n(.+?)\n\$\$</p>", re.DOTALL)
MARKDOWN_LINK = re.compile(r'href="(?![a-z]+:|#)([^"#]+)\.(?:md|py)(#[^"]*)?"')
# An executed notebook's outputs, as nbconvert renders them: a stream to stderr, a figure.
STDERR_OUTPUT = re.compile(
    r'<div class="jp-RenderedText[^"]*" data-mime-type="application/vnd\.jupyter\.stderr"'
    r"[^>]*>\s*<pre>(.*?)</pre>",
    re.DOTALL,
)
FIGURE = re.compile(r'<img [^>]*src="data:image/png;base64,')

log = logging.getLogger(f"mkdocs.hooks.{__name__}")


def config_table(recipe: str, name: str | None = None) -> str:
    if name is None:
        config = load(recipe).config
    else:
        config = getattr(importlib.import_module(f"rl_pg.app.{recipe}"), name)
    docs = field_docs(config)
    rows = ["| flag | default | meaning |", "|---|---|---|"]
    for field in dataclasses.fields(config):
        if field.default is not dataclasses.MISSING:
            default = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        else:
            default = "(required)"
        positional = "Positional" in str(field.type)
        flag = field.name.upper() if positional else "--" + field.name.replace("_", "-")
        text = docs.get(field.name, "").replace("|", "\\|").replace("<", "&lt;")
        rows.append(f"| `{flag}` | `{default!r}` | {text} |")
    return "\n".join(rows)


def shipped_agents() -> str:
    """The agents shipped with rl_pg, with the results their files carry (what
    ``rl-pg evaluate`` measured before ``rl-pg export`` wrote them)."""
    from rl_pg.app.sources import SHIPPED
    from rl_pg.checkpoint import load_checkpoint

    def result(record) -> str:
        if record is None:
            return "—"
        text = f"{record['mean_return']:.2f} ± {record['std_return']:.2f} ({record['episodes']})"
        if "mean_route_completion" in record:
            text += f", route completion {record['mean_route_completion']:.3f}"
        return text

    rows = [
        "| command | trained for | best checkpoint, greedy | sampled |",
        "|---|---:|---|---|",
    ]
    for path in sorted(SHIPPED.glob("*.pt")):
        agent = load_checkpoint(path)
        rows.append(
            f"| `rl-pg play {path.stem} --pretrained` | {agent['state']['frames']:,} frames | "
            f"{result(agent['agent'].get('greedy'))} | {result(agent['agent'].get('sampled'))} |"
        )
    return "\n".join(rows)


def mathml(latex: str) -> str:
    from latex2mathml.converter import convert

    return f'<div class="math">{convert(latex, display="block")}</div>'


def inline_maths(markdown: str) -> str:
    """``$...$`` in running text (not in code) as inline MathML. Each is wrapped in a
    ``<span>``: Markdown takes a line that starts with ``<math>`` for a block of HTML,
    which would cut the paragraph around it."""
    from latex2mathml.converter import convert

    parts = CODE.split(markdown)  # code at the odd indices, left as it is
    return "".join(
        part if i % 2 else INLINE_MATH.sub(lambda m: f"<span>{convert(m.group(1))}</span>", part)
        for i, part in enumerate(parts)
    )


def notebook_html(content: str, page_dir: str) -> str:
    """A rendered notebook's Markdown cells with their maths as MathML and their links to
    ``.md`` pages and other notebooks as links to the built pages (``page_dir``: the
    page's folder in the source, e.g. ``tutorials``)."""
    from latex2mathml.converter import convert

    def markdown_cells(part: str) -> str:
        part = HTML_DISPLAY_MATH.sub(lambda m: mathml(html.unescape(m.group(1))), part)
        return INLINE_MATH.sub(lambda m: convert(html.unescape(m.group(1))), part)

    def link(match: re.Match) -> str:
        target = posixpath.normpath(posixpath.join(page_dir, match.group(1)))
        target = "" if target == "index" else target.removesuffix("/index") + "/"
        # the notebook's page is served one folder deeper (tutorials/name/index.html)
        depth = page_dir.count("/") + 2 if page_dir else 1
        return f'href="{"../" * depth}{target}{match.group(2) or ""}"'

    parts = HTML_CODE.split(content)
    return "".join(
        part if i % 2 else MARKDOWN_LINK.sub(link, markdown_cells(part))
        for i, part in enumerate(parts)
    )


def notebook_faults(content: str) -> list[str]:
    """What an executed notebook's HTML shows that a learner should not see: each
    output to stderr, and no figure at all."""
    faults = [
        "printed to stderr:\n" + html.unescape(re.sub(r"<[^>]+>", "", text)).strip()
        for text in STDERR_OUTPUT.findall(content)
    ]
    if not FIGURE.search(content):
        faults.append("draws no figure")
    return faults


def on_config(config, **kwargs):
    """Before the build: the tutorials' kernels get an IPython directory of their own,
    whose kernel config keeps their log to errors (see the module's description)."""
    directory = Path(tempfile.mkdtemp(prefix="rl_pg-docs-ipython-"))
    atexit.register(shutil.rmtree, directory, ignore_errors=True)
    (directory / "profile_default").mkdir()
    (directory / "profile_default" / "ipython_kernel_config.py").write_text(
        'c.IPKernelApp.log_level = "ERROR"\n'
    )
    os.environ["IPYTHONDIR"] = str(directory)
    return config


def on_page_content(html_text: str, page, config, **kwargs) -> str:
    if page.file.src_uri.endswith(".py"):  # a tutorial, rendered by mkdocs-jupyter
        if config.plugins["mkdocs-jupyter"].config["execute"]:
            for fault in notebook_faults(html_text):
                log.warning(f"{page.file.src_uri} {fault}")
        return notebook_html(html_text, posixpath.dirname(page.file.src_uri))
    return html_text


def on_page_markdown(markdown: str, page=None, config=None, **kwargs) -> str:
    if page is not None:  # the stored tables and values as their files hold them
        folder = Path(config["docs_dir"]) / posixpath.dirname(page.file.src_uri)
        markdown = render(markdown, folder)
    markdown = inline_maths(DISPLAY_MATH.sub(lambda m: mathml(m.group(1)), markdown))
    markdown = AGENTS.sub(lambda m: shipped_agents(), markdown)
    return PATTERN.sub(lambda m: config_table(m.group(1), m.group(2)), markdown)
