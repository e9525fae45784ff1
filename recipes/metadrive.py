"""The original driving set-up on MetaDrive (optional backend; docs/recipes/metadrive.md).

MetaDrive-validation-v0: a 259-dimensional observation in [0, 1] and a
Box(-1, 1, (2,)) action, discretised into the 9 joint driving actions; gamma 0.75,
entropy bonus 0.1, 200 episodes per update, Adam 1e-4, a checkpoint every 100
updates. MetaDrive downloads its assets from the internet on first use, so it is not
installed with rl_pg; this recipe stops with instructions when it is missing.

    pip install metadrive-simulator   # then run it once with network access
    python recipes/metadrive.py
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from torch import nn
from torchrl.envs import EnvBase

from rl_pg.envs import driving_env
from rl_pg.models import mlp_actor_critic
from rl_pg.training import Count, TrainConfig, train
from rl_pg.training.cli import parse_config
from rl_pg.training.console import format_summary
from rl_pg.training.interrupt import exit_quietly_on_interrupt

INSTALL_HINT = (
    "MetaDrive is not installed. It is an optional backend because it downloads its "
    "assets from the internet on first use: `pip install metadrive-simulator`, then run "
    "`python -m metadrive.pull_asset` on a machine with network access. The same driving "
    "set-up runs offline on highway-env: `python recipes/highway.py`."
)


@dataclass
class Config(TrainConfig):
    """REINFORCE on MetaDrive with the driving experiment's hyper-parameters."""

    env_id: str = "MetaDrive-validation-v0"
    """MetaDrive gymnasium id."""
    hidden: Count = 128
    """Width of the hidden layer (Linear(obs, 128)-ReLU-Linear(128, 9))."""
    total_frames: int = 2_000_000
    """Agent steps to train for (at most)."""
    episodes_per_batch: int = 200
    """Complete episodes per update."""
    gamma: float = 0.75
    """Discount factor."""
    entropy_coeff: float = 0.1
    """Entropy bonus weight."""
    lr: float = 1e-4
    """Learning rate."""
    checkpoint_interval: int = 100
    """Updates between checkpoints."""
    eval_interval: int = 50_000
    """Agent steps between greedy evaluations."""


def _require_metadrive():
    """Imports the MetaDrive package (which registers its gymnasium ids).

    This file is also called ``metadrive``: the search skips the recipes folder so
    that the simulator, not this recipe, is found.
    """
    recipes = Path(__file__).resolve().parent
    path = [p for p in sys.path if Path(p or ".").resolve() != recipes]
    spec = importlib.machinery.PathFinder.find_spec("metadrive", path)
    if spec is None or spec.submodule_search_locations is None:
        raise ImportError(INSTALL_HINT)
    module = sys.modules.get("metadrive")
    if module is None or getattr(module, "__spec__", None) != spec:
        module = importlib.util.module_from_spec(spec)
        sys.modules["metadrive"] = module
        spec.loader.exec_module(module)
    return module


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    _require_metadrive()
    return driving_env(cfg.env_id, flags=["crash", "arrive_dest"], render=render)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden,), activation=nn.ReLU)


def main(cfg: Config) -> dict:
    _require_metadrive()
    return train(
        cfg,
        recipe="metadrive",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
        eval_flags=("crash", "arrive_dest"),
    )


if __name__ == "__main__":
    with exit_quietly_on_interrupt():
        print(format_summary(main(parse_config(Config))))
