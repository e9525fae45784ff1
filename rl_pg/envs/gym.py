"""Gymnasium environments the way rl_pg's recipes use them."""

from __future__ import annotations

from collections.abc import Sequence

from torchrl.envs import EnvBase, GymEnv, TransformedEnv

from rl_pg.discretize import DiscretizeAction
from rl_pg.envs.info import InfoFlags

__all__ = ["DRIVING_ACTIONS", "driving_env", "gym_env"]

DRIVING_ACTIONS = [[x, y] for x in (1.0, 0.0, -1.0) for y in (0.6, 0.0, -0.6)]
"""The SPEC's 9 driving actions: (x, y), x in {+1, 0, -1}, y in {+0.6, 0, -0.6}, index 3i + j."""


def gym_env(env_id: str, *, render: bool = False, **kwargs) -> GymEnv:
    """``GymEnv`` with index (not one-hot) discrete actions, and frames when ``render``.

    Keyword Args:
        render (bool): add the rendered frames under ``"pixels"`` (for recordings).
            Defaults to ``False``.
        **kwargs: passed to ``gymnasium.make``.

    Examples:
        >>> from rl_pg.envs import gym_env
        >>> type(gym_env("CartPole-v1").action_spec).__name__
        'Categorical'
    """
    if render:
        kwargs.update(from_pixels=True, pixels_only=False)
    return GymEnv(env_id, categorical_action_encoding=True, **kwargs)


def driving_env(
    env_id: str, *, flags: Sequence[str] = (), render: bool = False, **kwargs
) -> EnvBase:
    """A driving simulator whose ``[acceleration, steering]`` action is one of the SPEC's 9.

    Keyword Args:
        flags (sequence of str): boolean ``info`` entries to expose (e.g. ``"crashed"``).
            Defaults to ``()``.
        render (bool): add frames under ``"pixels"``. Defaults to ``False``.
        **kwargs: passed to ``gymnasium.make``.
    """
    env = gym_env(env_id, render=render, **kwargs)
    if flags:
        env.set_info_dict_reader(InfoFlags(flags))
    return TransformedEnv(env, DiscretizeAction(actions=DRIVING_ACTIONS))
