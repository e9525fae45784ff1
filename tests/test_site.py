"""The documentation site in a real browser: every page of a fresh build loads in
headless Chromium with no console error, no failed request and no broken image, every
link inside the site reaches a page (and its anchor), no maths is left as LaTeX, no
inline formula or value marker stands outside its paragraph, no list item is folded
into the paragraph above it, no page marker shows as text, and every table or code
block wider than the text column scrolls with a drawn scrollbar.

Chromium is Debian's package (``apt-get install chromium``), driven by playwright through
``executable_path``. Without it the test is skipped, except under CI, where .ci/run
installs it and a missing browser is a failure. ``RL_PG_SCREENSHOTS=DIR`` keeps
screenshots of the main pages there. ``RL_PG_SITE_DIR=DIR`` tests the site built there
instead of building one (CI builds the site, its tutorials executed, before the tests).
"""

from __future__ import annotations

import functools
import http.server
import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from urllib.parse import unquote, urljoin, urlparse

import pytest

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = os.environ.get("RL_PG_CHROMIUM") or shutil.which("chromium")
MAIN_PAGES = {  # screenshot name: page
    "home": "",
    "theory": "theory/",
    "tutorial": "tutorials/reward_to_go/",
    "metadrive": "recipes/metadrive/",
}
# Text that is LaTeX the build did not render: $$ blocks, or $...$ inside a line.
RAW_MATHS = re.compile(r"\$\$|(?<![\w$])\$(?=\S)[^$\n]*\\[a-zA-Z]+[^$\n]*(?<=\S)\$(?![\w$])")

# The project's page markers (tables, values, figures generated from stored results).
RAW_MARKER = re.compile(r"<!--\s*(?:/?value|rl-pg report|end of (?:report|table))[^>]{0,40}")
# Tables and code wider than the text column must sit in a box that scrolls sideways with
# a scrollbar (docs/stylesheets/extra.css draws it plainly), not cut off by overflow:hidden.
HIDDEN_OVERFLOW = r"""(() => {
  const article = document.querySelector('article'); if (!article) return [];
  const problems = [];
  article.querySelectorAll('table, pre, pre > code').forEach(element => {
    const wide = element.scrollWidth > article.clientWidth + 1;
    if (!wide && element.scrollWidth <= element.clientWidth + 1) return;
    let box = element, scrolls = false;
    while (box && box !== article.parentElement) {
      const style = getComputedStyle(box);
      if (['auto', 'scroll'].includes(style.overflowX) && box.scrollWidth > box.clientWidth) {
        // (headless Chromium draws no scrollbar to measure: the CSS does) Material's
        // own bar is a faint thin line until hovered; the site's CSS must draw one
        // whose thumb and track show (an 'auto' colour leaves Material's).
        const alpha = c => { const v = c.match(/[\d.]+/g).map(Number); return v[3] ?? 1; };
        const [thumb, track] = style.scrollbarColor.match(/rgba?\([^)]*\)/g) || [];
        scrolls = style.scrollbarWidth === 'auto' && thumb !== undefined
          && track !== undefined && alpha(thumb) >= 0.5 && alpha(track) > 0;
        break;
      }
      if (style.overflowX === 'hidden' || style.overflowX === 'clip') break;
      box = box.parentElement;
    }
    const what = element.textContent.trim().slice(0, 50);
    if (!scrolls) problems.push(`a ${element.tagName.toLowerCase()} ${element.scrollWidth}px `
      + `wide, its column ${article.clientWidth}px, is cut off or scrolls unseen: ${what}`);
  });
  return problems;
})()"""

STRAY_TAGS = r"""(() => {
  const article = document.querySelector('article'); if (!article) return [];
  return Array.from(article.querySelectorAll('s, strike, del, u, ins, blink, font'))
    .map(e => `<${e.tagName.toLowerCase()}> around "${e.textContent.trim().slice(0, 40)}"`);
})()"""

# Where Markdown read the source other than it was written: a value marker that starts
# a line became a block of its own between two halves of its sentence, and a list item
# right after an item's second paragraph folded into it as text ("... budget. - Conclusion:").
TORN_PROSE = r"""(() => {
  const article = document.querySelector('article'); if (!article) return [];
  const problems = [];
  const prose = 'p, li, td, th, h1, h2, h3, h4, h5, h6, dd, dt, figcaption';
  const walker = document.createTreeWalker(article, NodeFilter.SHOW_COMMENT);
  for (let node = walker.nextNode(); node; node = walker.nextNode()) {
    const text = node.textContent.trim();
    if (/^value\b/.test(text) && !node.parentElement.closest(prose))
      problems.push(`a value marker between blocks splits its sentence: ${text.slice(0, 50)}`);
  }
  article.querySelectorAll('p').forEach(p => {
    const item = p.textContent.split('\n').slice(1).find(l => /^\s*([-*+]|\d+\.)\s+\S/.test(l));
    if (item !== undefined)
      problems.push(`a list item folded into the paragraph above it: ${item.trim().slice(0, 50)}`);
  });
  return problems;
})()"""

