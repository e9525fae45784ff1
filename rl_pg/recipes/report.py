"""Runs side by side: one table row per run, and their evaluation curves in one figure.

rl-pg report runs/lunarlander-seed*                    # a Markdown table
rl-pg report runs/lunarlander-seed* --plot seeds.png   # and the evaluation curves

Each row comes from the run directory alone: its summary (frames, training time, when it
first reached the recipe's threshold, its best evaluation) and the latest ``rl-pg
evaluate`` results of that best checkpoint, greedy and sampled, when there are any.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from rl_pg.recipes.evaluate import EVALUATIONS
from rl_pg.training.curves import plot_runs
from rl_pg.training.run_dir import SUMMARY

__all__ = ["Args", "format_report", "main", "read_report"]


@dataclass
class Args:
    """Tabulate runs side by side and plot their evaluation curves."""

    runs: tyro.conf.Positional[list[Path]]
    """Run directories written by a recipe (a shell glob works)."""
    plot: Path | None = None
    """Also draw every run's ``metric`` by frame into this PNG file."""
    metric: str = "eval/mean_return"
    """With plot: the logged scalar to draw (a CSV under RUN/logs/csv/scalars, without
    .csv), e.g. train/episode_return or eval/mean_route_completion."""
    ylim: tuple[float, float] | None = None
    """With plot: the vertical range (LOW HIGH), when a few early values squash the rest."""


def read_report(run_dir: Path) -> dict[str, Any]:
    """A run's summary, with its best checkpoint's latest greedy and sampled
    ``rl-pg evaluate`` results (``"greedy"``, ``"sampled"``; ``None`` when there are
    none of that checkpoint)."""
    path = Path(run_dir) / SUMMARY
    if not path.is_file():
        raise ValueError(
            f"{run_dir} has no {SUMMARY}: not a run directory, or its first run is still "
            "going (a run writes its summary when it ends or is interrupted)."
        )
    report = json.loads(path.read_text())
    report["greedy"] = report["sampled"] = None
    evaluations = Path(run_dir) / EVALUATIONS
    if evaluations.is_file():
        for line in evaluations.read_text().splitlines():
            record = json.loads(line)
            # best.pt moves on when a resumed run evaluates better: only results of the
            # checkpoint that is best now, on the recipe's test set (not `--on` another
            # one), describe it.
            if (
                record["checkpoint"] == "best"
                and record["frames"] == report["best_at_frames"]
                and "on" not in record
            ):
                report[record["mode"]] = record
    return report


def format_report(reports: list[dict[str, Any]], names: list[str]) -> str:
    """The runs as a Markdown table, and how many reached their threshold.

    Examples:
        >>> from rl_pg.recipes.report import format_report
        >>> table = format_report([{
        ...     "recipe": "cartpole", "seed": 0, "frames": 20224, "train_wall_s": 1.2,
        ...     "threshold": 475.0, "solved_at_frames": 20224, "best_eval_mean_return": 500.0,
        ...     "best_at_frames": 20224, "greedy": {"mean_return": 500.0, "std_return": 0.0,
        ...     "episodes": 100}, "sampled": None}], ["s0"])
        >>> print(table.splitlines()[0][:53])
        | run | recipe | seed | frames | training (s) | first
        >>> for line in table.splitlines()[2:]:
        ...     print(line)
        | s0 | cartpole | 0 | 20,224 | 1 | 20,224 | 500.00 at 20,224 | 500.00 ± 0.00 (100) | — |
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
            f"{r['train_wall_s']:.0f} | {solved} | {best} | {_result(r['greedy'])} | "
            f"{_result(r['sampled'])} |"
        )
    with_threshold = [r for r in reports if r.get("threshold") is not None]
    if with_threshold:
        solved = sum(r.get("solved_at_frames") is not None for r in with_threshold)
        lines.append(f"{solved}/{len(with_threshold)} runs reached their threshold.")
    return "\n".join(lines)


def _result(record: dict[str, Any] | None) -> str:
    if record is None:
        return "—"
    return f"{record['mean_return']:.2f} ± {record['std_return']:.2f} ({record['episodes']})"


def main(args: Args) -> str:
    """Prints (and returns) the table; draws the figure when ``args.plot`` is set."""
    if not args.runs:
        raise ValueError("name at least one run directory")
    reports = [read_report(run) for run in args.runs]
    names = _names(args.runs)
    table = format_report(reports, names)
    print(table)
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


def _names(runs: list[Path]) -> list[str]:
    """The shortest distinct names: the folders' own names, or whole paths if two share one."""
    names = [run.resolve().name for run in runs]
    return names if len(set(names)) == len(names) else [str(run) for run in runs]
