"""REINFORCE with a learned baseline on LunarLander-v3 (solved at a greedy mean of 200).

8 landers stepped as one batch; every update uses 64 steps of each, returns bootstrapped from
V where episodes are cut (whole-episode batches, ``--batch-mode episodes``, learned
but did not hold 200 in our run: see RESULTS.md). Discrete engines by default;
--continuous switches to continuous thrust with a Gaussian (TanhNormal) policy. Needs
the box2d extra:

    pip install -c constraints.txt -e ".[box2d]"
    python recipes/lunarlander.py --help
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Literal

from torchrl.envs import EnvBase

from rl_pg.envs import gym_env
from rl_pg.models import mlp_actor_critic
from rl_pg.training import Count, TrainConfig, train
from rl_pg.training.cli import parse_config
from rl_pg.training.console import format_summary
from rl_pg.training.interrupt import exit_quietly_on_interrupt


@dataclass
class Config(TrainConfig):
    """REINFORCE with reward-to-go and a learned value baseline on LunarLander-v3."""

    continuous: bool = False
    """Continuous thrust (Box(-1, 1, (2,))) with a Gaussian policy."""
    num_envs: Count = 8
    """Landers stepped together as one batch in this process."""
    hidden: Count = 128
    """Width of the two hidden layers of the actor and of the critic."""
    total_frames: int = 1_000_000
    """Environment steps to train for (at most)."""
    batch_mode: Literal["episodes", "segments"] = "segments"
    """Fixed-length segments with bootstrap from V."""
    segment_length: int = 64
    """Steps per lander per update."""
    episodes_per_batch: int = 16
    """Complete episodes per update (with --batch-mode episodes)."""
    lr: float = 1e-3
    """Learning rate."""
    entropy_coeff: float = 0.01
    """Entropy bonus weight."""
    critic_coeff: float = 0.5
    """Value-loss weight."""
    max_grad_norm: float | None = 0.5
    """Gradient-norm clipping (None: no clipping)."""
    checkpoint_interval: int = 100
    """Updates between checkpoints."""
    log_interval: int = 5
    """Updates between training-metric log lines."""
    eval_interval: int = 25_000
    """Frames between greedy evaluations."""
    threshold: float | None = 200.0
    """Evaluation mean return that counts as solved."""


def make_landers(cfg: Config, num_envs: int, *, render: bool = False) -> EnvBase:
    """``num_envs`` landers stepped as one batch (one lander: batch size ``[]``)."""
    return gym_env(
        "LunarLander-v3",
        num_envs=num_envs if num_envs > 1 else None,
        render=render,
        continuous=cfg.continuous,
    )


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    return make_landers(cfg, 1 if render else cfg.num_envs, render=render)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden, cfg.hidden))


def main(cfg: Config) -> dict:
    return train(
        cfg,
        recipe="lunarlander",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
        make_eval_env=partial(make_landers, cfg, cfg.eval_episodes),  # side by side
    )


if __name__ == "__main__":
    with exit_quietly_on_interrupt():
        print(format_summary(main(parse_config(Config))))