if CHROMIUM is None and os.environ.get("CI"):
    pytest.fail("CI runs the browser test: install Debian's chromium (.ci/run does).")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="no Chromium (apt-get install chromium) for the browser test"
)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site built in ``RL_PG_SITE_DIR``, or a fresh build (notebooks without their
    outputs: the full build runs them, see tests/test_tutorials.py), served on a free
    port of 127.0.0.1."""
    if os.environ.get("RL_PG_SITE_DIR"):
        root = Path(os.environ["RL_PG_SITE_DIR"])
        assert (root / "index.html").is_file(), (
            f"RL_PG_SITE_DIR={root} holds no built site: mkdocs build --site-dir {root}"
        )
    else:
        root = tmp_path_factory.mktemp("site")
        env = {**os.environ, "RL_PG_DOCS_EXECUTE": "false", "NO_MKDOCS_2_WARNING": "1"}
        built = subprocess.run(
            [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(root)],
            cwd=REPO, env=env, capture_output=True, text=True,
        )  # fmt: skip
        assert built.returncode == 0, built.stderr[-3000:]
    handler = functools.partial(_QuietHandler, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield root, f"http://127.0.0.1:{server.server_address[1]}/"
    server.shutdown()
    server.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # the test reports what failed itself
        pass


def _pages(root: Path) -> list[str]:
    """Every page of the build, as a path relative to the site ("" for the home page)."""
    pages = []
    for index in sorted(root.rglob("index.html")):
        relative = index.parent.relative_to(root).as_posix()
        pages.append("" if relative == "." else relative + "/")
    return pages


def _target_file(root: Path, url: str) -> Path:
    path = root / unquote(urlparse(url).path).lstrip("/")
    return path / "index.html" if path.is_dir() or not path.suffix else path


def test_every_page_loads_cleanly_in_chromium(site, tmp_path):
    from playwright.sync_api import sync_playwright

    root, base = site
    pages = _pages(root)
    assert len(pages) >= 30 and "tutorials/reward_to_go/" in pages
    shots = Path(os.environ.get("RL_PG_SCREENSHOTS") or tmp_path / "screenshots")
    shots.mkdir(parents=True, exist_ok=True)
    problems: list[str] = []
    links: dict[str, set[str]] = {}
    # Every page's search worker fetches and indexes the whole site's text (1 MB), a third
    # of this test's time: the first page does, the others get an index with no documents.
    search_index = json.loads((root / "search" / "search_index.json").read_text())
    empty = json.dumps({**search_index, "docs": []})

    def empty_search_index(route) -> None:
        route.fulfill(body=empty, content_type="application/json")

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        current = {"name": ""}

        def report(what: str) -> None:
            problems.append(f"{current['name']}: {what}")

        page.on("console", lambda m: m.type == "error" and report(f"console error: {m.text}"))
        page.on("pageerror", lambda error: report(f"script error: {error}"))
        # (ERR_ABORTED: a request the next navigation cancelled, e.g. the favicon's)
        page.on("requestfailed", lambda r: "ERR_ABORTED" not in (r.failure or "")
                and report(f"request failed: {r.url} ({r.failure})"))  # fmt: skip
        page.on("response", lambda r: r.status >= 400 and report(f"HTTP {r.status}: {r.url}"))
        for number, name in enumerate(pages):
            current["name"] = name or "home"
            if number == 1:  # the first page's search built the whole index, error-free
                page.route("**/search/search_index.json", empty_search_index)
            page.goto(urljoin(base, name), wait_until="load")
            broken = page.evaluate(
                "Array.from(document.images)"
                ".filter(i => !i.complete || i.naturalWidth === 0).map(i => i.src)"
            )
            problems += [f"{name}: broken image {src}" for src in broken]
            text = page.evaluate(
                "(() => { const body = document.querySelector('article') || document.body;"
                " const copy = body.cloneNode(true);"
                " copy.querySelectorAll('pre, code, script, style, math, .clipboard-copy-txt')"
                ".forEach(e => e.remove()); return copy.innerText; })()"
            )
            problems += [f"{name}: maths left as LaTeX: {m.group(0)[:60]!r}"
                         for m in RAW_MATHS.finditer(text)]  # fmt: skip
            torn = page.evaluate(  # inline maths that Markdown cut out of its paragraph
                "Array.from(document.querySelectorAll('article math[display=\"inline\"]'))"
                ".filter(m => !m.closest('p, li, td, th, span, h1, h2, h3, h4, a, em, strong'))"
                ".length"
            )
            if torn:
                problems.append(f"{name}: {torn} inline formulas stand outside any paragraph")
            raw = RAW_MARKER.findall(text)  # a page marker Markdown showed as text
            problems += [f"{name}: a page marker shows as text: {m!r}" for m in raw]
            problems += [f"{name}: {what}" for what in page.evaluate(HIDDEN_OVERFLOW)]
            # prose that HTML read as a tag (a docstring's `seed<S>` opened an <s>: the
            # rest of the page struck through): elements no page's source writes
            stray = page.evaluate(STRAY_TAGS)
            problems += [f"{name}: prose read as an HTML tag: {what}" for what in stray]
            problems += [f"{name}: {what}" for what in page.evaluate(TORN_PROSE)]
            hrefs = page.evaluate(
                "Array.from(document.querySelectorAll('article a[href]')).map(a => a.href)"
            )
            links[name] = {href for href in hrefs if href.startswith(base)}
            for shot, path in MAIN_PAGES.items():
                if path == name:
                    page.screenshot(path=str(shots / f"{shot}.png"), full_page=False)
        browser.close()
    for name, hrefs in links.items():
        for href in hrefs:
            target = _target_file(root, href)
            if not target.is_file():
                problems.append(f"{name}: link to a missing page {href}")
                continue
            anchor = urlparse(href).fragment
            if (
                anchor
                and target.suffix == ".html"
                and f'id="{unquote(anchor)}"' not in (target.read_text(errors="replace"))
            ):
                problems.append(f"{name}: link to a missing anchor {href}")
    assert not problems, "\n".join(sorted(set(problems)))
    assert {p.stem for p in shots.glob("*.png")} >= set(MAIN_PAGES)
