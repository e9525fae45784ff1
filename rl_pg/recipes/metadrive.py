"""The original driving set-up on MetaDrive (optional backend; docs/recipes/metadrive.md).

MetaDrive-validation-v0: a 259-dimensional observation in [0, 1] and a
Box(-1, 1, (2,)) action, discretised into the 9 joint driving actions; gamma 0.75,
entropy bonus 0.1, 200 episodes per update, Adam 1e-4, a checkpoint every 100
updates. MetaDrive is not installed with rl_pg; this recipe stops with instructions
when it is missing::

    pip install metadrive-simulator
    rl-pg train metadrive
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass

from torch import nn
from torchrl.envs import EnvBase

from rl_pg.envs import driving_env
from rl_pg.models import mlp_actor_critic
from rl_pg.training import Count, TrainConfig
from rl_pg.training.recipe import Recipe

INSTALL_HINT = (
    "MetaDrive is not installed. It is an optional backend because it downloads its "
    "assets from the internet on first use: `pip install metadrive-simulator`, then run "
    "`python -m metadrive.pull_asset` on a machine with network access. The same driving "
    "set-up runs offline on highway-env: `rl-pg train highway`."
)


@dataclass
class Config(
    TrainConfig,
    total_frames=2_000_000,
    episodes_per_batch=200,
    gamma=0.75,
    entropy_coeff=0.1,
    lr=1e-4,
    checkpoint_interval=100,
    eval_interval=50_000,
):
    """REINFORCE on MetaDrive with the driving experiment's hyper-parameters."""

    env_id: str = "MetaDrive-validation-v0"
    """MetaDrive gymnasium id."""
    hidden: Count = 128
    """Width of the hidden layer (Linear(obs, 128)-ReLU-Linear(128, 9))."""


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    if importlib.util.find_spec("metadrive") is None:
        raise ImportError(INSTALL_HINT)
    import metadrive  # noqa: F401  (registers the environments)

    return driving_env(cfg.env_id, flags=["crash", "arrive_dest"], render=render)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden,), activation=nn.ReLU)


RECIPE = Recipe(
    name="metadrive",
    config=Config,
    make_env=make_env,
    make_models=make_models,
    eval_flags=("crash", "arrive_dest"),
)
