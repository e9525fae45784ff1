"""Runs side by side: one table row per run, and their evaluation curves in one figure.

rl-pg report runs/lunarlander-seed*                    # a Markdown table
rl-pg report runs/lunarlander-seed* --plot seeds.png   # and the evaluation curves
rl-pg report runs/lunarlander-seed* --store seeds.json # and keep what the table shows
rl-pg report --stored seeds.json                       # the same table, from that file
rl-pg report --stored seeds.json --plot iqm.png        # and the seeds' aggregate curve
rl-pg report --stored a.json b.json --plot iqm.png     # one aggregate curve per setting
rl-pg report --stored a.json b.json --profile p.png    # settings' performance profiles
rl-pg report --stored a.json b.json --settings         # one row per setting
rl-pg report --stored seeds.json --curves              # the evaluations, run by run
rl-pg report --stored seeds.json --evaluations         # every metric of rl-pg evaluate's
rl-pg report --refresh RESULTS.md                      # every stored table in a page

Each row comes from the run directory alone: its summary (frames, training time, when it
first reached the recipe's threshold, its best evaluation) and the latest ``rl-pg
evaluate`` results of that best checkpoint, greedy and sampled, when there are any.

Results are data: ``--store`` writes the rows with each run's config and evaluation
curve to a JSON file, and a Markdown page shows a stored table between the lines
``<!-- rl-pg report --stored FILE -->`` and ``<!-- end of report -->`` (FILE relative to
the page), which ``--refresh`` rewrites from the file, so the page cannot drift from it.
A line ``<!-- rl-pg report --stored FILE... --plot FIGURE.png [--ylim LOW HIGH] -->``
names a figure drawn from the files (one colour per file), and ``<!-- rl-pg report
--stored FILE... --profile FIGURE.png -->`` a performance profile drawn from several;
``--refresh`` draws both again.
``<!-- rl-pg report --stored FILE... --settings -->`` opens a table of one row per file,
``<!-- rl-pg report --stored FILE --curves -->`` one of every stored evaluation during
training, ``<!-- rl-pg report --stored FILE --evaluations -->`` one of every metric of
the best and final checkpoints' ``rl-pg evaluate`` results.
A table of a JSON object's entries, one row each (a benchmark's results), is written
between ``<!-- table FILE /JSON/POINTER FORMAT | KEY HEADER | VALUE HEADER... -->`` and
``<!-- end of table -->`` (one value header per column when the entries are objects).
A figure in a sentence is written ``<!-- value FILE /JSON/POINTER FORMAT -->0.75×<!--
/value -->``: the value at that JSON pointer (RFC 6901) of FILE, through the Python
format FORMAT (e.g. ``{:.2f}×``), which ``--refresh`` writes again; a ``*`` in the
pointer gathers every entry there, which the format summarises (``{0.count}/{0.n}``,
``{0.min:.1f}–{0.max:.1f}``, ``{0.median}``: see ``Gathered``).
"""

from __future__ import annotations

import dataclasses
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tyro

from rl_pg.app.evaluate import EVALUATIONS
from rl_pg.checkpoint import write_atomically
from rl_pg.training.curves import (
    is_png,
    plot_profiles,
    plot_runs,
    plot_seeds,
    plot_settings,
    plot_solved,
    plot_solved_settings,
    read_curve,
    seed_aggregate,
)
from rl_pg.training.records import (
    EVALUATION_RECORD,
    RUN_SUMMARY,
    check_values,
    optional,
    read_json,
)
from rl_pg.training.run_dir import CONFIG, SUMMARY, claim_output
from rl_pg.training.seeds import fresh_seed

__all__ = [
    "Args",
    "draw_stored",
    "format_curves",
    "format_evaluations",
    "format_report",
    "format_settings",
    "holds",
    "main",
    "plot_profile",
    "plot_stored",
    "read_report",
    "read_stored",
    "refresh",
    "smoothed",
    "store_report",
    "stored_map",
    "stored_table",
    "stored_value",
]

STORED_POINTS = 200  # a stored curve's most points: longer ones are stored smoothed
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
# What a setting's flags leave out: where a run went, which seed, how it was watched.
NOT_SETTINGS = frozenset({"seed", "n_seeds", "run_dir", "resume", "progress", "threads", "device"})
MODES = ("greedy", "sampled")
# What an evaluation record says about itself, not about the driving: not a column.
RECORD_ABOUT = frozenset({"checkpoint", "frames", "mode", "episodes", "seed", "seconds", "on",
                          "weights", "mean_return", "std_return", "mean_length"})  # fmt: skip


