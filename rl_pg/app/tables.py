"""Markdown tables of runs: one row per run (``rl-pg report``), every evaluation of a
stored file's runs (``--curves``), every metric of their best and final checkpoints
(``--evaluations``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.app.stores import MODES, holds, stored_runs
from rl_pg.training.aggregates import seed_aggregate
from rl_pg.training.metric import Metric

__all__ = ["RECORD_ABOUT", "format_curves", "format_evaluations", "format_report"]

# What an evaluation record says about itself, not about the driving: not a column.
RECORD_ABOUT = frozenset({"checkpoint", "frames", "mode", "episodes", "seed", "seconds", "on",
                          "weights", "mean_return", "std_return", "mean_length"})  # fmt: skip


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
        >>> from rl_pg.app.tables import format_curves
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
    runs = stored_runs(path)
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
        >>> from rl_pg.app.tables import format_evaluations
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
    for run in stored_runs(path):
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
        >>> from rl_pg.app.tables import format_report
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
        metric = Metric.of_summary(r)
        lines.append(
            f"| {name} | {r['recipe']} | {r['seed']} | {r['frames']:,}"
            + (" (interrupted)" if r.get("interrupted") else "")
            + " | "
            f"{_seconds(r['train_wall_s'])} | {solved} | {_best(r, metric)} | "
            f"{_result(r['greedy'], metric)} | {_result(r['sampled'], metric)} |"
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


def _seconds(seconds: float) -> str:
    """A training time: tenths of a second below 10 s (a CartPole run takes one or two)."""
    return f"{seconds:.1f}" if seconds < 10 else f"{seconds:.0f}"


def _best(report: dict[str, Any], metric: Metric) -> str:
    """The evaluation best.pt was kept at: its mean return, or the metric the run
    selected by, named."""
    if metric.key == "mean_return":
        value = report.get("best_eval_mean_return")
        return "—" if value is None else f"{value:.2f} at {report['best_at_frames']:,}"
    value = report.get("best_eval_value")
    if value is None:
        return "—"
    return f"{metric.key} {metric.text(value)} at {report['best_at_frames']:,}"


def _result(record: dict[str, Any] | None, metric: Metric | None = None) -> str:
    if record is None:
        return "—"
    text = f"{record['mean_return']:.2f} ± {record['std_return']:.2f} ({record['episodes']})"
    if record.get("crashed_rate") is not None:  # part of the driving recipes' targets
        text += f", {record['crashed_rate']:.0%} crashed"
    if metric is not None and metric.key != "mean_return" and metric.key in record:
        text += f", {metric.key} {metric.text(record[metric.key])}"  # what best.pt was kept by
    return text
