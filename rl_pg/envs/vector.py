"""Vectorised gymnasium environments as a TorchRL environment with little per-step cost."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

# TorchRL's own conversion of gymnasium spaces (what GymWrapper uses), so that both
# wrappers give an environment the same specs.
from torchrl.envs.libs.gym import _gym_to_torchrl_spec_transform

__all__ = ["EnvPoolEnv", "VectorGymEnv"]


class VectorGymEnv(EnvBase):
    """A gymnasium ``VectorEnv`` as a TorchRL environment of batch size ``[num_envs]``.

    What TorchRL's ``GymWrapper`` does for vector environments, minus its generality:
    a step hands the actions to gymnasium, wraps the arrays it returns as tensors
    (without copying them) and builds one TensorDict; no ``info`` parsing, no per-step
    type checks, and a partial reset that only replaces the finished environments'
    observations. Around a step of 32 CartPoles (212 µs in gymnasium) it spends 73 µs
    where ``GymWrapper`` spends 281 µs: what matters when the environments themselves
    take microseconds.

    The environments finished at a step are reset alone, by gymnasium's
    ``reset_mask``: the vector environment's own autoreset must be disabled
    (``AutoresetMode.DISABLED``), so that no final observation is lost and no step is
    spent on a reset. Seeding follows ``GymWrapper``: ``set_seed(s)`` resets the
    environments with seeds ``s, s + 1, ...``; later resets continue their generators.
    Both wrappers therefore produce the same trajectories from the same seed and actions.

    Observations: a ``Box`` space is read under ``"observation"``, a ``Dict`` space under
    its own keys. Discrete actions are indices (TorchRL's ``Categorical``).

    Args:
        env (gymnasium.vector.VectorEnv): the environments, with autoreset disabled.

    Keyword Args:
        device (torch.device, optional): where the tensors are put. Defaults to the CPU.

    Examples:
        >>> import gymnasium as gym
        >>> from rl_pg.envs import VectorGymEnv
        >>> envs = gym.make_vec(
        ...     "CartPole-v1", num_envs=4, vectorization_mode="sync",
        ...     vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.DISABLED},
        ... )
        >>> env = VectorGymEnv(envs)
        >>> _ = env.set_seed(0)
        >>> rollout = env.rollout(3)
        >>> rollout.batch_size, rollout["next", "observation"].shape
        (torch.Size([4, 3]), torch.Size([4, 3, 4]))
    """

    def __init__(self, env: gym.vector.VectorEnv, *, device: torch.device | str | None = None):
        if not isinstance(env, gym.vector.VectorEnv):
            raise TypeError(
                f"VectorGymEnv wraps a gymnasium.vector.VectorEnv, got {type(env).__name__}. "
                f"Build one with gymnasium.make_vec(..., vector_kwargs={{'autoreset_mode': "
                f"gymnasium.vector.AutoresetMode.DISABLED}}), or use rl_pg.envs.gym_env."
            )
        self._check_autoreset(env)
        n = env.num_envs
        super().__init__(batch_size=torch.Size([n]), device=device)
        self._env = env
        self._n = n
        spaces, action_space = self._spaces(env)
        if isinstance(spaces, gym.spaces.Box):
            self._obs_keys = ("observation",)
            spaces = {"observation": spaces}
        elif isinstance(spaces, gym.spaces.Dict):
            self._obs_keys = tuple(spaces.keys())
        else:
            raise TypeError(
                f"VectorGymEnv reads Box or Dict observations, got "
                f"{type(spaces).__name__}; wrap the environment with TorchRL's GymWrapper."
            )
        self.observation_spec = Composite(
            {key: self._spec(space) for key, space in spaces.items()}, shape=self.batch_size
        )
        self.action_spec = self._spec(action_space)
        self.reward_spec = Unbounded(shape=(n, 1), device=self.device)
        done = Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=done.clone(), terminated=done.clone(), truncated=done.clone(), shape=(n,)
        )
        # What GymWrapper turns each observation into (e.g. a scalar Box: shape [n, 1]).
        self._formats = {
            key: (self.observation_spec[key].dtype, self.observation_spec[key].shape)
            for key in self._obs_keys
        }
        self._seed: int | None = None

    @staticmethod
    def _check_autoreset(env: gym.vector.VectorEnv) -> None:
        mode = env.metadata.get("autoreset_mode", getattr(env, "autoreset_mode", None))
        if mode != gym.vector.AutoresetMode.DISABLED:
            raise ValueError(
                f"The vector environment resets its environments itself (autoreset mode "
                f"{mode}); VectorGymEnv resets finished environments when TorchRL asks. "
                f"Build it with vector_kwargs={{'autoreset_mode': "
                f"gymnasium.vector.AutoresetMode.DISABLED}}."
            )

    def _spaces(self, env: gym.vector.VectorEnv) -> tuple[gym.Space, gym.Space]:
        """One environment's observation and action spaces."""
        return env.single_observation_space, env.single_action_space

    # The three calls into the vector environment; EnvPoolEnv overrides them.

    def _env_step(self, actions: np.ndarray):
        obs, reward, terminated, truncated, _ = self._env.step(actions)
        return obs, reward, terminated, truncated

    def _env_reset(self, seed: int | None):
        """Resets every environment (with seeds ``seed, seed + 1, ...`` if given)."""
        return self._env.reset(seed=seed)[0]

    def _env_reset_some(self, mask: np.ndarray):
        """Resets the environments where ``mask``; returns every environment's observation."""
        return self._env.reset(options={"reset_mask": mask})[0]

    def _spec(self, space: gym.Space):
        spec = _gym_to_torchrl_spec_transform(
            space, device=self.device, categorical_action_encoding=True
        )
        return spec.expand(self._n, *spec.shape)

    def _observations(self, obs) -> dict[str, torch.Tensor]:
        if len(self._obs_keys) == 1 and not isinstance(obs, dict):
            obs = {self._obs_keys[0]: obs}
        return {
            key: torch.from_numpy(np.asarray(obs[key])).to(dtype).reshape(shape)
            for key, (dtype, shape) in self._formats.items()
        }

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        obs, reward, terminated, truncated = self._env_step(action.detach().cpu().numpy())
        out = self._observations(obs)
        shape = (self._n, 1)
        out["reward"] = torch.from_numpy(np.asarray(reward, dtype=np.float32)).view(shape)
        terminated = torch.from_numpy(np.asarray(terminated, dtype=bool)).view(shape)
        truncated = torch.from_numpy(np.asarray(truncated, dtype=bool)).view(shape)
        out["terminated"], out["truncated"] = terminated, truncated
        out["done"] = terminated | truncated
        if self.device is not None and self.device.type != "cpu":
            out = {key: value.to(self.device, non_blocking=True) for key, value in out.items()}
        return TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)

    def _step_proc_data(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        # `_step` already writes every done entry and the reward in their spec's shape:
        # nothing to complete (EnvBase's version checks and fills them at each step).
        if self.run_type_checks:
            return super()._step_proc_data(next_tensordict)
        return next_tensordict

    def _step_and_maybe_reset(
        self, tensordict: TensorDictBase
    ) -> tuple[TensorDictBase, TensorDictBase]:
        # EnvBase's version, with the partial reset done here: gymnasium resets the
        # finished environments and returns every observation, so the next root
        # needs its observations replaced and its done flags cleared, not TorchRL's
        # generic reset (reset keys, spec checks, a `where` over every entry).
        tensordict = self.step(tensordict)
        next_root = self._step_mdp(tensordict)
        if self._post_step_mdp_hooks is not None:
            tensordict, next_root = self._post_step_mdp_hooks(tensordict, next_root)
        done = next_root.get("done")
        if done.any():
            obs = self._env_reset_some(done.reshape(self._n).cpu().numpy())
            for key, value in self._observations(obs).items():
                next_root.set(key, value.to(done.device))
            for key in ("done", "terminated", "truncated"):
                next_root.set(key, torch.zeros_like(done))
        return tensordict, next_root

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        if reset is not None and not reset.all():
            obs = self._env_reset_some(reset.reshape(self._n).cpu().numpy())
        else:
            seed, self._seed = self._seed, None
            obs = self._env_reset(seed)
        out = self._observations(obs)
        for key in ("done", "terminated", "truncated"):
            out[key] = torch.zeros(self._n, 1, dtype=torch.bool, device=self.device)
        return TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed
        self.reset()

    def close(self, *, raise_if_closed: bool = True) -> None:
        super().close(raise_if_closed=raise_if_closed)
        self._env.close()


class EnvPoolEnv(VectorGymEnv):
    """`EnvPool <https://envpool.readthedocs.io>`_'s C++ environments as a TorchRL
    environment of batch size ``[num_envs]``: a [`VectorGymEnv`][rl_pg.envs.VectorGymEnv]
    whose environments step in EnvPool's own threads.

    Same data layout and reset rules: a finished environment is reset at once (EnvPool's
    ``reset(env_ids)``), so its final observation is kept and no step is spent on
    EnvPool's own next-step reset. EnvPool seeds its environments when it builds them:
    ``set_seed(s)`` rebuilds the pool with seed ``s``. Specs come from gymnasium's
    registration of ``task_id`` when there is one (EnvPool declares some observation
    bounds wrongly, e.g. LunarLander's), else from EnvPool.

    Args:
        task_id (str): an EnvPool task, e.g. ``"CartPole-v1"``.
        num_envs (int): environments in the pool.

    Keyword Args:
        device (torch.device, optional): where the tensors are put. Defaults to the CPU.
        **kwargs: passed to ``envpool.make_gymnasium`` (e.g. ``num_threads``).

    Raises:
        ImportError: EnvPool is not installed (``pip install "rl_pg[envpool]"``).
    """

    def __init__(
        self,
        task_id: str,
        num_envs: int,
        *,
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
        self._task_id = task_id
        self._make = lambda seed: envpool.make_gymnasium(
            task_id, num_envs=num_envs, seed=seed, **kwargs
        )
        self._last_obs = None
        super().__init__(self._make(0), device=device)

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
        obs, reward, terminated, truncated, _ = self._env.step(actions)
        self._last_obs = obs
        return obs, reward, terminated, truncated

    def _env_reset(self, seed: int | None):
        if seed is not None:
            self._env.close()
            self._env = self._make(seed)
        self._last_obs = self._env.reset()[0]
        return self._last_obs

    def _env_reset_some(self, mask: np.ndarray):
        ids = np.flatnonzero(mask)
        fresh = self._env.reset(ids)[0]
        obs = self._last_obs.copy()
        obs[ids] = fresh
        self._last_obs = obs
        return obs