@dataclass
class Args:
    """Tabulate runs side by side and plot their evaluation curves."""

    runs: tyro.conf.Positional[list[Path]] = field(default_factory=list)
    """Run directories written by a recipe (a shell glob works)."""
    store: Path | None = None
    """Also store the table in this JSON file (read by --stored). Its rows, with every
    run's config and evaluation curve."""
    stored: list[Path] | None = None
    """Print the tables of files written by --store. One table per file, instead of
    reading run directories."""
    refresh: list[Path] | None = None
    """Rewrite the stored tables of these Markdown files. Each from its file (see
    --stored)."""
    plot: Path | None = None
    """Also draw every run's ``metric`` into this PNG file. By frame; with --stored,
    each stored curve and their interquartile mean with a 95 % bootstrap band, one
    colour per file."""
    metric: str = "eval/mean_return"
    """With plot or store: the logged scalar to draw or keep. A CSV under
    RUN/logs/csv/scalars, without .csv, e.g. train/episode_return or
    eval/mean_route_completion; stored, a curve of more than 200 points is kept as the
    means of 200 windows."""
    ylim: tuple[float, float] | None = None
    """With plot: the vertical range, LOW HIGH. For when a few early values squash the
    rest."""
    settings: bool = False
    """With --stored: one row per file, the setting its runs share. The flags that differ
    from the recipe's defaults, how many runs reached the threshold and when (median),
    how many best checkpoints hold it greedily and by sampling, and their median scores."""
    curves: bool = False
    """With --stored: the evaluation curve as a table. One row per evaluation (its
    frames), one column per run; the evaluation kept as the run's best in bold."""
    evaluations: bool = False
    """With --stored: every metric of the best and final checkpoints' evaluations. One row
    per run, checkpoint and way of acting (greedy, sampled), one column per metric the
    recipe's evaluation reports (MetaDrive's route completion, success and crash rates)."""
    profile: Path | None = None
    """With --stored: draw the files' performance profiles into this PNG. One curve per
    file: the share of its runs whose best checkpoint scores above τ both ways (the
    lower of its greedy and sampled results), with a 95 % bootstrap band."""
    replace: bool = False
    """Let --store, --plot and --profile overwrite a file rl-pg report did not write.
    Never a run's own files; a store or a PNG written before is replaced without it."""


def read_report(run_dir: Path) -> dict[str, Any]:
    """A run's summary, with its best checkpoint's latest greedy and sampled
    ``rl-pg evaluate`` results (``"greedy"``, ``"sampled"``; ``None`` when there are
    none of that checkpoint), those on its default fresh episodes first, the final
    checkpoint's (``"last"``) and the training's frames per second."""
    path = Path(run_dir) / SUMMARY
    if not path.is_file():
        raise ValueError(
            f"{run_dir} has no {SUMMARY}: not a run directory, or its first run is still "
            "going (a run writes its summary when it ends or is interrupted)."
        )
    try:
        report = check_values(json.loads(path.read_text()), RUN_SUMMARY, str(path))
    except ValueError as err:  # not JSON, or a field missing or wrong
        why = str(err).removeprefix(f"{path}: ")
        raise ValueError(
            f"{path} is not a run summary ({why}); rl-pg resume {run_dir} writes it again "
            f"when the run ends or is stopped."
        ) from None
    report["greedy"] = report["sampled"] = None
    report["last"] = {"greedy": None, "sampled": None}
    # the training's speed over all its sessions (train_wall_s leaves evaluations out)
    seconds = report["train_wall_s"]
    report["frames_per_s"] = report["frames"] / seconds if seconds else None
    evaluations = Path(run_dir) / EVALUATIONS
    if evaluations.is_file():
        # best.pt moves on when a resumed run evaluates better: only results of the
        # checkpoint that is best now, on the recipe's test set (not `--on` another one),
        # describe it; of those, the latest on rl-pg evaluate's own episodes (a result on
        # episodes chosen with --seed is only taken where there is none). The same for
        # the last checkpoint, at the frames the run ended on.
        fresh = fresh_seed(report["seed"])
        for number, line in enumerate(evaluations.read_text().splitlines(), start=1):
            where = f"{evaluations}, line {number}"
            try:
                record = check_values(json.loads(line), EVALUATION_RECORD, where)
            except ValueError as err:
                if line.strip():  # a write killed half-way, or an edit: say so, skip it
                    why = str(err).removeprefix(f"{where}: ")
                    print(
                        f"rl-pg report: {where}, is not an evaluation record ({why}); skipped.",
                        file=sys.stderr,
                    )
                continue
            if "on" in record:
                continue
            if record["checkpoint"] == "best" and record["frames"] == report["best_at_frames"]:
                results = report
            elif record["checkpoint"] == "last" and record["frames"] == report["frames"]:
                results = report["last"]
            else:
                continue
            kept = results[record["mode"]]
            if kept is None or record["seed"] == fresh or kept["seed"] != fresh:
                results[record["mode"]] = record
    return report


