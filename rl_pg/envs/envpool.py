"""EnvPool's C++ environments as a TorchRL environment: ``VectorGymEnv``'s batch,
stepped by EnvPool's threads, in one pool or in groups that step in turn."""

from __future__ import annotations

import os
import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

# TorchRL's own conversion of gymnasium spaces (what GymWrapper uses), so that both
# wrappers give an environment the same specs.
from rl_pg.envs.vector import VectorGymEnv

__all__ = ["BOX_CAST_WARNING", "EnvPoolEnv"]


class EnvPoolEnv(VectorGymEnv):
    """`EnvPool <https://envpool.readthedocs.io>`_'s C++ environments as a TorchRL
    environment of batch size ``[num_envs]``: a [`VectorGymEnv`][rl_pg.envs.VectorGymEnv]
    whose environments step in EnvPool's own threads.

    Same data layout and reset rules: a finished environment is reset at once (EnvPool's
    ``reset(env_ids)``), so its final observation is kept and no step is spent on
    EnvPool's own next-step reset. EnvPool seeds its environments when it builds them:
    ``set_seed(s)`` rebuilds the pool with seed ``s`` (environment ``i`` gets ``s + i``).
    Specs come from gymnasium's registration of ``task_id`` when there is one (EnvPool
    declares some observation bounds wrongly, e.g. LunarLander's), else from EnvPool.

    With ``groups=2`` the environments are two pools (the first ``ceil(num_envs / 2)``
    environments, then the rest), seeded as the one pool would be (so ``step`` gives the
    same trajectories), and each group can be stepped on its own without waiting for it:
    ``step_send(tensordict, group)`` hands the group's actions to EnvPool's threads and
    returns at once, ``step_recv(group)`` waits for that step. A
    [`DoubleBufferedCollector`][rl_pg.collectors.DoubleBufferedCollector] acts on one
    group while the other steps.

    Args:
        task_id (str): an EnvPool task, e.g. ``"CartPole-v1"``.
        num_envs (int): environments in all.

    Keyword Args:
        groups (int): 1, or 2 for two separately steppable halves (``num_envs`` >= 2),
            which share the cores' threads (unless ``num_threads`` is given).
            Defaults to 1.
        device (torch.device, optional): where the tensors are put. Defaults to the CPU.
        **kwargs: passed to ``envpool.make_gymnasium`` (e.g. ``num_threads``).

    Raises:
        ImportError: EnvPool is not installed (``pip install "rl_pg[envpool]"``).

    Examples:
        >>> import torch
        >>> from rl_pg.envs import EnvPoolEnv
        >>> env = EnvPoolEnv("CartPole-v1", num_envs=4, groups=2)
        >>> root = env.reset()
        >>> first = root[:2].set("action", torch.zeros(2, dtype=torch.long))
        >>> env.step_send(first, 0)           # group 0 steps in EnvPool's threads...
        >>> step, next_root = env.step_recv(0)  # ...until this returns its step
        >>> step["next", "reward"].shape, next_root.batch_size
        (torch.Size([2, 1]), torch.Size([2]))
        >>> env.close()
    """

    def __init__(
        self,
        task_id: str,
        num_envs: int,
        *,
        groups: int = 1,
        device: torch.device | str | None = None,
        **kwargs: Any,
    ) -> None:
        try:
            import envpool
        except ImportError as err:
            raise ImportError(
                'EnvPoolEnv needs EnvPool: pip install -c constraints.txt -e ".[envpool]" '
                "(Linux wheels; gymnasium's vector environments need nothing more)."
            ) from err
        if task_id not in envpool.list_all_envs():
            raise ValueError(
                f"EnvPool has no task {task_id!r}; among its classic tasks: "
                f"{[t for t in envpool.list_all_envs() if '/' not in t][:12]}..."
            )
        if groups not in (1, 2) or num_envs < groups:
            raise ValueError(
                f"groups must be 1, or 2 with at least 2 environments (two halves), got "
                f"groups={groups!r} for num_envs={num_envs}."
            )
        self._task_id = task_id
        if groups > 1 and "num_threads" not in kwargs:
            # EnvPool gives each pool a thread per core; two pools would run twice as
            # many threads as cores, and each step's send wakes more of them.
            kwargs["num_threads"] = max(1, len(os.sched_getaffinity(0)) // groups)
        self.group_sizes = [(num_envs + g) // groups for g in reversed(range(groups))]
        """Environments in each group, in order (the larger first)."""
        firsts = [sum(self.group_sizes[:g]) for g in range(groups)]
        self._make = lambda seed: _Pools(
            [
                envpool.make_gymnasium(task_id, num_envs=size, seed=seed + first, **kwargs)
                for size, first in zip(self.group_sizes, firsts, strict=True)
            ]
        )
        self._sent: list[TensorDictBase | None] = [None] * groups
        super().__init__(self._make(0), device=device)

    @property
    def groups(self) -> int:
        """Number of separately steppable groups of environments."""
        return len(self._env.pools)

    @staticmethod
    def _check_autoreset(env) -> None:
        pass  # EnvPool resets at the step after an end; resetting at once pre-empts it

    def _spaces(self, env):
        if self._task_id in gym.registry:
            reference = gym.make(self._task_id)
            spaces = reference.observation_space, reference.action_space
            reference.close()
            if spaces[0].shape == env.single_observation_space.shape:
                return spaces
        return env.single_observation_space, env.single_action_space

    def _env_step(self, actions: np.ndarray):
        return self._env.step(actions)

    def _env_reset(self, seed: int | list[int] | None):
        if isinstance(seed, list):
            raise ValueError(
                "EnvPool seeds its environments when it builds the pool (environment i "
                "with seed + i): it cannot reset them with a seed each. Use the "
                "gymnasium backend (rl_pg.envs.gym_env(..., backend='gymnasium')) for "
                "environments reset with seeds of your choice."
            )
        if seed is not None:
            self._env.close()
            self._env = self._make(seed)
            self._sent = [None] * self.groups
        return self._env.reset()

    def _env_reset_some(self, mask: np.ndarray):
        return self._env.reset_some(mask)

    def step_send(self, tensordict: TensorDictBase, group: int) -> None:
        """Hands ``tensordict``'s actions (of group ``group``'s environments, batch size
        ``[num_envs / groups]``) to EnvPool and returns while they step."""
        self.send_action(tensordict.get(self.action_key), group)
        self._sent[group] = tensordict

    def step_recv(self, group: int) -> tuple[TensorDictBase, TensorDictBase]:
        """Waits for group ``group``'s step; returns what ``step_and_maybe_reset`` returns
        for that group: the tensordict sent with its ``"next"`` entries, and the next
        root, where the environments that finished are already reset."""
        sent = self._sent[group]
        if sent is not None and not isinstance(sent, TensorDictBase):
            raise RuntimeError(
                f"Group {group}'s step was sent with send_action: receive it with "
                f"recv_tensors({group})."
            )
        step, observations = self.recv_tensors(group)
        next_td = TensorDict._new_unsafe(
            step, batch_size=torch.Size([len(step["reward"])]), device=self.device
        )
        sent.set("next", next_td)
        next_root = next_td.exclude("reward")
        if step["done"].any():
            self._write_restarted(next_root, observations)
        return sent, next_root

    def send_action(self, action: torch.Tensor, group: int) -> None:
        """Hands group ``group``'s ``action`` (its environments' rows) to EnvPool and
        returns while they step: ``step_send`` without a TensorDict."""
        if self._sent[group] is not None:
            raise RuntimeError(
                f"Group {group} is already stepping: call step_recv({group}) or "
                f"recv_tensors({group}) before sending it another action."
            )
        self._env.send(group, action.numpy(force=True))
        self._sent[group] = action

    def recv_tensors(self, group: int) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Waits for group ``group``'s step; returns what ``step_tensors`` returns for
        that group: the ``"next"`` entries, and the next root's observations (the
        environments that finished already reset)."""
        if self._sent[group] is None:
            raise RuntimeError(f"Group {group} is not stepping: call step_send first.")
        self._sent[group] = None
        return self._step_and_roots(
            self._env.recv(group), lambda mask: self._env.reset_some(mask, group)
        )


# EnvPool builds its float32 Boxes from float64 bounds, and gymnasium warns of the cast
# for every pool: the bounds are the task's own, nothing for a user to fix.
BOX_CAST_WARNING = ".*Box .* precision lowered"


class _Pools(gym.vector.VectorEnv):
    """One or more EnvPool pools as one vector environment (the groups of an
    [`EnvPoolEnv`][rl_pg.envs.EnvPoolEnv]), remembering each pool's last observations so
    that a partial reset can return every environment's."""

    def __init__(self, pools: list) -> None:
        self.pools = pools
        self.sizes = [pool.config["num_envs"] for pool in pools]
        self.num_envs = sum(self.sizes)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", BOX_CAST_WARNING, UserWarning)
            # Read from every pool: each builds them once, at the first reading (else at
            # its first reset, outside this filter).
            spaces = [(pool.single_observation_space, pool.single_action_space) for pool in pools]
        self.single_observation_space, self.single_action_space = spaces[0]
        self.metadata = {}
        self._ids = [np.arange(size, dtype=np.int32) for size in self.sizes]
        self._bounds = np.cumsum(self.sizes)[:-1]
        self._last: list[np.ndarray | None] = [None] * len(pools)
        self._direct = [_direct_layout(pool) for pool in pools]
        self._checked = [False] * len(pools)

    def send(self, group: int, actions: np.ndarray) -> None:
        pool, direct = self.pools[group], self._direct[group]
        if direct is None or not self._checked[group]:
            pool.send(actions, self._ids[group])  # checks the actions' dtype and shape once
            self._checked[group] = True
            return
        ids = self._ids[group]
        pool._send([ids, ids, np.ascontiguousarray(actions, dtype=direct[0])])  # as _from

    def recv(self, group: int):
        direct = self._direct[group]
        if direct is None:
            obs, reward, terminated, truncated, _ = self.pools[group].recv()
        else:
            state = self.pools[group]._recv()
            obs, reward, done, truncated = (state[i] for i in direct[1])
            terminated = done & ~truncated  # as EnvPool's gymnasium API derives it
        self._last[group] = obs
        return obs, reward, terminated, truncated

    def step(self, actions: np.ndarray):
        if len(self.pools) == 1:  # the common case: no splitting and joining per step
            self.send(0, actions)
            return self.recv(0)
        parts = np.split(actions, self._bounds)
        for group, part in enumerate(parts):
            self.send(group, part)
        steps = [self.recv(group) for group in range(len(self.pools))]
        return tuple(np.concatenate(field) for field in zip(*steps, strict=True))

    def reset(self):
        self._last = [pool.reset()[0] for pool in self.pools]
        return self._last[0] if len(self.pools) == 1 else np.concatenate(self._last)

    def reset_some(self, mask: np.ndarray, group: int | None = None) -> np.ndarray:
        """Resets the environments where ``mask`` (of all groups, or of ``group``'s);
        returns the observations of the same environments as ``mask``."""
        groups = range(len(self.pools)) if group is None else [group]
        masks = [mask] if group is not None else np.split(mask, self._bounds)
        for g, part in zip(groups, masks, strict=True):
            ids = np.flatnonzero(part).astype(np.int32)
            if len(ids):
                obs = self._last[g].copy()
                obs[ids] = self.pools[g].reset(ids)[0]
                self._last[g] = obs
        return (
            self._last[groups[0]]
            if len(groups) == 1
            else np.concatenate([self._last[g] for g in groups])
        )

    def close(self, **kwargs) -> None:
        for pool in self.pools:
            pool.close()


def _direct_layout(pool) -> tuple[np.dtype, list[int]] | None:
    """How to step ``pool`` through EnvPool's own arrays, or None to use its API.

    EnvPool's ``send`` and ``recv`` wrap two C++ calls that take and give a list of
    arrays (``_send``, ``_recv``) in Python that builds dictionaries, infers multiplayer
    ids and unflattens the info tree at every step, which a double-buffered loop pays
    twice per step on the thread that also runs the policy. For a single-player pool
    with one action array and an ``"obs"`` array this gives the action's dtype and the
    positions of the observation, reward, done and truncation arrays in ``_recv``'s
    list; any other layout (or an EnvPool that names things otherwise) keeps the API.
    The first ``send`` of each pool still goes through the API, which checks the
    actions' dtype and shape once.
    """
    try:
        action_keys = list(pool._spec._action_keys)
        action_dtype = np.dtype(pool._spec._action_spec[-1][0])
        state_keys = list(pool._state_keys)
        players = pool.config.get("max_num_players", 1)
    except (AttributeError, IndexError, TypeError):
        return None
    wanted = ("obs", "reward", "done", "trunc")
    if (
        players != 1
        or action_keys[:2] != ["env_id", "players.env_id"]
        or len(action_keys) != 3
        or not all(key in state_keys for key in wanted)
        or not all(callable(getattr(pool, name, None)) for name in ("_send", "_recv"))
    ):
        return None
    return action_dtype, [state_keys.index(key) for key in wanted]
