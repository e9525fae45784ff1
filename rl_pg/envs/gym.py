"""Gymnasium environments the way rl_pg's recipes use them."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import gymnasium as gym

# TorchRL imports this module the first time an environment renders, and it keeps the
# error of its failed `import gym` as a module global: that error's frames hold every
# frame that called the import, and with them the caller's environments, alive to the
# end of the process (a simulator's bindings then report them leaked at exit). Imported
# here, the frames it keeps are imports'.
import torchrl.envs.libs.utils  # noqa: F401
from torchrl.envs import EnvBase, GymEnv, TransformedEnv

from rl_pg._checks import check_int
from rl_pg.discretize import DiscretizeAction
from rl_pg.envs.envpool import EnvPoolEnv
from rl_pg.envs.info import InfoFlags
from rl_pg.envs.vector import VectorGymEnv

__all__ = ["DRIVING_ACTIONS", "driving_env", "gym_env"]

DRIVING_ACTIONS = [[x, y] for x in (1.0, 0.0, -1.0) for y in (0.6, 0.0, -0.6)]
"""The 9 driving actions: (x, y), x in {+1, 0, -1}, y in {+0.6, 0, -0.6}, index 3i + j."""


def gym_env(
    env_id: str,
    *,
    num_envs: int | None = None,
    render: bool = False,
    backend: str = "gymnasium",
    **kwargs: Any,
) -> EnvBase:
    """A gymnasium environment as a TorchRL env, with index (not one-hot) discrete actions.

    With ``num_envs`` the environments are stepped together in this process by
    gymnasium's ``SyncVectorEnv`` (batch size ``[num_envs]``) behind a
    [`VectorGymEnv`][rl_pg.envs.VectorGymEnv]. Its auto-reset is disabled: the finished
    environments are reset when TorchRL asks, so no final observation is lost and no
    step is spent on resets. TorchRL's own
    ``GymEnv(num_envs=N)`` runs one sub-process per environment instead, which costs
    more than it saves for cheap environments such as CartPole.

    Keyword Args:
        num_envs (int, optional): step this many copies as one batched environment.
            Defaults to ``None`` (one environment, batch size ``[]``).
        render (bool): add the rendered frames under ``"pixels"`` (for recordings; one
            environment only). Defaults to ``False``.
        backend (str): ``"gymnasium"``, or ``"envpool"`` to step ``num_envs`` copies in
            EnvPool's C++ threads instead (an [`EnvPoolEnv`][rl_pg.envs.EnvPoolEnv];
            ``pip install "rl_pg[envpool]"``). Defaults to ``"gymnasium"``.
        **kwargs: passed to ``gymnasium.make``; with EnvPool, to
            [`EnvPoolEnv`][rl_pg.envs.EnvPoolEnv] (e.g. ``groups=2``) and
            ``envpool.make_gymnasium``.

    Examples:
        >>> from rl_pg.envs import gym_env
        >>> type(gym_env("CartPole-v1").action_spec).__name__
        'Categorical'
        >>> gym_env("CartPole-v1", num_envs=8).batch_size
        torch.Size([8])
    """
    if backend not in ("gymnasium", "envpool"):
        raise ValueError(f"backend must be 'gymnasium' or 'envpool', got {backend!r}.")
    if "groups" in kwargs and backend != "envpool":
        raise ValueError(
            "groups splits an EnvPool pool into halves that step in turn: use "
            "backend='envpool' with it (gymnasium's vector environments step as one)."
        )
    if backend == "envpool":
        if num_envs is None or render:
            raise ValueError(
                "backend='envpool' steps batches of environments and renders nothing: give "
                "num_envs and leave render=False (use gymnasium for one watched episode)."
            )
        return EnvPoolEnv(env_id, check_int("num_envs", num_envs, low=1), **kwargs)
    if num_envs is None:
        if render:
            kwargs.update(from_pixels=True, pixels_only=False)
            # Frames are drawn off screen: SDL (pygame) needs no display, and probing
            # for one prints errors on a machine without ("XDG_RUNTIME_DIR is invalid").
            os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        if "frameskip" in kwargs:
            # TorchRL's GymEnv overwrites gymnasium's `frameskip` with its own
            # `frame_skip` (default 1): pass it under TorchRL's name, which reaches
            # gymnasium.make as frameskip, so that one env skips like the batched ones.
            kwargs["frame_skip"] = kwargs.pop("frameskip")
        return GymEnv(env_id, categorical_action_encoding=True, **kwargs)
    if render:
        raise ValueError("render=True needs a single environment: leave num_envs=None.")
    num_envs = check_int("num_envs", num_envs, low=1)
    vector_env = gym.make_vec(
        env_id,
        num_envs=num_envs,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.DISABLED},
        **kwargs,
    )
    return VectorGymEnv(vector_env)


def driving_env(
    env_id: str, *, flags: Sequence[str] = (), render: bool = False, **kwargs: Any
) -> EnvBase:
    """A driving simulator whose ``[acceleration, steering]`` action is one of ``DRIVING_ACTIONS``.

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