def is_store(path: str | Path) -> bool:
    """Whether ``path`` is a table store ``--store`` wrote (JSON with its ``"runs"``)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(data, dict) and isinstance(data.get("runs"), list)


def store_report(runs: list[Path], path: Path, *, metric: str = "eval/mean_return") -> None:
    """Writes the runs' rows (as ``read_report`` reads them), names, configs and
    ``metric`` curves to the JSON file ``path`` (atomically). A curve of more than
    ``STORED_POINTS`` points (a training metric, logged every few updates) is stored
    smoothed: see ``smoothed``."""
    names = _names(runs)
    stored = []
    for name, run in zip(names, runs, strict=True):
        frames, values, window = smoothed(*read_curve(run, metric))
        fix = "it is written as the run starts: restore it from a copy"
        config = read_json(Path(run) / CONFIG, what="a run's config", schema={}, fix=fix)
        curve = {"metric": metric, "window": window, "frames": frames.tolist(),
                 "values": values.tolist()}  # fmt: skip
        stored.append({"name": name, "report": read_report(run), "config": config, "curve": curve})
    write_atomically(Path(path), json.dumps({"runs": stored}, indent=1) + "\n")


def smoothed(
    frames: np.ndarray, values: np.ndarray, points: int | None = None
) -> tuple[np.ndarray, np.ndarray, int]:
    """A curve of at most ``points`` points (default ``STORED_POINTS``): the means of
    consecutive windows of ``window`` logged values, each at its window's last frame
    (a last, shorter window keeps the curve's end), and ``window`` (1: as logged).

    Examples:
        >>> import numpy as np
        >>> from rl_pg.app.report import smoothed
        >>> smoothed(np.arange(1.0, 6.0), np.array([0.0, 1.0, 0.0, 1.0, 1.0]), points=2)
        (array([3., 5.]), array([0.33333333, 1.        ]), 3)
    """
    points = STORED_POINTS if points is None else points
    window = max(1, -(-len(values) // points))  # the smallest that fits
    if window == 1:
        return frames, values, 1
    starts = np.arange(0, len(values), window)
    means = np.add.reduceat(values, starts) / np.diff(np.append(starts, len(values)))
    ends = np.minimum(starts + window, len(values)) - 1
    return frames[ends], means, window


def read_stored(path: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """The rows and names ``store_report`` wrote to ``path``.

    Raises:
        ValueError: ``path`` is missing, or is not a file ``--store`` wrote (the
            message names the file).
    """
    runs = _stored_runs(path)
    return [run["report"] for run in runs], [run["name"] for run in runs]


def _stored_runs(path: Path) -> list[dict[str, Any]]:
    """The runs a file written by ``--store`` holds (each with its name, report, config
    and curve), every value checked, or a ValueError naming the file and the field."""
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError as err:
        raise ValueError(
            f"{path} does not exist: write it with rl-pg report RUN... --store."
        ) from err
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(
            f"{path} is not a stored report ({type(err).__name__}: {err}); write it with "
            f"rl-pg report RUN... --store {path}."
        ) from err
    try:
        if not isinstance(data, dict) or not isinstance(data.get("runs"), list):
            raise ValueError(f'{path}: should hold {{"runs": [...]}}.')
        for number, run in enumerate(data["runs"]):
            where = f"{path}, run {number}"
            check_values(run, STORED_RUN, where)
            check_values(run["report"], optional(RUN_SUMMARY), f"{where}, report")
            for mode in ("greedy", "sampled"):
                if run["report"].get(mode) is not None:
                    check_values(
                        run["report"][mode], optional(EVALUATION_RECORD), f"{where}, {mode}"
                    )
            curve = check_values(run["curve"], STORED_CURVE, f"{where}, curve")
            if "frames" in curve and len(curve["frames"]) != len(curve["values"]):
                raise ValueError(
                    f"{where}, curve: {len(curve['frames'])} frames for "
                    f"{len(curve['values'])} values."
                )
    except ValueError as err:
        raise ValueError(
            f"{err} It is not a stored report as rl-pg report writes one: write it again "
            f"with rl-pg report RUN... --store {path}."
        ) from None
    return data["runs"]


# What each reading of a store needs is there; whatever is there holds its kind.
STORED_RUN = {"name": "text", "report": "object", "config?": "object", "curve": "object"}
STORED_CURVE = {"metric?": "text", "frames?": "list of numbers", "values": "list of numbers",
                "window?": "count"}  # fmt: skip


def plot_stored(
    paths: Path | list[Path], figure: Path, *, ylim: tuple[float, float] | None = None
) -> Path:
    """Draws the seeds of stored reports into ``figure``: each run's curve, and their
    interquartile mean with a 95 % bootstrap band (see
    [`plot_seeds`][rl_pg.training.curves.plot_seeds]); for runs that stopped when
    solved (their curves end where each passed), the share of them solved by each
    frame (see [`plot_solved`][rl_pg.training.curves.plot_solved]). Several files are
    several settings on one figure, one colour each, named by the file's stem.

    Raises:
        ValueError: a file that is not a stored report, or two files of one stem (the
            figure could not tell them apart).
    """
    paths = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    stems = [path.stem for path in paths]
    if len(set(stems)) != len(stems):
        raise ValueError(f"--plot names each file's runs by its stem; these repeat one: {paths}.")
    settings = {}
    for stem, runs in zip(_setting_names(stems), map(_stored_runs, paths), strict=True):
        groups = _by_setting(runs)  # runs of one file that differ in more than the seed
        if len(groups) == 1:
            settings[stem] = runs
        else:
            settings.update({f"{stem}: {label}": group for label, group in groups.items()})
    for name, group in settings.items():
        if len(group) < 2:
            raise ValueError(
                f"--plot draws the seeds of each setting with their spread, and the setting "
                f"{name!r} has {len(group)} run: store two or more seeds of it (a file "
                f"whose runs differ in more than the seed holds one setting per difference)."
            )
    stems = list(settings)
    paths = stems  # one figure per setting from here
    runs = [run for group in settings.values() for run in group]
    title = ", ".join(sorted({run["report"]["recipe"] for run in runs}))
    if all(run["config"].get("stop_when_solved") for run in runs):
        reached = {
            stem: {run["name"]: run["report"].get("solved_at_frames") for run in group}
            for stem, group in settings.items()
        }  # fmt: skip
        budget = max(run["report"]["frames"] for run in runs)  # where the last one stopped
        if len(paths) == 1:
            return plot_solved(reached[stems[0]], Path(figure), budget=budget, title=title)
        return plot_solved_settings(reached, Path(figure), budget=budget, title=title)
    metrics = {run["curve"]["metric"] for run in runs}
    thresholds = {run["report"].get("threshold") for run in runs}
    metric = metrics.pop() if len(metrics) == 1 else "the stored metric"
    windows = {run["curve"].get("window", 1) for run in runs}
    if windows != {1}:  # stored smoothed: say over how many logged values
        title += f" (curves: means of {'/'.join(map(str, sorted(windows)))} logged values)"
    shared = thresholds.pop() if len(thresholds) == 1 else None
    curves = {
        stem: {
            run["name"]: (np.array(run["curve"]["frames"]), np.array(run["curve"]["values"]))
            for run in group
        }
        for stem, group in settings.items()
    }
    draw = dict(
        ylabel=metric, title=title, ylim=ylim,
        threshold=shared if metric == "eval/mean_return" else None,
    )  # fmt: skip
    if len(paths) == 1:
        return plot_seeds(curves[stems[0]], Path(figure), **draw)
    return plot_settings(curves, Path(figure), **draw)


def _by_setting(runs: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """A stored file's runs by setting: seeds of one setting are one group; runs whose
    configs differ in more than the seed (a file written from mixed runs) are not
    seeds of each other, and each setting is named by the flags that set it apart."""
    recipes = [run["report"]["recipe"] for run in runs]
    if len(set(recipes)) > 1:
        return {
            name: [r for r, of in zip(runs, recipes, strict=True) if of == name] for name in recipes
        }
    if len({tuple(_setting([run])) for run in runs}) == 1:
        return {"": runs}
    from rl_pg.app.flags import flag

    configs = [config for config, _ in _as_run(runs)]
    quiet = _quiet_fields()
    varying = [
        name
        for name in configs[0]
        if name not in quiet and len({json.dumps(c.get(name)) for c in configs}) > 1
    ]
    groups: dict[str, list[dict[str, Any]]] = {}
    for run, config in zip(runs, configs, strict=True):
        label = " ".join(flag(name, config.get(name)) for name in varying)
        groups.setdefault(label, []).append(run)
    return groups


def _setting_names(stems: list[str]) -> list[str]:
    """Files' stems without the words all of them start with (``gridworld-no-baseline``,
    ``gridworld-reward-to-go`` -> ``no-baseline``, ``reward-to-go``).

    Examples:
        >>> from rl_pg.app.report import _setting_names
        >>> _setting_names(["bandit-ema", "bandit-no-baseline"]), _setting_names(["seeds"])
        (['ema', 'no-baseline'], ['seeds'])
    """
    words = [stem.split("-") for stem in stems]
    shared = 0
    while len(stems) > 1 and all(
        len(w) > shared + 1 and w[shared] == words[0][shared] for w in words
    ):
        shared += 1
    return ["-".join(w[shared:]) for w in words]


def plot_profile(paths: list[Path], figure: Path) -> Path:
    """Draws the performance profile of each stored file's runs into ``figure``: a run's
    score is its best checkpoint's lower mean return of the greedy and the sampled
    evaluations (what it holds both ways). Each file is one setting, named by its stem.

    Raises:
        ValueError: a file that is not a stored report, or a run in it without both
            evaluations (the message names the file and the run).
    """
    scores, thresholds, recipes = {}, set(), set()
    for path in paths:
        reports, names = read_stored(path)
        for report, name in zip(reports, names, strict=True):
            if report["greedy"] is None or report["sampled"] is None:
                raise ValueError(
                    f"{path}: run {name} has no greedy and sampled evaluation of its best "
                    f"checkpoint (rl-pg evaluate RUN --episodes 100, and with --sample), so "
                    f"it has no score to profile; evaluate it, then --store again."
                )
        scores[Path(path).stem] = np.array(
            [min(r["greedy"]["mean_return"], r["sampled"]["mean_return"]) for r in reports]
        )
        thresholds |= {r.get("threshold") for r in reports}
        recipes |= {r["recipe"] for r in reports}
    return plot_profiles(
        scores,
        Path(figure),
        xlabel="τ: the best checkpoint's mean return, the lower of greedy and sampled",
        title=", ".join(sorted(recipes)),
        threshold=thresholds.pop() if len(thresholds) == 1 else None,
    )


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

    def table(match: re.Match) -> str:
        opening = match.group(0).splitlines()[0]
        return f"{opening}\n{stored_table(match, page.parent)}\n<!-- end of report -->"

    refreshed = STORED_TABLE.sub(table, text)
    refreshed = STORED_MAP.sub(
        lambda m: (
            f"{m.group(0).splitlines()[0]}\n{stored_map(m, page.parent)}\n<!-- end of table -->"
        ),
        refreshed,
    )
    refreshed = STORED_VALUE.sub(
        lambda m: m.group(0).replace(
            f"-->{m['value']}<!-- /value", f"-->{stored_value(m, page.parent)}<!-- /value"
        ),
        refreshed,
    )
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
        >>> from rl_pg.app.report import STORED_VALUE, stored_value
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
        >>> from rl_pg.app.report import STORED_MAP, stored_map
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
        >>> from rl_pg.app.report import Gathered
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


def format_settings(paths: list[Path]) -> str:
    """One Markdown row per stored file: the setting its runs share, how many reached
    the threshold and when, and how their best checkpoints score both ways.

    A run that never reached the threshold counts as later than any that did (so the
    median is "—" when half of them never did). "held" counts the best checkpoints whose
    greedy and sampled means both reach the threshold.
    """
    head = (
        "| setting | seeds | reached | median frames to threshold | held both ways "
        "| greedy, median | sampled, median |"
    )
    lines = [head, "|---|---:|---:|---:|---:|---:|---:|"]
    stored = [_stored_runs(path) for path in paths]
    settings = [_setting(runs) for runs in stored]
    recipes = [runs[0]["report"]["recipe"] for runs in stored]
    mixed = len(set(recipes)) > 1  # settings of several recipes: say which is which
    # flags every row shares (a budget, say) are said once, under the table
    shared = set.intersection(*map(set, settings)) if len(settings) > 1 else set()
    for runs, setting, recipe in zip(stored, settings, recipes, strict=True):
        reports = [run["report"] for run in runs]
        reached = [r.get("solved_at_frames") for r in reports]
        median = float(np.median([np.inf if at is None else at for at in reached]))
        scores = {
            mode: [r[mode]["mean_return"] for r in reports if r.get(mode) is not None]
            for mode in MODES
        }
        evaluated = all(len(values) == len(reports) for values in scores.values())
        threshold = reports[0].get("threshold")
        held = (
            f"{sum(min(g, s) >= threshold for g, s in zip(*scores.values(), strict=True))}"
            f"/{len(reports)}"
            if evaluated and threshold is not None
            else "—"
        )
        # a row of the shared flags alone is not the defaults: say where its flags are
        label = " ".join(f"`{f}`" for f in setting if f not in shared) or (
            "only the flags below" if setting else "defaults"
        )
        lines.append(
            f"| {recipe + ': ' if mixed else ''}{label} | "
            f"{_seeds([r['seed'] for r in reports])} | "
            f"{sum(at is not None for at in reached)}/{len(reports)} | "
            + ("—" if not np.isfinite(median) else f"{median:,.0f}")
            + f" | {held} | "
            + " | ".join(
                f"{np.median(values):.1f}" if values and evaluated else "—"
                for values in scores.values()
            )
            + " |"
        )
    if shared:
        common = " ".join(f"`{flag}`" for flag in settings[0] if flag in shared)
        lines += ["", f"Every row: {common}."]
    return "\n".join(lines)


def _seeds(seeds: list[int]) -> str:
    """Seeds as a short list: runs of three or more consecutive ones as a range.

    Examples:
        >>> from rl_pg.app.report import _seeds
        >>> _seeds([0, 1, 2, 3, 4, 5, 6, 7, 8, 9]), _seeds([0, 1, 2, 4, 5, 8, 9]), _seeds([4])
        ('0–9', '0–2 4 5 8 9', '4')
    """
    parts, run = [], []
    for seed in sorted(set(seeds)):
        if run and seed != run[-1] + 1:
            parts.append(run)
            run = []
        run.append(seed)
    parts.append(run)
    return " ".join(f"{r[0]}–{r[-1]}" if len(r) >= 3 else " ".join(map(str, r)) for r in parts if r)


def _setting(runs: list[dict[str, Any]]) -> list[str]:
    """The flags every run shares that differ from its recipe's defaults, as rl-pg
    train would take them; a flag the runs disagree on is listed with all its values.
    A field that does nothing in a run (``TrainConfig.inert``: ``--target-kl`` without
    ``--lr-control kl``) counts as the default there; a field whose default None is
    resolved by the run's other fields (LunarLander's ``scale_lr_factor``, the
    gridworld's ``threshold``) is compared with what it resolves to for that run."""
    from rl_pg.app.flags import flag
    from rl_pg.recipes import load
    from rl_pg.training import TrainConfig

    recipes = {run["report"]["recipe"] for run in runs}
    if len(recipes) != 1:
        raise ValueError(f"a setting's runs come from one recipe, got {sorted(recipes)}.")
    recipe = load(recipes.pop())
    defaults = _defaults(recipe)
    quiet = _quiet_fields()
    configs = [config for config, _ in _as_run(runs)]
    resolved = [
        field.name
        for field in dataclasses.fields(recipe.config)
        if field.default is None and defaults.get(field.name) is not None
    ]
    flags = []
    for name in defaults:
        if name in quiet:
            continue
        values, own = [], []  # each run's value, and whether it is its default
        for config in configs:
            default = _resolved(recipe, config, name) if name in resolved else defaults[name]
            inert = TrainConfig.inert(name, config)
            values.append(default if inert else config[name])
            own.append(inert or config[name] == default)
        if not all(own):
            distinct = [v for i, v in enumerate(values) if v not in values[:i]]
            shown = [flag(name, v) for v in distinct]
            flags.append(shown[0] if len(shown) == 1 else " / ".join(shown))
    return flags


