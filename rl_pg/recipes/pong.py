"""REINFORCE with a learned baseline on Atari Pong (the set-up of docs/recipes/pong.md).

Frames go through ``FrameDifference`` (80x80 binarised differences, 6 400 inputs);
a shared Linear(6400, 200)-ReLU trunk feeds a policy head (6 logits) and a value
head. 16 games stepped as one batch (gymnasium's SyncVectorEnv behind TorchRL);
every 50 steps an update with n-step returns bootstrapped from V; gamma 0.99,
entropy 0.01, value-loss weight 2, Adam 1e-3, gradient clip 1. Needs the atari extra
(ale-py ships the ROMs)::

    pip install -c constraints.txt "rl_pg[atari]"
    rl-pg train pong
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.modules import ActorValueOperator, ConvNet, ProbabilisticActor, ValueOperator

from rl_pg._checks import require_extra
from rl_pg.envs import gym_env
from rl_pg.frame_difference import FrameDifference
from rl_pg.training import Count, Range, TrainConfig
from rl_pg.training.recipe import Recipe
from rl_pg.training.settings import BatchedEnvironments


@dataclass
class Config(
    TrainConfig,
    BatchedEnvironments,
    num_envs=16,
    total_frames=2_000_000,  # agent steps, each 4 Atari frames
    batch_mode="segments",
    segment_length=50,  # t_max
    entropy_coeff=0.01,
    critic_coeff=2.0,
    max_grad_norm=1.0,
    eval_interval=100_000,
    eval_episodes=4,  # a game lasts thousands of steps
    threshold=0.0,  # a milestone: the game is solved at 20
    stop_when_solved=False,
    checkpoint_interval=200,
    env_restart_interval=200,  # 160k agent steps: a game is rarely cut
    log_interval=10,
):
    """REINFORCE + learned baseline with bootstrapped 50-step segments on ALE Pong."""

    hidden: Count = 200
    """Width of the shared trunk."""
    trunk: Literal["dense", "conv"] = "dense"
    """Shared trunk: a dense layer, or convolutions over the 80x80 images. 'dense' is
    one layer over the flattened inputs. 'conv' is two convolutions (16 8x8 filters
    with stride 4, 32 4x4 with stride 2) then a dense layer of ``hidden`` units; that
    trunk and the heads start from orthogonal weights (gain sqrt 2; the policy head's
    0.01, the value head's 1). The convolutions see the same filters at every place of
    the court, with a sixth of the dense layer's weights, but they learn only with
    many updates: pair them with short segments (``--segment-length 10``)."""
    frame: bool = False
    """Also feed the current frame beside the difference (12 800 inputs). A difference
    shows nothing of a paddle that stands still; with sticky actions where it stands
    matters."""
    train_sticky: Annotated[float, Range(0, 1, high_open=True)] = 0.0
    """Sticky-action probability of the training games. At 0 the policy can learn one
    line of play that a repeated action breaks (see eval_sticky)."""
    eval_sticky: Annotated[float, Range(0, 1, high_open=True)] = 0.25
    """Sticky-action probability of evaluated and played games. Each step the game
    repeats the previous action instead of the agent's with this probability (ALE's
    sticky actions; 0.25 as Machado et al. 2018 evaluate). At 0, Pong and a greedy
    policy are deterministic: every greedy game replays one game."""


def _register_atari() -> None:
    require_extra("ale_py", "atari", "Pong")
    import ale_py
    import gymnasium

    gymnasium.register_envs(ale_py)
    # ALE prints its banner to stderr for every game it creates; keep its errors only.
    ale_py.ALEInterface.setLoggerMode(ale_py.LoggerMode.Error)


FRAMESKIP = 4  # each agent step is 4 Atari frames


def make_game(*, sticky: float = 0.0, render: bool = False) -> EnvBase:
    """One game (evaluation, deployment); ``sticky``: ALE's repeat-action probability."""
    _register_atari()
    env = gym_env(  # GymEnv names image observations "pixels"
        "ALE/Pong-v5", frameskip=FRAMESKIP, repeat_action_probability=sticky
    )
    return TransformedEnv(env, FrameDifference(keep_pixels=render))


