"""docs/pages.py: the pages' tables, values and figures are what their stored files hold.

How each marker is written is tested with the stored report it shows
(tests/test_cli.py, ``test_report_stores_its_table_and_refreshes_pages_from_the_file``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pages import (
    STORED_FIGURE,
    STORED_MAP,
    STORED_TABLE,
    STORED_VALUE,
    draw_stored,
    refresh,
    render,
    stored_map,
    stored_table,
    stored_value,
)

REPO = Path(__file__).resolve().parents[1]


def test_every_stored_table_and_figure_in_the_repository_is_current(tmp_path):
    from matplotlib.testing.compare import compare_images

    pages = [
        REPO / "README.md",
        REPO / "RESULTS.md",
        REPO / "benchmarks" / "README.md",
        *sorted((REPO / "docs").rglob("*.md")),
    ]
    found, checked = 0, set()
    for page in pages:
        for match in STORED_TABLE.finditer(page.read_text()):
            found += 1
            expected = stored_table(match, page.parent)
            assert match["table"].strip() == expected, (
                f"{page.name}: the table of {match['files']} is not what the file holds; "
                f"run python docs/pages.py {page.relative_to(REPO)}"
            )
        for match in STORED_MAP.finditer(page.read_text()):
            found += 1
            assert match["table"].strip() == stored_map(match, page.parent), (
                f"{page.name}: the table of {match['file']}'s {match['pointer']} is not what "
                f"the file holds; run python docs/pages.py {page.relative_to(REPO)}"
            )
        for match in STORED_VALUE.finditer(page.read_text()):
            found += 1
            assert match["value"] == stored_value(match, page.parent), (
                f"{page.name}: {match['value']!r} is not {match['file']}'s "
                f"{match['pointer']}; run python docs/pages.py {page.relative_to(REPO)}"
            )
        for match in STORED_FIGURE.finditer(page.read_text()):
            found += 1
            # a figure that several pages show, from the same files, is drawn once
            inputs = [(page.parent / name).resolve() for name in match["files"].split()]
            figure = (page.parent / match["figure"]).resolve()
            same = (figure, *inputs, match["kind"], match["low"], match["high"])
            if same in checked:
                continue
            checked.add(same)
            drawn = draw_stored(match, page.parent, tmp_path / f"{found}.png")
            # a tolerance for another matplotlib's anti-aliasing, not for other data
            difference = compare_images(str(page.parent / match["figure"]), str(drawn), tol=2)
            assert difference is None, (
                f"{page.name}: {match['figure']} is not drawn from {match['files']} "
                f"({difference}); run python docs/pages.py {page.relative_to(REPO)}"
            )
    assert found >= 3


def test_a_stored_figure_never_replaces_a_file_that_is_not_a_figure(tmp_path):
    (tmp_path / "store.json").write_text(json.dumps({"runs": []}))
    (tmp_path / "setup.cfg").write_text("[tool]\n")
    page = tmp_path / "page.md"
    page.write_text("<!-- rl-pg report --stored store.json --plot setup.cfg -->\n")
    with pytest.raises(ValueError, match=r"setup\.cfg exists and is a file this command did not"):
        refresh(page)
    assert (tmp_path / "setup.cfg").read_text() == "[tool]\n"


def test_the_docs_build_writes_a_stale_page_from_its_files_and_leaves_the_file(tmp_path):
    (tmp_path / "b.json").write_text(json.dumps({"speed": {"a": 1234.5}, "ratio": 0.7526}))
    text = (
        "Runs at <!-- value b.json /ratio {:.2f}× -->9×<!-- /value --> the speed.\n\n"
        "<!-- table b.json /speed {:,.0f} | loop | frames/s -->\n| stale |\n<!-- end of table -->\n"
    )
    page = tmp_path / "page.md"
    page.write_text(text)
    rendered = render(text, tmp_path)
    assert "-->0.75×<!-- /value -->" in rendered and "| a | 1,234 |" in rendered
    assert "stale" not in rendered and page.read_text() == text
    assert refresh(page) and page.read_text() == rendered and not refresh(page)


def test_a_page_that_is_not_there_is_named(tmp_path, capsys):
    from pages import main

    with pytest.raises(SystemExit, match=r"pages: .*nothing\.md: no such file"):
        main([str(tmp_path / "nothing.md")])
    assert not (tmp_path / "nothing.md").exists()
