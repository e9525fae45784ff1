"""The variance lesson on a real task: train a recipe's seeds while measuring the policy
gradient's noise for every return estimator, then draw and tabulate it.

``rl-pg lab variance RECIPE`` runs [`variance_lab`][rl_pg.app.lab.variance_lab]:
each seed trains with ``grad_stats`` set (the same batches, the same parameters, every
estimator), in ``ROOT/seed<S>`` (a stopped seed resumes, a finished one is kept), and
[`summarise`][rl_pg.app.lab.summarise] reads their logs into
``ROOT/variance.png`` (noise scale and SNR by frame, seeds aggregated),
``ROOT/variance_by_seed.png`` (the loss's own noise beside each seed's evaluations,
seeds whose best checkpoint holds the threshold on fresh episodes, greedily and by
sampling, drawn solid and the others dashed: run ``rl-pg evaluate`` on each seed first)
and ``ROOT/variance.md`` / ``ROOT/variance.json`` (a table).

A noise scale is a ratio of means, `B = mean(tr Σ) / mean(|∇J|²)` over the measurements
of a window, as McCandlish et al. (2018) average it: each batch's `|∇J|²` estimate is
unbiased but often negative, their ratio per batch is not.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.app.lab_figures import seed_figure, variance_figure
from rl_pg.app.noise import (
    comparable,
    measurements,
    noise_scale_curve,
    relative_variance,
    stored_config,
    units,
)
from rl_pg.app.stores import read_report
from rl_pg.checkpoint import write_atomically
from rl_pg.gradient_statistics import ESTIMATORS
from rl_pg.training.checkpoints import CHECKPOINT
from rl_pg.training.config import TrainConfig
from rl_pg.training.resuming import changed_settings
from rl_pg.training.run_dir import SUMMARY

__all__ = ["LabArgs", "summarise", "variance_lab"]


@dataclasses.dataclass
class LabArgs:
    """Train a recipe's seeds measuring the gradient noise of every return estimator,
    then draw it (ROOT/variance.png) and tabulate it (ROOT/variance.md). Every other
    flag is the recipe's (rl-pg train RECIPE --help) and applies to every seed; --run-dir
    is ROOT (default runs/lab-variance-RECIPE)."""

    seeds: list[int] = dataclasses.field(default_factory=lambda: [0, 1, 2])
    """Seeds trained, each in ROOT/seedS (S the seed). A finished one is kept, a stopped
    one resumes."""
    every: int = 20
    """Updates between measurements. Measuring every estimator on one batch costs about
    one to two updates of the recipes' small networks."""


def variance_lab(recipe, cfg: TrainConfig, *, seeds: Sequence[int], every: int, root: Path):
    """Trains ``recipe`` with ``cfg`` on each seed, measuring every ``every`` updates,
    then writes the figure and the table; returns the table's data.

    Raises:
        ValueError: no seed, or ``every`` below 1.
    """
    if not seeds:
        raise ValueError("The lab needs at least one seed (--seeds).")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"--every must be a positive number of updates, got {every!r}.")
    root = Path(root)
    runs = {seed: root / f"seed{seed}" for seed in seeds}
    for seed, run_dir in runs.items():  # before any training: one setting per folder
        own = dataclasses.replace(cfg, seed=seed, run_dir=run_dir, grad_stats=every)
        _same_setting(own if recipe.prepare is None else recipe.prepare(own), run_dir)
    for seed, run_dir in runs.items():
        if _finished(run_dir):
            continue
        resume = (run_dir / CHECKPOINT).exists()
        recipe.train(
            dataclasses.replace(cfg, seed=seed, run_dir=run_dir, grad_stats=every, resume=resume)
        )
    return summarise(runs, root, title=f"{recipe.name}: gradient noise of each return estimator")


def _same_setting(cfg: TrainConfig, run_dir: Path) -> None:
    """Refuses a lab folder whose seed ``run_dir`` was trained with other settings than
    ``cfg``'s: its seeds would be measured under two settings and pooled as one."""
    if not (run_dir / "config.json").is_file():
        return
    stored = stored_config(run_dir)
    keep = frozenset({"resume", "run_dir", "progress", "threads", "workers", "ray"})
    changed = changed_settings(cfg, stored, may_change=keep | _LOGGING)
    if changed:
        details = ", ".join(
            f"--{k.replace('_', '-')} {_shown(old)} (now {_shown(new)})"
            for k, (old, new) in changed.items()
        )
        raise ValueError(
            f"{run_dir} was trained with {details}: a lab folder holds the seeds of one "
            f"setting. Give these flags another --run-dir, or repeat that seed's."
        )


_LOGGING = frozenset(TrainConfig.groups["logging"][1])


def _shown(value: Any) -> str:
    return (
        "unset"
        if value is None
        else " ".join(map(str, value))
        if isinstance(value, list)
        else str(value)
    )


def _finished(run_dir: Path) -> bool:
    path = run_dir / SUMMARY
    if not path.is_file():
        return False
    try:
        return not json.loads(path.read_text()).get("interrupted", False)
    except json.JSONDecodeError:
        return False