def make_games(num_envs: int, *, sticky: float = 0.0) -> EnvBase:
    """``num_envs`` games stepped as one batch."""
    if num_envs == 1:
        return make_game(sticky=sticky)
    _register_atari()
    games = gym_env(  # frames under "observation"
        "ALE/Pong-v5", num_envs=num_envs, frameskip=FRAMESKIP, repeat_action_probability=sticky
    )
    return TransformedEnv(games, FrameDifference(in_key="observation"))


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    if render:
        return make_game(render=True)
    return make_games(max(1, cfg.num_envs // max(1, cfg.workers)), sticky=cfg.train_sticky)


def make_play_env(cfg: Config, *, render: bool = False) -> EnvBase:
    """The game ``rl-pg play`` deploys in, recorded or not: as evaluations play it."""
    return make_game(sticky=cfg.eval_sticky, render=render)


class _Images(nn.Sequential):
    """The trunk's layers over the difference (and the current frame) as 80x80 images:
    flattened side by side for a dense layer, as channels for convolutions."""

    def __init__(self, *layers: nn.Module, channels: bool) -> None:
        super().__init__(*layers)
        self.channels = channels

    def forward(self, difference: torch.Tensor, *frame: torch.Tensor) -> torch.Tensor:
        if self.channels:
            images = [difference.unflatten(-1, (80, 80)), *frame]
            return super().forward(torch.stack(images, dim=-3))
        return super().forward(torch.cat([difference, *(f.flatten(-2) for f in frame)], -1))


def make_models(env: EnvBase, cfg: Config):
    # FrameDifference keeps the current frame as the next step's previous one.
    in_keys = ["observation", "previous_frame"] if cfg.frame else ["observation"]
    if cfg.trunk == "conv":
        convolutions = ConvNet(
            in_features=len(in_keys),
            num_cells=[16, 32],
            kernel_sizes=[8, 4],
            strides=[4, 2],
            activation_class=nn.ReLU,
        )  # 80x80 -> 16x19x19 -> 32x8x8, flattened
        layers = _Images(convolutions, nn.Linear(32 * 8 * 8, cfg.hidden), nn.ReLU(), channels=True)
    else:
        layers = _Images(nn.Linear(len(in_keys) * 6400, cfg.hidden), nn.ReLU(), channels=False)
    trunk = TensorDictModule(layers, in_keys, ["hidden"])
    policy = ProbabilisticActor(
        TensorDictModule(nn.Linear(cfg.hidden, env.action_spec.space.n), ["hidden"], ["logits"]),
        in_keys=["logits"],
        spec=env.action_spec,
        distribution_class=torch.distributions.Categorical,
    )
    value = ValueOperator(nn.Linear(cfg.hidden, 1), in_keys=["hidden"])
    if cfg.trunk == "conv":
        _orthogonal(layers, policy.module[0].module, value.module)
    model = ActorValueOperator(trunk, policy, value)
    return model.get_policy_operator(), model.get_value_operator()


def _orthogonal(trunk: nn.Module, policy_head: nn.Linear, value_head: nn.Linear) -> None:
    """Orthogonal weights and zero biases, as Atari's actor-critic networks start: gain
    sqrt 2 in the ReLU trunk, 0.01 for the policy head (a near-uniform first policy), 1
    for the value head."""
    for layer in trunk.modules():
        if isinstance(layer, (nn.Conv2d, nn.Linear)):
            nn.init.orthogonal_(layer.weight, math.sqrt(2))
            nn.init.zeros_(layer.bias)
    for head, gain in ((policy_head, 0.01), (value_head, 1.0)):
        nn.init.orthogonal_(head.weight, gain)
        nn.init.zeros_(head.bias)


def make_eval_env(cfg: Config) -> EnvBase:
    """The evaluation games, side by side, with sticky actions (``eval_sticky``)."""
    return make_games(cfg.eval_episodes, sticky=cfg.eval_sticky)


RECIPE = Recipe(
    name="pong",
    config=Config,
    make_env=make_env,
    make_models=make_models,
    make_eval_env=make_eval_env,
    make_play_env=make_play_env,
)
