"""The project's own pages, written from stored results: the tables, figures and numbers
of README.md, RESULTS.md and the docs come from JSON files through this module, so that
a page cannot drift from the results it shows.

    python docs/pages.py RESULTS.md docs/recipes/*.md   # write every marker again

A page marks what it shows with HTML comments, which Markdown renders as nothing:

- ``<!-- rl-pg report --stored FILE -->`` ... ``<!-- end of report -->``: the table
  ``rl-pg report --stored FILE`` prints (one row per run; ``--settings`` with several
  files: one row per file; ``--curves``: every evaluation; ``--evaluations``: every
  metric of the best and final checkpoints). FILE is relative to the page.
- ``<!-- rl-pg report --stored FILE... --plot FIGURE.png [--ylim LOW HIGH] -->`` and
  ``<!-- rl-pg report --stored FILE... --profile FIGURE.png -->``: a figure drawn from
  the files, as ``rl-pg report`` draws it.
- ``<!-- table FILE /JSON/POINTER FORMAT | KEY HEADER | VALUE HEADER... -->`` ...
  ``<!-- end of table -->``: one row per entry of the JSON object at that pointer
  (RFC 6901), one value column, or one per key when the entries are objects (a
  benchmark's results).
- ``<!-- value FILE /JSON/POINTER FORMAT -->0.75×<!-- /value -->``: a figure in a
  sentence, the value at that pointer through the Python format FORMAT (``{:.2f}×``);
  a ``*`` in the pointer gathers every entry there, which the format summarises
  (``{0.count}/{0.n}``, ``{0.min:.1f}–{0.max:.1f}``, ``{0.median}``: see ``Gathered``).

The docs build writes every marker of a page it renders (``docs/hooks.py``), and
``tests/test_cli.py`` fails on a page whose text or figure differs from its files.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.app.figures import plot_profile, plot_stored
from rl_pg.app.outputs import claim_output
from rl_pg.app.settings import format_settings
from rl_pg.app.stores import holds, read_stored
from rl_pg.app.tables import format_curves, format_evaluations, format_report
from rl_pg.checkpoint import write_atomically
from rl_pg.training.curves import (
    is_png,
)

STORED_FIGURE = re.compile(
    r"^<!-- rl-pg report --stored (?P<files>\S+(?: \S+)*?) --(?P<kind>plot|profile) "
    r"(?P<figure>\S+)(?: --ylim (?P<low>\S+) (?P<high>\S+))? -->$",
    re.MULTILINE,
)

STORED_TABLE = re.compile(
    r"^<!-- rl-pg report --stored (?P<files>[^-\s]\S*(?: [^-\s]\S*)*)"
    r"(?:(?P<settings> --settings)|(?P<curves> --curves)|(?P<evaluations> --evaluations))? "
    r"-->\n(?P<table>.*?)^<!-- end of report -->$",
    re.MULTILINE | re.DOTALL,
)

STORED_MAP = re.compile(
    r"^<!-- table (?P<file>\S+) (?P<pointer>/\S*) (?P<format>\S*\{[^}]*\}\S*) "
    r"(?P<headers>(?:\| [^|\n]+? )+)-->\n(?P<table>.*?)^<!-- end of table -->$",
    re.MULTILINE | re.DOTALL,
)

STORED_VALUE = re.compile(
    r"<!-- value (?P<file>\S+) (?P<pointer>/.*?) (?P<format>\S*\{[^}]*\}\S*) -->"
    r"(?P<value>[^<]*)<!-- /value -->"
)


def figure_ylim(match: re.Match) -> tuple[float, float] | None:
    """The ``--ylim`` of a stored figure's line (None without one)."""
    return None if match["low"] is None else (float(match["low"]), float(match["high"]))


def draw_stored(match: re.Match, folder: Path, figure: Path | None = None) -> Path:
    """Draws the figure a page's line ``match`` (``STORED_FIGURE``) names, its files
    relative to ``folder`` (the page's), into ``figure`` (default: the one it names)."""
    files = [Path(folder) / name for name in match["files"].split()]
    figure = Path(folder) / match["figure"] if figure is None else figure
    if match["kind"] == "profile":
        return plot_profile(files, figure)
    return plot_stored(files, figure, ylim=figure_ylim(match))


def refresh(page: Path) -> bool:
    """Rewrites every stored table of the Markdown file ``page`` from its file and draws
    its stored figures again; True if the page or a figure changed."""
    page = Path(page)
    text = page.read_text()
    refreshed = render(text, page.parent)
    changed = refreshed != text
    if changed:
        write_atomically(page, refreshed)
    for match in STORED_FIGURE.finditer(refreshed):
        figure = page.parent / match["figure"]
        claim_output(figure, flag=f"the figure marker of {page}", writes="a figure (PNG)",
                     ours=is_png, suffix=".png")  # fmt: skip
        before = figure.read_bytes() if figure.is_file() else None
        draw_stored(match, page.parent)
        changed |= figure.read_bytes() != before
    return changed


