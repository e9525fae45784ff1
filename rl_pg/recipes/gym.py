"""REINFORCE on any gymnasium environment with a flat observation vector and discrete
or box actions: the recipe for an id rl_pg has no recipe of its own for::

    rl-pg train gym --env-id Acrobot-v1
    rl-pg train gym --env-id MountainCarContinuous-v0 --threshold 90
    rl-pg play runs/latest

Discrete actions get a categorical policy, box actions a Beta on their bounds (a
Gaussian the environment clips with ``--bounded normal``); a learned V(s) weights the
returns by GAE, with Adam at 1e-3. Several copies of
the environment step as one batch, each update taking a few steps of each (episodes of
any length train from the first update); the returns are bootstrapped where an episode
is cut. Solved at ``--threshold`` (default: the id's own ``reward_threshold`` in
gymnasium's registry, when it has one).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from torchrl.envs import EnvBase

from rl_pg.envs import gym_env
from rl_pg.models import mlp_actor_critic
from rl_pg.training import Count, TrainConfig
from rl_pg.training.recipe import Recipe
from rl_pg.training.settings import BatchedEnvironments


@dataclass
class Config(
    TrainConfig,
    BatchedEnvironments,
    num_envs=16,
    total_frames=500_000,
    batch_mode="segments",
    segment_length=16,
    returns="gae",
    gae_lambda=0.95,
    normalize_advantage=True,
    lr=1e-3,  # Adam's rate held (the KL-set rate let Acrobot's policy collapse)
    max_grad_norm=0.5,
    eval_interval=25_000,
    stop_when_solved=False,
):
    """REINFORCE with GAE and a learned value baseline on a gymnasium id of your choice."""

    env_id: str = ""
    """The gymnasium id to train on (required), e.g. Acrobot-v1. Its package must be
    installed and imported by gymnasium (the classic-control and Box2D ids are)."""
    hidden: Count = 64
    """Width of the two hidden layers of the actor and of the critic."""
    bounded: Literal["beta", "normal", "tanh_normal"] = "beta"
    """Box actions: the policy's distribution on their bounds. A Beta, a Normal the
    environment clips, or a TanhNormal."""
    normalize_observations: bool = True
    """Standardise the observations. Running mean and variance, shared by actor and
    critic: an unknown environment's observations may be on any scale."""

    def __post_init__(self) -> None:
        if not self.env_id:
            raise ValueError(
                "rl-pg train gym needs --env-id: the gymnasium id to train on, e.g. "
                "--env-id Acrobot-v1 (gymnasium.pprint_registry() lists them)."
            )
        if self.threshold is None:  # the registry's own target, when it has one
            self.threshold = _registered_threshold(self.env_id)
        _check_spaces(self.env_id)
        super().__post_init__()


def _registered_threshold(env_id: str) -> float | None:
    import gymnasium

    try:
        spec = gymnasium.spec(env_id)
    except gymnasium.error.Error as err:
        raise ValueError(
            f"--env-id {env_id!r} is not a registered gymnasium id ({err}). "
            f"gymnasium.pprint_registry() lists the installed ones."
        ) from None
    threshold = spec.reward_threshold
    return None if threshold is None else float(threshold)


def _check_spaces(env_id: str) -> None:
    """Refuses, in one line, an id whose observations are not a flat vector or whose
    actions are neither discrete nor a box: this recipe's models could not read them."""
    import gymnasium
    from gymnasium.spaces import Box, Discrete

    try:
        env = gymnasium.make(env_id)
    except gymnasium.error.Error as err:  # e.g. a package it needs is not installed
        raise ValueError(f"--env-id {env_id}: gymnasium cannot make it: {err}") from None
    try:
        observations, actions = env.observation_space, env.action_space
    finally:
        env.close()
    if not (isinstance(observations, Box) and len(observations.shape) <= 1):
        raise ValueError(
            f"--env-id {env_id} observes {observations}, and this recipe's networks read a "
            f"flat vector of numbers (a Box of one dimension). Images, dictionaries and "
            f"discrete observations need models of their own (docs: Composing modules)."
        )
    if not isinstance(actions, (Discrete, Box)):
        raise ValueError(
            f"--env-id {env_id} acts in {actions}, and this recipe's policies choose one "
            f"of n actions (Discrete) or a vector in bounds (Box)."
        )


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    if render or cfg.num_envs == 1:
        return gym_env(cfg.env_id, render=render)
    return gym_env(cfg.env_id, num_envs=cfg.num_envs)


def make_eval_env(cfg: Config) -> EnvBase:
    """The evaluation episodes, played side by side."""
    return gym_env(cfg.env_id, num_envs=cfg.eval_episodes if cfg.eval_episodes > 1 else None)


def make_models(env: EnvBase, cfg: Config):
    if env.full_action_spec[env.action_key].domain == "discrete":  # a categorical policy
        return mlp_actor_critic(
            env, hidden=(cfg.hidden, cfg.hidden), normalize=cfg.normalize_observations
        )
    return mlp_actor_critic(
        env,
        hidden=(cfg.hidden, cfg.hidden),
        bounded=cfg.bounded,
        state_independent_scale=cfg.bounded != "beta",
        normalize=cfg.normalize_observations,
    )


RECIPE = Recipe(
    name="gym",
    config=Config,
    make_env=make_env,
    make_models=make_models,
    make_eval_env=make_eval_env,
)