def summarise(runs: dict[int, Path], root: Path, *, title: str) -> dict[str, Any]:
    """The figure (``root/variance.png``) and the table (``root/variance.md``,
    ``root/variance.json``) of the runs ``{seed: run_dir}``; returns the table's data:
    for each estimator measured, each seed's noise scale over its whole run and over
    each half, and the mean units per measurement."""
    estimators = [
        e
        for e in ESTIMATORS
        if all(
            (r / "logs/csv/scalars/grad" / e / "trace_covariance.csv").is_file()
            for r in runs.values()
        )
    ]
    if not estimators:
        raise FileNotFoundError(_nothing_measured(runs, root))
    table: dict[str, Any] = {"seeds": list(runs), **units(runs), "estimators": {}}
    for estimator in estimators:
        measured = {seed: measurements(run_dir, estimator) for seed, run_dir in runs.items()}
        end = max(m["frames"].max() for m in measured.values()) + 1
        pooled = noise_scale_curve(list(measured.values()), np.array([0.0, end / 2, end]))
        whole = noise_scale_curve(list(measured.values()), np.array([0.0, end]))
        table["estimators"][estimator] = {
            "noise_scale": float(whole[1][0]),
            "noise_scale_first_half": float(pooled[1][0]),
            "noise_scale_second_half": float(pooled[1][1]),
            "snr": float(whole[2][0]),
            "units": float(np.concatenate([m["units"] for m in measured.values()]).mean()),
            "measurements": int(sum(len(m["frames"]) for m in measured.values())),
            "variance_relative_to_episode_return": float(
                relative_variance(
                    list(measured.values()),
                    [measurements(r, "episode_return") for r in runs.values()],
                    np.array([0.0, end]),
                )[0]
            )
            if "episode_return" in estimators and comparable(estimator, runs)
            else None,
            "noise_scale_by_seed": {
                seed: float(noise_scale_curve([m], np.array([0.0, end]))[1][0])
                for seed, m in measured.items()
            },
        }
    table["held"] = {seed: _held(run_dir) for seed, run_dir in runs.items()}
    # the data first: a figure that fails loses no measurement
    write_atomically(root / "variance.json", json.dumps(table, indent=2))
    write_atomically(root / "variance.md", _markdown(table))
    variance_figure(runs, estimators, root / "variance.png", title=title)
    # The quietest estimator resolves the signal |∇J|² best (they share it, GAE nearly).
    quietest = next(e for e in ("gae", "reward_to_go_minus_value", *estimators) if e in estimators)
    seed_figure(runs, table["held"], root / "variance_by_seed.png", title=title, estimator=quietest)
    return table


def _nothing_measured(runs: dict[int, Path], root: Path) -> str:
    """Why no estimator's statistics are in every run, and what to change."""
    short = []
    for seed, run_dir in runs.items():
        try:
            every = json.loads((run_dir / "config.json").read_text()).get("grad_stats")
            updates = json.loads((run_dir / SUMMARY).read_text())["updates"]
        except (OSError, ValueError, KeyError):
            continue
        if not every:
            return (
                f"{run_dir} measured no gradient statistics (a run trained without "
                f"--grad-stats, not by rl-pg lab): give the lab another --run-dir."
            )
        if updates < every:
            short.append(f"seed {seed} trained {updates} updates")
    if short:
        return (
            f"The runs under {root} measured nothing: {', '.join(short)}, and a measurement "
            f"is taken every {every} updates (--every). Lower --every, or give each seed "
            f"a larger budget (--total-frames / --total-updates)."
        )
    return f"No gradient statistics in every run under {root}: train them with --grad-stats N."


def _held(run_dir: Path) -> dict[str, Any] | None:
    """Whether the run's best checkpoint held the run's threshold on fresh episodes
    greedily and by sampling (its latest ``rl-pg evaluate`` results), with both means;
    None where either was not measured or the run has no threshold."""
    report = read_report(run_dir)
    threshold = report["threshold"]
    greedy, sampled = report["greedy"], report["sampled"]
    if threshold is None or greedy is None or sampled is None:
        return None
    means = greedy["mean_return"], sampled["mean_return"]
    return {"holds": min(means) >= threshold, "greedy": means[0], "sampled": means[1]}


def _markdown(table: dict[str, Any]) -> str:
    """The table: each estimator's noise scale over every seed's measurements pooled,
    in the first and the second half of training, the SNR at the batch size used, and
    each seed alone (— where the mean signal was not positive: noise dominates)."""
    scale, units = "noise scale B", "units"
    if table.get("unit") == "group":  # B counts groups
        scale, units = f"noise scale B (groups of {table['group_size']})", "groups"
    lines = [
        f"| estimator | tr Σ / tr Σ of R(τ) | {scale} | first half | second half "
        f"| SNR at the batch size ({units}) | B by seed |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for estimator, row in table["estimators"].items():
        by_seed = " / ".join(_number(b) for b in row["noise_scale_by_seed"].values())
        relative = row["variance_relative_to_episode_return"]
        lines.append(
            f"| {estimator} | {_number(np.nan if relative is None else relative)} | "
            f"{_number(row['noise_scale'])} | "
            f"{_number(row['noise_scale_first_half'])} | "
            f"{_number(row['noise_scale_second_half'])} | "
            f"{_number(row['snr'])} ({row['units']:.3g}) | {by_seed} |"
        )
    return "\n".join(lines) + "\n"


def _number(value: float) -> str:
    return "—" if not np.isfinite(value) else f"{value:,.3g}"