def stored_table(match: re.Match, folder: Path) -> str:
    """The table a page's ``STORED_TABLE`` match ``match`` shows, its files relative to
    ``folder`` (the page's): one row per run, or with ``--settings`` one per file."""
    files = [Path(folder) / name for name in match["files"].split()]
    if match["settings"]:
        return format_settings(files)
    if len(files) != 1:
        raise ValueError(f"a table of runs reads one stored file, got {match['files']!r}.")
    if match["curves"]:
        return format_curves(files[0])
    if match["evaluations"]:
        return format_evaluations(files[0])
    return format_report(*read_stored(files[0]))


def stored_value(match: re.Match, folder: Path) -> str:
    """The figure a page's ``STORED_VALUE`` match ``match`` shows: its file's value at
    its JSON pointer (the file relative to ``folder``, the page's), formatted.

    Examples:
        >>> import json, tempfile
        >>> from pathlib import Path
        >>> from pages import STORED_VALUE, stored_value
        >>> folder = Path(tempfile.mkdtemp())
        >>> _ = (folder / "b.json").write_text(json.dumps({"ratios": {"a/b": 0.7526}}))
        >>> line = "runs at <!-- value b.json /ratios/a~1b {:.2f}× -->?<!-- /value --> the speed"
        >>> stored_value(STORED_VALUE.search(line), folder)
        '0.75×'
    """
    value, path = _stored_json(match, folder)
    return _formatted(match["format"], value, path, match["pointer"])


def stored_map(match: re.Match, folder: Path) -> str:
    r"""The table a page's ``STORED_MAP`` match ``match`` shows: one row per entry of the
    JSON object at its pointer (the file relative to ``folder``, the page's), its key,
    then its value; when the values are objects themselves, one column per key of the
    first (``| ROW HEADER | COLUMN HEADER... |``, as many as it has keys). Fractional
    numbers go through the marker's format, whole ones get thousands separators,
    anything else is written as it is.

    Examples:
        >>> import json, tempfile
        >>> from pathlib import Path
        >>> from pages import STORED_MAP, stored_map
        >>> folder = Path(tempfile.mkdtemp())
        >>> data = {"rates": {"a": 1234.5, "b": 99}, "runs": {"x": {"s": 1.5, "ok": "2/3"}}}
        >>> _ = (folder / "b.json").write_text(json.dumps(data))
        >>> page = "<!-- table b.json /rates {:,.0f} | loop | frames/s -->\n<!-- end of table -->"
        >>> print(stored_map(STORED_MAP.search(page), folder))
        | loop | frames/s |
        |---|---:|
        | a | 1,234 |
        | b | 99 |
        >>> page = "<!-- table b.json /runs {:.2f} | run | seconds | solved -->\n<!-- end of table"
        >>> page += " -->"
        >>> print(stored_map(STORED_MAP.search(page), folder))
        | run | seconds | solved |
        |---|---:|---:|
        | x | 1.50 | 2/3 |
    """
    value, path = _stored_json(match, folder)
    headers = [h.strip() for h in match["headers"].strip().strip("|").split("|")]
    where = f"{path}, {match['pointer']}"
    if not isinstance(value, dict) or not value:
        raise ValueError(
            f"{where} holds {type(value).__name__}, not an object of rows: point the table "
            f"at an object (name -> value, or name -> {{column -> value}})."
        )
    first = next(iter(value.values()))
    columns = list(first) if isinstance(first, dict) else None
    if len(headers) != 1 + (len(columns) if columns else 1):
        wanted = f"its columns {columns}" if columns else "its values"
        raise ValueError(
            f"The table of {where} has {len(headers)} headers; it needs one for the rows "
            f"and one for each of {wanted}."
        )
    rows = ["| " + " | ".join(headers) + " |", "|---|" + "---:|" * (len(headers) - 1)]
    for key, item in value.items():
        cells = [item.get(c) for c in columns] if columns else [item]
        text = [_cell(match["format"], cell, path, match["pointer"]) for cell in cells]
        rows.append(f"| {key} | " + " | ".join(text) + " |")
    return "\n".join(rows)


def _cell(form: str, value: Any, path: Path, pointer: str) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    if isinstance(value, int):  # counts: whole, with thousands separators
        return f"{value:,}"
    return _formatted(form, value, path, pointer)


def _stored_json(match: re.Match, folder: Path) -> tuple[Any, Path]:
    """The value at a marker's JSON pointer in its file, and the file. A ``*`` segment
    stands for every entry there: the values it gathers come as a ``Gathered``."""
    path = Path(folder) / match["file"]
    if not path.is_file():
        raise ValueError(f"{path} does not exist (named by {match.group(0).splitlines()[0]!r}).")
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: not a JSON file ({err}).") from err
    parts = [p.replace("~1", "/").replace("~0", "~") for p in match["pointer"].split("/")[1:]]
    values = _walk(value, parts, path, match["pointer"])
    return (Gathered(values) if "*" in parts else values[0]), path