def _defaults(recipe) -> dict[str, Any]:
    config = recipe.config() if recipe.prepare is None else recipe.prepare(recipe.config())
    return json.loads(json.dumps(vars(config), default=str))


def _quiet_fields() -> set[str]:
    """Fields that say nothing about a setting: the seed, where and how it logged."""
    from rl_pg.training import TrainConfig

    return NOT_SETTINGS | set(TrainConfig.groups["logging"][1])


def _as_run(runs: list[dict[str, Any]]) -> list[tuple[dict[str, Any], Any]]:
    """Each stored run's config as it ran (a field newer than the run at the value it
    had then, the rest at the recipe's defaults), with its recipe."""
    from rl_pg.recipes import load

    out = []
    for run in runs:
        recipe = load(run["report"]["recipe"])
        out.append(({**_defaults(recipe), **recipe.config.as_run(run["config"])}, recipe))
    return out


def _resolved(recipe, config: dict[str, Any], name: str) -> Any:
    """What field ``name``'s default None resolves to in a run of ``config`` (its
    other fields as they are, by the config or the recipe's ``prepare``), as
    ``config_dict`` writes it."""
    own = recipe.config.from_stored(config, **{name: None})
    own = own if recipe.prepare is None else recipe.prepare(own)
    return json.loads(json.dumps(getattr(own, name), default=str))


