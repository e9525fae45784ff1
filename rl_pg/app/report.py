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

Each row comes from the run directory alone: its summary (frames, training time, when it
first reached the recipe's threshold, its best evaluation) and the latest ``rl-pg
evaluate`` results of that best checkpoint, greedy and sampled, when there are any.

Results are data: ``--store`` writes the rows with each run's config and evaluation
curve to a JSON file, which ``--stored`` reads back without the run directories: the
same table, the seeds' aggregate curves, their performance profiles, one row per
setting, every evaluation or every metric of the best and final checkpoints.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro

from rl_pg.app.figures import plot_profile, plot_stored
from rl_pg.app.outputs import claim_output
from rl_pg.app.settings import format_settings
from rl_pg.app.stores import is_store, read_report, read_stored, run_names, store_report
from rl_pg.app.tables import format_curves, format_evaluations, format_report
from rl_pg.training.curves import (
    is_png,
    plot_runs,
)
from rl_pg.training.metric import Metric

__all__ = ["Args", "main"]


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
    plot: Path | None = None
    """Also draw every run's ``metric`` into this PNG file. By frame; with --stored,
    each stored curve and their interquartile mean with a 95 % bootstrap band, one
    colour per file."""
    metric: str | None = None
    """With plot or store: the logged scalar to draw or keep. A CSV under
    RUN/logs/csv/scalars, without .csv, e.g. train/episode_return or
    eval/mean_route_completion; stored, a curve of more than 200 points is kept as the
    means of 200 windows. None: the evaluation entry the runs chose best.pt by
    (eval/mean_return unless their recipe selects by another)."""
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
    if bool(args.runs) == (args.stored is not None):
        raise ValueError("name run directories, or files with --stored (one of the two).")
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
    names = run_names(args.runs)
    table = format_report(reports, names)
    print(table)
    selected = {Metric.of_summary(r).logged for r in reports}
    # the runs' own metric, when they share one; what their thresholds are judged on
    judged = selected.pop() if len(selected) == 1 else "eval/mean_return"
    metric = args.metric or judged
    if args.store is not None:
        store_report(args.runs, args.store, metric=metric)
        print(f"stored: {args.store}")
    if args.plot is not None:
        thresholds = {r.get("threshold") for r in reports}
        shared = thresholds.pop() if len(thresholds) == 1 else None
        figure = plot_runs(
            dict(zip(names, args.runs, strict=True)),
            args.plot,
            metric=metric,
            title=", ".join(sorted({r["recipe"] for r in reports})),
            threshold=shared if metric == judged else None,
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