def _walk(
    value: Any, parts: list[str], path: Path, pointer: str, *, gathering: bool = False
) -> list[Any]:
    """The values ``parts`` (a JSON pointer's segments, ``*`` for every entry) reach.
    Below a ``*``, an entry that is null where the pointer goes on gathers as None
    (a run without that record, e.g. no final-checkpoint evaluation when the best
    checkpoint is the final one); a key that is absent is an error, as without ``*``."""
    if not parts:
        return [value]
    key, rest = parts[0], parts[1:]
    if key == "*" and isinstance(value, (list, dict)):
        entries = value if isinstance(value, list) else list(value.values())
        return [
            found
            for entry in entries
            for found in _walk(entry, rest, path, pointer, gathering=True)
        ]
    if value is None and gathering:
        return [None]
    try:
        value = value[int(key)] if isinstance(value, list) else value[key]
    except (KeyError, IndexError, ValueError, TypeError) as err:
        raise ValueError(f"{path} has nothing at {pointer} (no {key!r}).") from err
    return _walk(value, rest, path, pointer, gathering=gathering)


class Gathered:
    """The values a marker's ``*`` pointer gathers, for its format to summarise:
    ``{0.n}`` of them, ``{0.count}`` set (not null, not false), ``{0.missing}`` not set
    (runs that never reached their threshold, say), and of the numbers among
    them ``{0.min}``, ``{0.max}`` and ``{0.median}``, each with a format spec
    (``{0.min:.1f}–{0.max:.1f}``). Of runs' reports (``/runs/*/report``), ``{0.held}``:
    how many best checkpoints score at least their threshold both greedily and by
    sampling (see ``holds``; None, which no format writes, unless every run has both
    evaluations and a threshold).

    Examples:
        >>> from pages import Gathered
        >>> "{0.count}/{0.n} solved, {0.min:,}–{0.max:,} frames".format(Gathered([900, None, 300]))
        '2/3 solved, 300–900 frames'
        >>> Gathered([900, None, 300]).missing
        1
    """

    def __init__(self, values: list[Any]) -> None:
        self.n = len(values)
        self.count = sum(v is not None and v is not False for v in values)
        self.missing = self.n - self.count
        numbers = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
        self.min = min(numbers) if numbers else None
        self.max = max(numbers) if numbers else None
        self.median = float(np.median(numbers)) if numbers else None
        held = [holds(v) if isinstance(v, dict) else None for v in values]
        self.held = None if None in held else sum(held)

    def __format__(self, spec: str) -> str:
        raise ValueError(
            "a * pointer gathers several values: format one of their summaries, "
            "{0.n}, {0.count}, {0.missing}, {0.min}, {0.max}, {0.median} or {0.held}"
        )


def _formatted(form: str, value: Any, path: Path, pointer: str) -> str:
    try:
        return form.format(value)
    except (ValueError, TypeError, IndexError, KeyError) as err:
        raise ValueError(
            f"The format {form!r} cannot write {value!r} ({path}, {pointer}): {err}."
        ) from err


def main(argv: list[str] | None = None) -> str:
    """Writes again every marker of the pages ``argv`` names; prints and returns what
    changed. A marker that cannot be written exits with its reason, on one line."""
    pages = [Path(page) for page in (sys.argv[1:] if argv is None else argv)]
    if not pages or any(page.name in ("-h", "--help") for page in pages):
        sys.exit("usage: python docs/pages.py PAGE.md...  (writes every marker again)")
    for page in pages:
        if not page.is_file():
            sys.exit(
                f"pages: {page}: no such file; name pages (Markdown) whose stored tables, "
                f"values and figures to write again from their files."
            )
    try:
        changed = [str(page) for page in pages if refresh(page)]
    except ValueError as err:
        sys.exit(f"pages: {err}")
    message = f"refreshed: {', '.join(changed)}" if changed else "every stored table is current"
    print(message)
    return message


def render(markdown: str, folder: Path) -> str:
    """``markdown`` (a page in ``folder``) with its tables and values written from their
    files, in memory (the figures are files of their own: ``refresh`` draws them)."""
    text = STORED_TABLE.sub(
        lambda m: (
            f"{m.group(0).splitlines()[0]}\n{stored_table(m, folder)}\n<!-- end of report -->"
        ),
        markdown,
    )
    text = STORED_MAP.sub(
        lambda m: f"{m.group(0).splitlines()[0]}\n{stored_map(m, folder)}\n<!-- end of table -->",
        text,
    )
    return STORED_VALUE.sub(
        lambda m: m.group(0).replace(
            f"-->{m['value']}<!-- /value", f"-->{stored_value(m, folder)}<!-- /value"
        ),
        text,
    )


if __name__ == "__main__":
    main()
