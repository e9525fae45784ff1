"""What measuring the policy gradient's noise costs a training run.

``--grad-stats N`` measures, every N updates, the per-unit gradients of every return
estimator on that update's batch (rl_pg.gradient_statistics). Here the CartPole and
LunarLander recipes train with their defaults for a fixed number of frames, with and
without the measurement, repetitions interleaved; the figure of merit is the training
wall-clock with it over the training wall-clock without (target at the interval the
variance lab uses, 10: <= 1.10).

    python benchmarks/grad_stats.py
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tyro
from common import REPO, table, write_json
from throughput import cartpole, lunarlander, recipe_training


@dataclass
class Config:
    """Training time with --grad-stats N over training time without, CartPole and LunarLander."""

    cartpole_frames: int = 100_000
    """Frames per CartPole repetition."""
    lunarlander_frames: int = 50_000
    """Frames per LunarLander repetition."""
    intervals: list[int] = field(default_factory=lambda: [10, 1])
    """Values of --grad-stats timed against no measurement."""
    repeats: int = 3
    """Interleaved repetitions per contender (medians are compared)."""
    threads: int = 1
    """torch threads (the recipes' default)."""
    json_path: Path = REPO / "benchmarks" / "results" / "grad_stats.json"
    """Where the results go."""


def main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    runs = {}
    for task, recipe, frames in (
        ("CartPole", cartpole, cfg.cartpole_frames),
        ("LunarLander", lunarlander, cfg.lunarlander_frames),
    ):
        runs[task, None] = (recipe_training(recipe), frames)
        for every in cfg.intervals:
            runs[task, every] = (recipe_training(recipe, grad_stats=every), frames)
    rates: dict[tuple, list[float]] = {key: [] for key in runs}
    for _ in range(cfg.repeats):
        for key, (run, frames) in runs.items():
            rates[key].append(run(frames))
    median = {key: statistics.median(r) for key, r in rates.items()}
    rows, cost = [], {}
    for (task, every), rate in median.items():
        slowdown = median[task, None] / rate
        if every is not None:
            cost[f"{task} --grad-stats {every}"] = slowdown
        rows.append([task, "off" if every is None else every, rate, slowdown])
    print(table(rows, ["task", "--grad-stats", "frames/s (median)", "time / time without"]))
    return write_json(
        cfg.json_path,
        cfg,
        frames_per_s={f"{t} {e}": r for (t, e), r in rates.items()},
        median_frames_per_s={f"{t} {e}": r for (t, e), r in median.items()},
        time_over_time_without=cost,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
