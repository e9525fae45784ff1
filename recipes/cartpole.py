"""REINFORCE on CartPole-v1 until greedy play is solved (mean >= 475 over 20 episodes).

Config -> environment -> models -> rl_pg's training loop: each update uses 4 whole
episodes collected by the current policy, reward-to-go minus a learned V(s).

    python recipes/cartpole.py --help
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import tyro
from torchrl.envs import EnvBase

from rl_pg.envs import gym_env
from rl_pg.models import mlp_actor_critic
from rl_pg.trainer import TrainConfig, train


@dataclass
class Config(TrainConfig):
    """REINFORCE with reward-to-go and a learned value baseline on CartPole-v1."""

    env_id: str = "CartPole-v1"
    """Gymnasium environment id."""
    hidden: int = 64
    """Width of the two hidden layers of the actor and of the critic."""
    total_frames: int = 300_000
    """Environment steps to train for (at most)."""
    episodes_per_batch: int = 4
    """Complete episodes per update."""
    lr: float = 5e-3
    """Learning rate."""
    max_grad_norm: float | None = 1.0
    """Gradient-norm clipping (None: no clipping)."""
    normalize_advantage: bool = True
    """Standardise the policy weights over each batch."""
    threshold: float | None = 475.0
    """Evaluation mean return that counts as solved."""


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    return gym_env(cfg.env_id, render=render)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden, cfg.hidden))


def main(cfg: Config) -> dict:
    return train(
        cfg,
        recipe="cartpole",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
    )


if __name__ == "__main__":
    print(main(tyro.cli(Config)))
