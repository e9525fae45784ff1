"""REINFORCE on the 4x4 gridworld, and the comparison of its return estimators.

The experiment is described in docs/recipes/gridworld.md::

    rl-pg train gridworld                    # reward-to-go minus a learned V(s)
    rl-pg train gridworld --compare          # no baseline / running mean /
                                             # reward-to-go / learned V, 5 seeds
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from torch import nn
from torchrl.envs import EnvBase

from rl_pg.envs import GridWorldEnv
from rl_pg.models import mlp_actor_critic
from rl_pg.training import Count, TrainConfig
from rl_pg.training.comparison import run_variants
from rl_pg.training.curves import plot_curves, read_curve
from rl_pg.training.recipe import Recipe
from rl_pg.training.settings import BatchedEnvironments

# The comparison of docs/recipes/gridworld.md, plus reward-to-go minus a learned V(s).
VARIANTS = {
    "no baseline": {"returns": "discounted_return", "baseline": "none"},
    "running-mean baseline": {"returns": "discounted_return", "baseline": "running_mean"},
    "reward-to-go": {"returns": "reward_to_go", "baseline": "none"},
    "reward-to-go - learned V": {"returns": "reward_to_go", "baseline": "critic"},
}


@dataclass
class Config(
    TrainConfig,
    BatchedEnvironments,
    num_envs=30,
    total_frames=1_000_000,
    total_updates=30,  # the experiment: 30 updates of 30 episodes
    episodes_per_batch=30,
    gamma=1.0,
    lr=0.02,
    eval_interval=1,  # after every update
    eval_episodes=1,  # the gridworld is deterministic: one greedy episode tells its return
):
    """REINFORCE on a 4x4 gridworld (goal +1, pit -1, -0.1 per step), gamma = 1."""

    hidden: Count = 32
    """Width of the hidden layer (obs -> hidden -> 4, ReLU)."""
    max_steps: Count = 100
    """Episode truncation horizon."""
    compare: bool = False
    """Run every variant of the comparison on n_seeds seeds and plot them."""
    n_seeds: Count = 5
    """Seeds per variant with --compare."""


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    if render:  # one grid, drawn
        return GridWorldEnv(max_steps=cfg.max_steps, render=True)
    return GridWorldEnv(batch_size=cfg.num_envs, max_steps=cfg.max_steps)


def make_eval_env(cfg: Config) -> EnvBase:
    return GridWorldEnv(max_steps=cfg.max_steps)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden,), activation=nn.ReLU)


def prepare(cfg: Config) -> Config:
    if cfg.threshold is None:  # solved: the shortest path's return (float32 slack)
        cfg = dataclasses.replace(cfg, threshold=GridWorldEnv().optimal_return - 1e-6)
    return cfg


def compare(cfg: Config) -> dict:
    """Every variant on ``n_seeds`` seeds; the curves side by side in comparison.png."""
    root = Path(cfg.run_dir or "runs/gridworld-comparison")
    seeds = range(cfg.seed, cfg.seed + cfg.n_seeds)
    results = run_variants(RECIPE.train, cfg, VARIANTS, seeds=seeds, root=root)
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


RECIPE = Recipe(
    name="gridworld",
    config=Config,
    make_env=make_env,
    make_models=make_models,
    make_eval_env=make_eval_env,
    prepare=prepare,
    commands={"compare": compare},
)
