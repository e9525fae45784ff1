"""REINFORCE on CartPole-v1 until greedy play is solved (mean >= 475 over 20 episodes).

Config -> environment -> models -> rl_pg's training loop. By default 32 CartPoles are
stepped as one batch in this process (gymnasium's SyncVectorEnv behind TorchRL's
GymWrapper) and each update uses 8 steps of each, with reward-to-go bootstrapped from
a learned V(s) at the segment's end and V(s) as the baseline: the fastest set-up on a
CPU (see benchmarks/). The textbook variant, whole episodes from one environment:

    python recipes/cartpole.py --batch-mode episodes --num-envs 1
    python recipes/cartpole.py --help
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
    """REINFORCE with reward-to-go and a learned value baseline on CartPole-v1."""

    env_id: str = "CartPole-v1"
    """Gymnasium environment id."""
    hidden: Count = 64
    """Width of the two hidden layers of the actor and of the critic."""
    num_envs: Count = 32
    """CartPoles stepped together as one batch (1: a single unbatched environment)."""
    total_frames: int = 300_000
    """Environment steps to train for (at most)."""
    batch_mode: Literal["episodes", "segments"] = "segments"
    """Fixed-length segments bootstrapped from V, or whole episodes."""
    segment_length: int = 8
    """Steps per environment per update (segments)."""
    episodes_per_batch: int = 4
    """Complete episodes per update (with --batch-mode episodes)."""
    lr: float = 5e-3
    """Learning rate."""
    max_grad_norm: float | None = 1.0
    """Gradient-norm clipping (None: no clipping)."""
    normalize_advantage: bool = True
    """Standardise the policy weights over each batch."""
    eval_interval: int = 5_000
    """Frames between greedy evaluations."""
    threshold: float | None = 475.0
    """Evaluation mean return that counts as solved."""


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    if render or cfg.num_envs == 1:
        return gym_env(cfg.env_id, render=render)
    return gym_env(cfg.env_id, num_envs=cfg.num_envs)


def make_eval_env(cfg: Config) -> EnvBase:
    """The evaluation episodes, played side by side."""
    return gym_env(cfg.env_id, num_envs=cfg.eval_episodes if cfg.eval_episodes > 1 else None)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden, cfg.hidden))


def main(cfg: Config) -> dict:
    return train(
        cfg,
        recipe="cartpole",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
        make_eval_env=partial(make_eval_env, cfg),
    )


if __name__ == "__main__":
    with exit_quietly_on_interrupt():
        print(format_summary(main(parse_config(Config))))
