"""REINFORCE on LunarLander-v3 (solved at a greedy mean of 200).

Discrete engines by default; --continuous switches to the continuous-thrust version
with a Gaussian (TanhNormal) policy. Needs the box2d extra:

    pip install -c constraints.txt -e ".[box2d]"
    python recipes/lunarlander.py --help
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import tyro
from torchrl.envs import EnvBase, RewardSum, SerialEnv, TransformedEnv

from rl_pg.envs import gym_env
from rl_pg.models import mlp_actor_critic
from rl_pg.trainer import TrainConfig, train


@dataclass
class Config(TrainConfig):
    """REINFORCE with reward-to-go and a learned value baseline on LunarLander-v3."""

    continuous: bool = False
    """Continuous thrust (Box(-1, 1, (2,))) with a Gaussian policy."""
    envs: int = 1
    """Landers stepped together in one process (useful with --batch-mode segments)."""
    hidden: int = 128
    """Width of the two hidden layers of the actor and of the critic."""
    total_frames: int = 1_000_000
    """Environment steps to train for (at most)."""
    episodes_per_batch: int = 16
    """Complete episodes per update."""
    lr: float = 2e-3
    """Learning rate."""
    max_grad_norm: float | None = 1.0
    """Gradient-norm clipping (None: no clipping)."""
    normalize_advantage: bool = True
    """Standardise the policy weights over each batch."""
    eval_interval: int = 25_000
    """Frames between greedy evaluations."""
    threshold: float | None = 200.0
    """Evaluation mean return that counts as solved."""


def make_lander(cfg: Config, *, render: bool = False) -> EnvBase:
    return gym_env("LunarLander-v3", render=render, continuous=cfg.continuous)


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    if render or cfg.envs == 1:
        return make_lander(cfg, render=render)
    # RewardSum logs whole-episode returns even when updates see segments.
    return TransformedEnv(SerialEnv(cfg.envs, partial(make_lander, cfg)), RewardSum())


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden, cfg.hidden))


def main(cfg: Config) -> dict:
    return train(
        cfg,
        recipe="lunarlander",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
        make_eval_env=partial(make_lander, cfg),
    )


if __name__ == "__main__":
    print(main(tyro.cli(Config)))
