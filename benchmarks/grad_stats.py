"""What measuring the policy gradient's noise costs a training run.

``--grad-stats N`` measures, every N updates, the per-unit gradients of every return
estimator on that update's batch (rl_pg.gradient_statistics). Here the CartPole and
LunarLander recipes train with their defaults for a fixed number of frames, with and
without the measurement, repetitions interleaved. Two figures: the training wall-clock
with it over the training wall-clock without (medians; moves with the machine's noise),
and, within each measured run, the measurement's own share of its training time (the
logged ``time/grad_stats_s`` over ``train_wall_s``: steady, since it needs no second
run). Target: <= 10 % at the interval the variance lab uses by default (20).

    python benchmarks/grad_stats.py
"""

from __future__ import annotations

import statistics
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tyro
from common import REPO, table, write_json
from throughput import cartpole, lunarlander

from rl_pg.training.curves import read_curve


@dataclass
class Config:
    """Training time with --grad-stats N over training time without, CartPole and LunarLander."""

    cartpole_frames: int = 100_000
    """Frames per CartPole repetition."""
    lunarlander_frames: int = 50_000
    """Frames per LunarLander repetition."""
    tasks: list[str] = field(default_factory=lambda: ["CartPole", "LunarLander"])
    """Tasks timed (CartPole, LunarLander)."""
    intervals: list[int] = field(default_factory=lambda: [20, 10])
    """Values of --grad-stats timed against no measurement."""
    repeats: int = 3
    """Interleaved repetitions per contender (medians are compared)."""
    threads: int = 1
    """torch threads (the recipes' default)."""
    json_path: Path = REPO / "benchmarks" / "results" / "grad_stats.json"
    """Where the results go."""


def training(recipe, grad_stats: int | None):
    """``frames -> (frames/s, the measurement's share of the training time)``."""

    def run(frames: int) -> tuple[float, float]:
        with tempfile.TemporaryDirectory() as run_dir:
            summary = recipe.train(
                recipe.config(
                    run_dir=Path(run_dir), total_frames=frames, threshold=None,
                    eval_interval=10**12, eval_episodes=1, checkpoint_interval=10**12,
                    progress=False, grad_stats=grad_stats,
                )
            )  # fmt: skip
            share = 0.0
            if grad_stats is not None:
                share = read_curve(run_dir, "time/grad_stats_s")[1].sum() / summary["train_wall_s"]
        return summary["frames"] / summary["train_wall_s"], share

    return run


def main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    runs = {}
    for task, recipe, frames in (
        ("CartPole", cartpole, cfg.cartpole_frames),
        ("LunarLander", lunarlander, cfg.lunarlander_frames),
    ):
        if task not in cfg.tasks:
            continue
        runs[task, None] = (training(recipe, None), frames)
        for every in cfg.intervals:
            runs[task, every] = (training(recipe, every), frames)
    rates: dict[tuple, list[float]] = {key: [] for key in runs}
    shares: dict[tuple, list[float]] = {key: [] for key in runs}
    for _ in range(cfg.repeats):
        for key, (run, frames) in runs.items():
            rate, share = run(frames)
            rates[key].append(rate)
            shares[key].append(share)
    median = {key: statistics.median(r) for key, r in rates.items()}
    rows, cost, share_of_training = [], {}, {}
    for (task, every), rate in median.items():
        slowdown = median[task, None] / rate
        share = statistics.median(shares[task, every])
        if every is not None:
            cost[f"{task} --grad-stats {every}"] = slowdown
            share_of_training[f"{task} --grad-stats {every}"] = share
        rows.append([task, "off" if every is None else every, rate, slowdown, share])
    header = ["task", "--grad-stats", "frames/s (median)", "time / time without", "share"]
    print(table(rows, header))
    return write_json(
        cfg.json_path,
        cfg,
        frames_per_s={f"{t} {e}": r for (t, e), r in rates.items()},
        median_frames_per_s={f"{t} {e}": r for (t, e), r in median.items()},
        time_over_time_without=cost,
        measurement_share_of_training=share_of_training,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