def figure_ylim(match: re.Match) -> tuple[float, float] | None:
    """The ``--ylim`` of a stored figure's line (None without one)."""
    return None if match["low"] is None else (float(match["low"]), float(match["high"]))


def format_curves(path: Path) -> str:
    """The evaluation curves a file written by ``--store`` holds, as a Markdown table:
    one row per evaluation, one column per run; each run's best evaluation (the
    checkpoint it kept) in bold, "—" where a run has no such evaluation (it stopped
    earlier). Row k holds every run's k-th evaluation: runs whose batches are whole
    episodes evaluate at the first update past each interval, so at frames that differ
    a little from run to run, which the frames column then gives as a range.

    Raises:
        ValueError: ``path`` is not a stored report, or holds no evaluation (the
            message names it).

    Examples:
        >>> import json, tempfile
        >>> from pathlib import Path
        >>> from rl_pg.app.report import format_curves
        >>> run = lambda name, frames, values, best: {"name": name, "report": {
        ...     "best_at_frames": best}, "curve": {"metric": "eval/mean_return",
        ...     "frames": frames, "values": values}}
        >>> path = Path(tempfile.mkdtemp()) / "seeds.json"
        >>> _ = path.write_text(json.dumps({"runs": [run("seed0", [100, 200], [-21.0, 3.5], 200),
        ...                                          run("seed1", [104], [-20.0], 104)]}))
        >>> print(format_curves(path))
        | frames | seed0 | seed1 |
        |---:|---:|---:|
        | 100–104 | -21 | **-20** |
        | 200 | **3.5** | — |
        <BLANKLINE>
        eval/mean_return at each evaluation; bold: the best, whose checkpoint each run kept.
    """
    runs = _stored_runs(path)
    for run in runs:
        if len(run["curve"]["frames"]) != len(run["curve"]["values"]):
            raise ValueError(
                f"{path}: run {run['name']}'s curve has {len(run['curve']['frames'])} frames "
                f"and {len(run['curve']['values'])} values; write the file again with rl-pg "
                f"report RUN... --store."
            )
    rows = max(len(run["curve"]["frames"]) for run in runs)
    if not rows:
        raise ValueError(
            f"{path} holds no evaluation: its runs were stored before their first one. "
            f"Store them again once they have evaluated (rl-pg report RUN... --store)."
        )
    lines = [
        "| frames | " + " | ".join(run["name"] for run in runs) + " |",
        "|---:|" + "---:|" * len(runs),
    ]
    for k in range(rows):
        at = [int(run["curve"]["frames"][k]) for run in runs if k < len(run["curve"]["frames"])]
        frames = f"{min(at):,}" if min(at) == max(at) else f"{min(at):,}–{max(at):,}"
        cells = []
        for run in runs:
            if k >= len(run["curve"]["values"]):
                cells.append("—")
                continue
            text = f"{run['curve']['values'][k]:.4g}"
            best = run["curve"]["frames"][k] == run["report"].get("best_at_frames")
            cells.append(f"**{text}**" if best else text)
        lines.append(f"| {frames} | " + " | ".join(cells) + " |")  # CSV frames: floats
    metrics = sorted({run["curve"]["metric"] for run in runs})
    lines += [
        "",
        f"{', '.join(metrics)} at each evaluation; bold: the best, whose checkpoint each run kept.",
    ]
    return "\n".join(lines)


