"""REINFORCE with a learned baseline on Atari Pong (the set-up of docs/recipes/pong.md).

Frames go through ``FrameDifference`` (80x80 binarised differences, 6 400 inputs);
a shared Linear(6400, 200)-ReLU trunk feeds a policy head (6 logits) and a value
head. 16 games stepped as one batch (gymnasium's SyncVectorEnv behind TorchRL);
every 50 steps an update with n-step returns bootstrapped from V; gamma 0.99,
entropy 0.01, value-loss weight 2, Adam 1e-3, gradient clip 1. Needs the atari extra
(ale-py ships the ROMs):

    pip install -c constraints.txt -e ".[atari]"
    python recipes/pong.py
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Literal

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.modules import ActorValueOperator, ProbabilisticActor, ValueOperator

from rl_pg.envs import gym_env
from rl_pg.frame_difference import FrameDifference
from rl_pg.training import Count, TrainConfig, train
from rl_pg.training.cli import parse_config
from rl_pg.training.console import format_summary
from rl_pg.training.interrupt import exit_quietly_on_interrupt


@dataclass
class Config(TrainConfig):
    """REINFORCE + learned baseline with bootstrapped 50-step segments on ALE Pong."""

    num_envs: Count = 16
    """Pong games played at once, as one batch (split evenly over the workers)."""
    hidden: Count = 200
    """Width of the shared trunk."""
    total_frames: int = 2_000_000
    """Agent steps (each 4 Atari frames) to train for (at most)."""
    batch_mode: Literal["episodes", "segments"] = "segments"
    """Fixed-length segments with bootstrap from V."""
    segment_length: int = 50
    """t_max: steps per environment per update."""
    entropy_coeff: float = 0.01
    """Entropy bonus weight."""
    critic_coeff: float = 2.0
    """Value-loss weight."""
    max_grad_norm: float | None = 1.0
    """Gradient-norm clipping."""
    eval_interval: int = 100_000
    """Agent steps between greedy evaluations."""
    eval_episodes: int = 4
    """Greedy games per evaluation (a game lasts thousands of steps)."""
    threshold: float | None = 0.0
    """Greedy mean score that counts as a milestone (the game is solved at 20)."""
    stop_when_solved: bool = False
    """Keep training past the milestone."""
    checkpoint_interval: int = 200
    """Updates between checkpoints."""
    log_interval: int = 10
    """Updates between training-metric log lines."""


def _register_atari() -> None:
    import ale_py
    import gymnasium

    gymnasium.register_envs(ale_py)


ALE = {"frameskip": 4, "repeat_action_probability": 0.0}  # skip 4 frames, no sticky actions


def make_game(*, render: bool = False) -> EnvBase:
    """One game (evaluation, deployment)."""
    _register_atari()
    env = gym_env("ALE/Pong-v5", **ALE)  # GymEnv names image observations "pixels"
    return TransformedEnv(env, FrameDifference(keep_pixels=render))


def make_games(num_envs: int) -> EnvBase:
    """``num_envs`` games stepped as one batch."""
    if num_envs == 1:
        return make_game()
    _register_atari()
    games = gym_env("ALE/Pong-v5", num_envs=num_envs, **ALE)  # frames under "observation"
    return TransformedEnv(games, FrameDifference(in_key="observation"))


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    if render:
        return make_game(render=True)
    return make_games(max(1, cfg.num_envs // max(1, cfg.workers)))


def make_models(env: EnvBase, cfg: Config):
    trunk = TensorDictModule(
        nn.Sequential(nn.Linear(6400, cfg.hidden), nn.ReLU()), ["observation"], ["hidden"]
    )
    policy = ProbabilisticActor(
        TensorDictModule(nn.Linear(cfg.hidden, env.action_spec.space.n), ["hidden"], ["logits"]),
        in_keys=["logits"],
        spec=env.action_spec,
        distribution_class=torch.distributions.Categorical,
    )
    value = ValueOperator(nn.Linear(cfg.hidden, 1), in_keys=["hidden"])
    model = ActorValueOperator(trunk, policy, value)
    return model.get_policy_operator(), model.get_value_operator()


def main(cfg: Config) -> dict:
    return train(
        cfg,
        recipe="pong",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
        make_eval_env=partial(make_games, cfg.eval_episodes),  # the games side by side
    )


if __name__ == "__main__":
    with exit_quietly_on_interrupt():
        print(format_summary(main(parse_config(Config))))
