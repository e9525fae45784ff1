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
from torchrl.envs import EnvBase, GymEnv

from rl_pg.models import mlp_actor, mlp_critic
from rl_pg.trainer import TrainConfig, train


@dataclass
class Config(TrainConfig):
    """REINFORCE with reward-to-go and a learned value baseline on LunarLander-v3."""

    continuous: bool = False
    """Continuous thrust (Box(-1, 1, (2,))) with a Gaussian policy."""
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


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    return GymEnv(
        "LunarLander-v3",
        continuous=cfg.continuous,
        categorical_action_encoding=True,
        **({"from_pixels": True, "pixels_only": False} if render else {}),
    )


def make_models(env: EnvBase, cfg: Config):
    hidden = (cfg.hidden, cfg.hidden)
    return mlp_actor(env, hidden=hidden), mlp_critic(env, hidden=hidden)


def main(cfg: Config) -> dict:
    return train(
        cfg,
        recipe="lunarlander",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
    )


if __name__ == "__main__":
    print(main(tyro.cli(Config)))