def format_evaluations(path: Path) -> str:
    """The ``rl-pg evaluate`` results a file written by ``--store`` holds, as a Markdown
    table: one row per run, checkpoint (its best; its final one, unless that is the
    best) and way of acting, with the episodes, the return (mean ± standard deviation),
    the length and one column per further metric the evaluations report (rates as
    percentages; the recipe's own values, such as MetaDrive's route completion, to three
    significant digits; "—" where a row's evaluation did not report it).

    Raises:
        ValueError: ``path`` is not a stored report, or holds no evaluation of a best or
            final checkpoint (the message names it and says how to make them).

    Examples:
        >>> import json, tempfile
        >>> from pathlib import Path
        >>> from rl_pg.app.report import format_evaluations
        >>> greedy = {"mode": "greedy", "episodes": 100, "mean_return": 288.9,
        ...           "std_return": 120.0, "mean_length": 370.0, "mean_route_completion": 0.7543,
        ...           "crash_rate": 0.14}
        >>> report = {"frames": 2000, "best_at_frames": 1500, "greedy": greedy, "sampled": None,
        ...           "last": {"greedy": {**greedy, "crash_rate": 0.2}, "sampled": None}}
        >>> path = Path(tempfile.mkdtemp()) / "seeds.json"
        >>> _ = path.write_text(json.dumps({"runs": [{"name": "seed0", "report": report,
        ...                                           "curve": {"values": []}}]}))
        >>> print(format_evaluations(path))
        | run | checkpoint | actions | episodes | return | length | route completion | crash rate |
        |---|---|---|---:|---:|---:|---:|---:|
        | seed0 | best (1,500) | greedy | 100 | 288.9 ± 120.0 | 370 | 0.754 | 14% |
        | seed0 | final (2,000) | greedy | 100 | 288.9 ± 120.0 | 370 | 0.754 | 20% |
    """
    rows = []
    for run in _stored_runs(path):
        report = run["report"]
        best, final = report.get("best_at_frames"), report["frames"]
        last = report.get("last") or {}  # files stored before final checkpoints were
        if best is None:  # never evaluated during training: no results of a best one
            label = "best"
        else:
            label = f"best ({best:,})" if best != final else f"best and final ({final:,})"
        checkpoints = [(label, report)]
        if best != final:  # else the best row holds the final checkpoint's results
            checkpoints.append((f"final ({final:,})", last))
        for label, records in checkpoints:
            rows += [
                (run["name"], label, mode, records[mode]) for mode in MODES if records.get(mode)
            ]
    if not rows:
        raise ValueError(
            f"{path} holds no evaluation of a best or final checkpoint: evaluate the runs "
            f"(rl-pg evaluate RUN, with --sample, with --checkpoint last), then store them "
            f"again (rl-pg report RUN... --store {path})."
        )
    metrics = []  # in the order the evaluations report them
    for *_, record in rows:
        metrics += [
            key
            for key, value in record.items()
            if key not in RECORD_ABOUT and key not in metrics
            and isinstance(value, (int, float)) and not isinstance(value, bool)
        ]  # fmt: skip
    headers = ["run", "checkpoint", "actions", "episodes", "return", "length"]
    headers += [key.removeprefix("mean_").replace("_", " ") for key in metrics]
    lines = ["| " + " | ".join(headers) + " |", "|---|---|---|" + "---:|" * (len(headers) - 3)]
    for name, label, mode, record in rows:
        cells = [name, label, mode, str(record["episodes"])]
        cells += [f"{record['mean_return']:.1f} ± {record['std_return']:.1f}"]
        cells += [f"{record['mean_length']:.0f}"]
        cells += [
            "—" if key not in record else
            f"{record[key]:.0%}" if key.endswith("_rate") else
            f"{record[key]:.3f}" if abs(record[key]) < 10 else f"{record[key]:.1f}"
            for key in metrics
        ]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def format_report(reports: list[dict[str, Any]], names: list[str]) -> str:
    """The runs as a Markdown table, and how many reached their threshold.

    Examples:
        >>> from rl_pg.app.report import format_report
        >>> table = format_report([{
        ...     "recipe": "cartpole", "seed": 0, "frames": 20224, "train_wall_s": 1.2,
        ...     "threshold": 475.0, "solved_at_frames": 20224, "best_eval_mean_return": 500.0,
        ...     "best_at_frames": 20224, "greedy": {"mean_return": 500.0, "std_return": 0.0,
        ...     "episodes": 100}, "sampled": None}], ["s0"])
        >>> print(table.splitlines()[0][:53])
        | run | recipe | seed | frames | training (s) | first
        >>> for line in table.splitlines()[2:]:
        ...     print(line)
        | s0 | cartpole | 0 | 20,224 | 1.2 | 20,224 | 500.00 at 20,224 | 500.00 ± 0.00 (100) | — |
        <BLANKLINE>
        1/1 runs reached their threshold.
    """
    head = (
        "| run | recipe | seed | frames | training (s) | first ≥ threshold | best evaluation "
        "| best checkpoint, greedy | sampled |"
    )
    lines = [head, "|---|---|---:|---:|---:|---:|---|---|---|"]
    for name, r in zip(names, reports, strict=True):
        solved = "—" if r.get("solved_at_frames") is None else f"{r['solved_at_frames']:,}"
        best = (
            "—"
            if r.get("best_eval_mean_return") is None
            else f"{r['best_eval_mean_return']:.2f} at {r['best_at_frames']:,}"
        )
        lines.append(
            f"| {name} | {r['recipe']} | {r['seed']} | {r['frames']:,}"
            + (" (interrupted)" if r.get("interrupted") else "")
            + " | "
            f"{_seconds(r['train_wall_s'])} | {solved} | {best} | {_result(r['greedy'])} | "
            f"{_result(r['sampled'])} |"
        )
    with_threshold = [r for r in reports if r.get("threshold") is not None]
    if with_threshold:
        lines.append("")  # the counts are not rows of the table
        solved = sum(r.get("solved_at_frames") is not None for r in with_threshold)
        lines.append(f"{solved}/{len(with_threshold)} runs reached their threshold.")
        if all(holds(r) is not None for r in with_threshold):
            held = sum(holds(r) for r in with_threshold)
            lines.append(
                f"{held}/{len(with_threshold)} best checkpoints score at least their "
                "threshold both greedily and by sampling."
            )
    aggregate = _aggregate(reports)
    if aggregate:
        if not with_threshold:
            lines.append("")  # not a row of the table
        lines.append(aggregate)
    return "\n".join(lines)


