"""REINFORCE on the 4x4 gridworld, and the comparison of its return estimators.

The experiment is described in docs/recipes/gridworld.md.

python recipes/gridworld.py                    # reward-to-go minus a learned V(s)
python recipes/gridworld.py --compare          # no baseline / running mean /
                                               # reward-to-go / learned V, 5 seeds
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from torch import nn
from torchrl.envs import EnvBase

from rl_pg.envs import GridWorldEnv
from rl_pg.models import mlp_actor_critic
from rl_pg.training import Count, TrainConfig, train
from rl_pg.training.cli import parse_config
from rl_pg.training.comparison import plot_curves, read_curve, run_variants
from rl_pg.training.console import format_summary
from rl_pg.training.interrupt import exit_quietly_on_interrupt

# The comparison of docs/recipes/gridworld.md, plus reward-to-go minus a learned V(s).
VARIANTS = {
    "no baseline": {"returns": "discounted_return", "baseline": "none"},
    "running-mean baseline": {"returns": "discounted_return", "baseline": "running_mean"},
    "reward-to-go": {"returns": "reward_to_go", "baseline": "none"},
    "reward-to-go - learned V": {"returns": "reward_to_go", "baseline": "critic"},
}


@dataclass
class Config(TrainConfig):
    """REINFORCE on a 4x4 gridworld (goal +1, pit -1, -0.1 per step), gamma = 1."""

    hidden: Count = 32
    """Width of the hidden layer (obs -> hidden -> 4, ReLU)."""
    envs: Count = 30
    """Gridworld copies stepped together."""
    max_steps: Count = 100
    """Episode truncation horizon."""
    compare: bool = False
    """Run every variant of the comparison on n_seeds seeds and plot them."""
    n_seeds: Count = 5
    """Seeds per variant with --compare."""
    total_frames: int = 1_000_000
    """Environment steps to train for (at most)."""
    total_updates: int | None = 30
    """Updates to train for (the experiment: 30 updates of 30 episodes)."""
    episodes_per_batch: int = 30
    """Complete episodes per update."""
    gamma: float = 1.0
    """Discount factor."""
    lr: float = 0.02
    """Learning rate."""
    eval_interval: int = 1
    """Frames between evaluations (1: after every update)."""
    eval_episodes: int = 1
    """The gridworld is deterministic: one greedy episode tells the greedy return."""


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    return GridWorldEnv(batch_size=cfg.envs, max_steps=cfg.max_steps)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden,), activation=nn.ReLU)


def main(cfg: Config) -> dict:
    if cfg.threshold is None:  # solved: the shortest path's return (float32 slack)
        cfg = dataclasses.replace(cfg, threshold=GridWorldEnv().optimal_return - 1e-6)
    return train(
        cfg,
        recipe="gridworld",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
        make_eval_env=lambda: GridWorldEnv(max_steps=cfg.max_steps),
    )


def compare(cfg: Config) -> dict:
    root = Path(cfg.run_dir or "runs/gridworld-comparison")
    seeds = range(cfg.seed, cfg.seed + cfg.n_seeds)
    results = run_variants(main, cfg, VARIANTS, seeds=seeds, root=root)
    curves = {
        name: [read_curve(run["run_dir"], "eval/mean_return") for run in runs]
        for name, runs in results.items()
    }
    plot_curves(
        curves,
        root / "comparison.png",
        xlabel="frames",
        ylabel="greedy return",
        title="4x4 gridworld: return estimators",
        hlines=[GridWorldEnv().optimal_return],
    )
    return results


if __name__ == "__main__":
    with exit_quietly_on_interrupt():
        config = parse_config(Config)
        print(compare(config) if config.compare else format_summary(main(config)))