def _aggregate(reports: list[dict[str, Any]]) -> str | None:
    """The best checkpoints' interquartile mean over the runs, greedy and sampled, with
    its 95 % percentile-bootstrap interval (Agarwal et al. 2021's aggregate); None for
    fewer than two runs evaluated that way."""
    parts = []
    for mode in ("greedy", "sampled"):
        scores = [r[mode]["mean_return"] for r in reports if r.get(mode)]
        if len(scores) >= 2:
            iqm, low, high = seed_aggregate(np.asarray(scores)[:, None])
            parts.append(f"{mode} {iqm[0]:.2f} [{low[0]:.2f}, {high[0]:.2f}]")
    if not parts:
        return None
    runs = max(sum(bool(r.get(mode)) for r in reports) for mode in ("greedy", "sampled"))
    return (
        f"Best checkpoints, interquartile mean of {runs} runs [95 % bootstrap interval]: "
        + ", ".join(parts)
        + "."
    )


def holds(report: dict[str, Any]) -> bool | None:
    """Whether a run's best checkpoint scores at least its threshold both greedily and by
    sampling (its lower mean return of the two); None without a threshold or without
    both evaluations."""
    if report.get("threshold") is None or not report.get("greedy") or not report.get("sampled"):
        return None
    lower = min(report["greedy"]["mean_return"], report["sampled"]["mean_return"])
    return lower >= report["threshold"]


def _seconds(seconds: float) -> str:
    """A training time: tenths of a second below 10 s (a CartPole run takes one or two)."""
    return f"{seconds:.1f}" if seconds < 10 else f"{seconds:.0f}"


def _result(record: dict[str, Any] | None) -> str:
    if record is None:
        return "—"
    text = f"{record['mean_return']:.2f} ± {record['std_return']:.2f} ({record['episodes']})"
    if record.get("crashed_rate") is not None:  # part of the driving recipes' targets
        text += f", {record['crashed_rate']:.0%} crashed"
    return text


def main(args: Args) -> str:
    """Prints (and returns) the table; draws the figure when ``args.plot`` is set."""
    if args.settings and args.stored is None:
        raise ValueError("--settings compares stored files: name them with --stored.")
    if args.curves and args.stored is None:
        raise ValueError(
            "--curves tabulates stored curves: name the file with --stored (write it with "
            "rl-pg report RUN... --store FILE)."
        )
    if args.evaluations and args.stored is None:
        raise ValueError(
            "--evaluations tabulates stored evaluations: name the file with --stored (write "
            "it with rl-pg report RUN... --store FILE)."
        )
    if sum((args.curves, args.settings, args.evaluations)) > 1:
        raise ValueError("--curves, --settings and --evaluations are three tables: ask for one.")
    if args.profile is not None and args.stored is None:
        raise ValueError("--profile draws stored files: name them with --stored.")
    outputs = (
        ("--store", args.store, "a table store (JSON)", is_store, ".json"),
        ("--plot", args.plot, "a figure (PNG)", is_png, ".png"),
        ("--profile", args.profile, "a figure (PNG)", is_png, ".png"),
    )
    for flag, path, writes, ours, suffix in outputs:  # before any work: refused, it costs nothing
        if path is not None:
            claim_output(path, flag=flag, writes=writes, ours=ours, suffix=suffix,
                         replace=args.replace)  # fmt: skip
    sources = sum((bool(args.runs), args.stored is not None, args.refresh is not None))
    if sources != 1:
        raise ValueError(
            "name run directories, or files with --stored, or pages with --refresh "
            "(one of the three)."
        )
    if args.refresh is not None:
        for page in args.refresh:
            if not page.is_file():
                raise ValueError(
                    f"--refresh {page}: no such file; it takes pages (Markdown) whose "
                    f"stored tables, values and figures it writes again from their files."
                )
        changed = [str(page) for page in args.refresh if refresh(page)]
        message = f"refreshed: {', '.join(changed)}" if changed else "every stored table is current"
        print(message)
        return message
    if args.stored is not None:
        if args.store is not None:
            raise ValueError("--store reads run directories: leave it out with --stored.")
        if args.settings:
            table = format_settings(args.stored)
            print(table)
            return table
        tables = []
        for path in args.stored:
            if args.curves:
                table = format_curves(path)
            elif args.evaluations:
                table = format_evaluations(path)
            else:
                table = format_report(*read_stored(path))
            tables.append(table if len(args.stored) == 1 else f"{path}:\n\n{table}")
        table = "\n\n".join(tables)
        print(table)
        if args.plot is not None:
            print(f"curves: {plot_stored(args.stored, args.plot, ylim=args.ylim)}")
        if args.profile is not None:
            print(f"performance profiles: {plot_profile(args.stored, args.profile)}")
        return table
    args.runs = _distinct(args.runs)
    reports = [read_report(run) for run in args.runs]
    names = _names(args.runs)
    table = format_report(reports, names)
    print(table)
    if args.store is not None:
        store_report(args.runs, args.store, metric=args.metric)
        print(f"stored: {args.store}")
    if args.plot is not None:
        thresholds = {r.get("threshold") for r in reports}
        shared = thresholds.pop() if len(thresholds) == 1 else None
        figure = plot_runs(
            dict(zip(names, args.runs, strict=True)),
            args.plot,
            metric=args.metric,
            title=", ".join(sorted({r["recipe"] for r in reports})),
            threshold=shared if args.metric == "eval/mean_return" else None,
            ylim=args.ylim,
        )
        print(f"curves: {figure}")
    return table


def _distinct(runs: list[Path]) -> list[Path]:
    """Each run once: ``runs/*`` also matches ``runs/latest``, which names the newest run
    (the command reads it as that run; earlier versions made it a link), and would count
    it twice (a link to a run not named is kept, as is its name)."""
    kept, seen = [], {}
    for run in runs:
        real = Path(run).resolve()
        if real in seen:
            if Path(run).is_symlink():
                continue
            kept[seen[real]] = run  # the folder's own name over the link's
            continue
        seen[real] = len(kept)
        kept.append(run)
    return kept


def _names(runs: list[Path]) -> list[str]:
    """The shortest distinct names: the folders' own names, or whole paths if two share one."""
    names = [run.resolve().name for run in runs]
    return names if len(set(names)) == len(names) else [str(run) for run in runs]
