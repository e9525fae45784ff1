"""Segment collectors: synchronous with little work per step, or overlapping the
environments' step with the policy's; both strictly on-policy (whole-episode batches
over them: [`EpisodeCollector`][rl_pg.episode_collector.EpisodeCollector])."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rl_pg.envs.envpool import EnvPoolEnv
from rl_pg.envs.vector import VectorGymEnv
from rl_pg.episode_collector import EpisodeCollector  # noqa: F401 (its import path before)
from rl_pg.lean import LeanCategoricalPolicy, hooked, hooked_globally
from rl_pg.segments import cleared_flags, observations_of, root_of, segment_of

__all__ = ["DoubleBufferedCollector", "SegmentCollector"]


class _Segments:
    """What both collectors share: the checks, seeding, iteration and frame count.
    A subclass collects one batch in ``_collect(horizon)``."""

    def __init__(
        self,
        env: EnvBase,
        policy: TensorDictModuleBase,
        frames_per_batch: int,
        *,
        total_frames: int = -1,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        device: torch.device | str | None = None,
    ) -> None:
        num_envs = env.batch_size.numel()  # 1 for an environment of batch size []
        if frames_per_batch <= 0 or frames_per_batch % num_envs:
            raise ValueError(
                f"frames_per_batch must be a positive multiple of the {num_envs} "
                f"environments (every environment steps as often), got {frames_per_batch}."
            )
        self.env = env
        self.policy = policy
        self.frames_per_batch = frames_per_batch
        self.total_frames = total_frames
        self.exploration_type = exploration_type
        self.device = None if device is None else torch.device(device)
        if self.device == (env.device or torch.device("cpu")):
            self.device = None  # no copies
        # Where the environment hands back plain tensors, the policy may act on them: a
        # lean policy that writes the environment's action from the observations alone,
        # on their device (a subclass says whether the environment does).
        self._on_tensors = (
            type(policy) is LeanCategoricalPolicy
            and self.device is None
            and policy.action_key == env.action_key
            and policy.acts_on(env.observation_spec.keys())
        )
        self._frames = 0
        self._reset_kwargs: dict = {}

    def _reset_env(self) -> TensorDictBase:
        """A reset of every environment, with the arguments ``reset`` was given."""
        kwargs, self._reset_kwargs = self._reset_kwargs, {}
        return self.env.reset(**kwargs)

    def set_seed(self, seed: int) -> int:
        """Seeds the environments (they are reset with it at the next batch)."""
        self.env.set_seed(seed)
        self.reset()
        return seed

    def reset(self, **kwargs) -> None:
        """Resets every environment: the next batch starts new episodes. The keyword
        arguments go to the environment's ``reset`` (as TorchRL's ``Collector.reset``
        passes them), e.g. ``seed=[...]``, one seed per environment."""
        self._reset_kwargs = kwargs
        self._forget()

    def _forget(self) -> None:
        """Drops where the environments stand: the next batch resets them."""
        raise NotImplementedError

    def __iter__(self) -> Iterator[TensorDictBase]:
        while self.total_frames < 0 or self._frames < self.total_frames:
            yield self.next()

    def next(self) -> TensorDictBase:
        """Collects one batch."""
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            batch = self._collect(self.frames_per_batch // self.env.batch_size.numel())
        self._frames += self.frames_per_batch
        return batch if self.device is None else batch.to(self.device)

    def _collect(self, horizon: int) -> TensorDictBase:
        raise NotImplementedError

    def _policy_at(
        self, observations: dict, clear: torch.Tensor, size: torch.Size
    ) -> TensorDictBase | dict:
        """A root of batch size ``size`` (``observations`` and the cleared done flags)
        with the policy's outputs: a dict of tensors where the policy acts on them, else
        a TensorDict."""
        if self._on_tensors and not (hooked(self.policy) or hooked_globally()):
            root = {**observations, "done": clear, "terminated": clear, "truncated": clear}
            if self.policy.act(root) is not None:
                return root
        return self._act(root_of(observations, clear, size, self.env.device))

    def _act(self, root: TensorDictBase) -> TensorDictBase:
        """The policy's outputs at ``root`` (on the policy's device, if it has one)."""
        return self.policy(root if self.device is None else root.to(self.device))

    def _action(self, root: TensorDictBase) -> torch.Tensor:
        """The action the policy wrote into ``root``."""
        action = root.get(self.env.action_key, None)
        if action is None:
            raise KeyError(
                f"The policy wrote no {self.env.action_key!r} entry (it wrote "
                f"{sorted(map(str, root.keys(True, True)))}): the environment steps on the "
                f"policy's action. Give the policy that out_key (a ProbabilisticActor's "
                f"out_keys=[{self.env.action_key!r}])."
            )
        return action

    def state_dict(self) -> dict:
        """The frames collected so far (as TorchRL's collectors report them)."""
        return {"frames": self._frames}

    def shutdown(self) -> None:
        """Closes the environments."""
        if not self.env.is_closed:
            self.env.close()


class SegmentCollector(_Segments):
    """Segments of experience from a batched environment, stepped synchronously with as
    little work per step as the environment allows.

    The batches are those of TorchRL's ``Collector`` on the same environment and policy
    (``Collector(env, policy, frames_per_batch, track_traj_ids=False)``): the same
    entries, and with the same seeds and random stream the same values, sampled actions
    included. What differs is the work around each step. For a
    [`VectorGymEnv`][rl_pg.envs.VectorGymEnv] or a one-group
    [`EnvPoolEnv`][rl_pg.envs.EnvPoolEnv] the environment hands back plain tensors
    (``step_tensors``) and the batch is built once, at its end; any other environment is
    stepped by its ``step_and_maybe_reset``. A
    [`LeanCategoricalPolicy`][rl_pg.lean.LeanCategoricalPolicy] (what
    [`lean_policy`][rl_pg.lean.lean_policy] makes of the recipes' categorical actors) then
    acts on those tensors too, without a TensorDict per step. For environments that take
    microseconds a step, that work is what a training loop over TorchRL's collector
    spends beyond a hand-written one.

    Each batch holds ``frames_per_batch / num_envs`` consecutive steps of every
    environment, batch size ``[*env.batch_size, T]`` (time last), and the environments
    carry on from where the last batch stopped.

    Args:
        env (EnvBase): the environments (one environment: batch size ``[]``).
        policy (TensorDictModuleBase): reads the environment's observations, writes its
            action (and whatever else it outputs, stored in the batch).
        frames_per_batch (int): steps per batch, a multiple of ``env.batch_size.numel()``.

    Keyword Args:
        total_frames (int): stop after this many steps (-1: never). Defaults to -1.
        exploration_type (ExplorationType): how the policy acts while collecting.
            Defaults to sampling (``ExplorationType.RANDOM``), as TorchRL's collectors.
        device (torch.device, optional): where the policy runs and the batches are
            returned. Defaults to the environment's device (the CPU).

    Examples:
        >>> import torch
        >>> from rl_pg.collectors import SegmentCollector
        >>> from rl_pg.envs import gym_env
        >>> from rl_pg.models import mlp_actor
        >>> env = gym_env("CartPole-v1", num_envs=4)
        >>> actor = mlp_actor(env, hidden=(16,))
        >>> collector = SegmentCollector(env, actor, frames_per_batch=32, total_frames=64)
        >>> [batch.batch_size for batch in collector]
        [torch.Size([4, 8]), torch.Size([4, 8])]
        >>> collector.shutdown()
    """

    def __init__(self, env: EnvBase, policy: TensorDictModuleBase, frames_per_batch: int, **kwargs):
        super().__init__(env, policy, frames_per_batch, **kwargs)
        # Exactly our vector environments: a subclass may step otherwise, and a
        # TransformedEnv passes its base's step_tensors on but would skip its transforms.
        self._lean = type(env) in (VectorGymEnv, EnvPoolEnv) and getattr(env, "groups", 1) == 1
        self._on_tensors = self._on_tensors and self._lean
        self._root: TensorDictBase | None = None
        self._observations: dict[str, torch.Tensor] | None = None

    def _forget(self) -> None:
        self._root = self._observations = None

    def _collect(self, horizon: int) -> TensorDictBase:
        if not self._lean:
            root = self._root if self._root is not None else self._reset_env()
            steps = []
            for _ in range(horizon):
                step, root = self.env.step_and_maybe_reset(self._act(root))
                steps.append(step)
            self._root = root
            return torch.stack(steps, dim=len(self.env.batch_size))
        env = self.env
        if self._observations is None:
            self._observations = observations_of(env, self._reset_env())
        observations, clear = self._observations, cleared_flags(env.batch_size, env.device)
        roots, nexts = [], []
        for _ in range(horizon):
            root = self._policy_at(observations, clear, env.batch_size)
            step, observations = env.step_tensors(self._action(root))
            roots.append(root)
            nexts.append(step)
        self._observations = observations
        return segment_of(roots, nexts, env.batch_size, env.device)


class DoubleBufferedCollector(_Segments):
    """Segments of experience from two groups of environments, one group stepping while
    the policy acts on the other (the double-buffered sampling of Sample Factory,
    Petrenko et al. 2020).

    A synchronous collector waits for all the environments, then for the policy, in
    turn. Here the environments are split in two groups that step without holding the
    GIL (an [`EnvPoolEnv`][rl_pg.envs.EnvPoolEnv] with ``groups=2``: EnvPool's C++
    threads): while group 0 steps, the policy acts on group 1's observations and hands
    its actions over, and the other way round, so on two or more cores most of the
    environments' time is hidden behind the policy's. It stays strictly on-policy: every
    action of a batch comes from the same policy (the one the caller updates between
    batches), and no step is taken ahead across a batch boundary. With the same seeds and
    a deterministic policy the batches are those of TorchRL's ``Collector`` on the same
    environment; a stochastic policy draws its actions in another order, so the batches
    have the same distribution but not the same values.

    Each batch holds ``frames_per_batch / num_envs`` consecutive steps of every
    environment, batch size ``[num_envs, T]`` (time last) with the entries TorchRL's
    ``Collector`` writes (the root, the policy's outputs and ``"next"``), and the
    environments carry on from where the last batch stopped.

    Args:
        env (EnvBase): environments in two groups: ``env.groups == 2``, their sizes
            ``env.group_sizes`` and the methods ``step_send(tensordict, group)`` and
            ``step_recv(group)`` (see
            [`EnvPoolEnv`][rl_pg.envs.EnvPoolEnv]).
        policy (TensorDictModuleBase): reads the environment's observations, writes its
            action (and whatever else it outputs, stored in the batch).
        frames_per_batch (int): steps per batch, a multiple of ``env.batch_size[0]``.

    Keyword Args:
        total_frames (int): stop after this many steps (-1: never). Defaults to -1.
        exploration_type (ExplorationType): how the policy acts while collecting.
            Defaults to sampling (``ExplorationType.RANDOM``), as TorchRL's collectors.
        device (torch.device, optional): where the policy runs and the batches are
            returned. Defaults to the environment's device (the CPU).

    Examples:
        >>> import torch
        >>> from rl_pg.collectors import DoubleBufferedCollector
        >>> from rl_pg.envs import EnvPoolEnv
        >>> from rl_pg.models import mlp_actor
        >>> env = EnvPoolEnv("CartPole-v1", num_envs=4, groups=2)
        >>> actor = mlp_actor(env, hidden=(16,))
        >>> collector = DoubleBufferedCollector(env, actor, frames_per_batch=32, total_frames=64)
        >>> [batch.batch_size for batch in collector]
        [torch.Size([4, 8]), torch.Size([4, 8])]
        >>> collector.shutdown()
    """

    def __init__(self, env: EnvBase, policy: TensorDictModuleBase, frames_per_batch: int, **kwargs):
        if getattr(env, "groups", 1) != 2 or not hasattr(env, "step_send"):
            raise TypeError(
                f"DoubleBufferedCollector steps two groups of environments in turn: it needs "
                f"an environment built in two groups, such as EnvPoolEnv(task, num_envs, "
                f"groups=2) (rl_pg.envs.gym_env(..., backend='envpool', groups=2)); got "
                f"{type(env).__name__}."
            )
        if len(env.batch_size) != 1:
            raise ValueError(
                f"The environment's batch size must be [num_envs], got {env.batch_size}."
            )
        super().__init__(env, policy, frames_per_batch, **kwargs)
        self._on_tensors = self._on_tensors and type(env) is EnvPoolEnv
        self._first = env.group_sizes[0]  # environments of group 0; group 1 has the rest
        # Where each group stands between batches: its roots, or for an EnvPoolEnv
        # (which hands back plain tensors) its observations.
        self._roots: list[TensorDictBase] | None = None
        self._observations: list[dict[str, torch.Tensor]] | None = None

    def _forget(self) -> None:
        self._roots = self._observations = None

    def _collect(self, horizon: int) -> TensorDictBase:
        env = self.env
        if type(env) is not EnvPoolEnv:  # another two-group environment: its TensorDicts
            return self._collect_tensordicts(horizon)
        if self._observations is None:
            root = self._reset_env()
            self._observations = [
                observations_of(env, part) for part in (root[: self._first], root[self._first :])
            ]
        # Each half's batch is built at its end.
        observations = self._observations
        sizes = [torch.Size([size]) for size in env.group_sizes]
        cleared = [cleared_flags(size, env.device) for size in sizes]
        roots: tuple[list, list] = ([], [])
        nexts: tuple[list, list] = ([], [])

        def send(group: int) -> None:
            root = self._policy_at(observations[group], cleared[group], sizes[group])
            env.send_action(self._action(root), group)
            roots[group].append(root)

        def receive(group: int) -> None:
            step, observations[group] = env.recv_tensors(group)
            nexts[group].append(step)

        send(0)
        for t in range(horizon):
            send(1)  # group 1 steps from here...
            receive(0)
            if t + 1 < horizon:  # on-policy: nothing is sent past the batch's end
                send(0)  # ...while group 0 acts
            receive(1)
        return torch.cat(
            [segment_of(roots[g], nexts[g], sizes[g], env.device) for g in (0, 1)], dim=0
        )

    def _collect_tensordicts(self, horizon: int) -> TensorDictBase:
        if self._roots is None:
            root = self._reset_env()
            self._roots = [root[: self._first], root[self._first :]]
        roots, env, act = self._roots, self.env, self._act
        steps: tuple[list, list] = ([], [])
        env.step_send(act(roots[0]), 0)
        for t in range(horizon):
            env.step_send(act(roots[1]), 1)  # group 1 steps from here...
            step, roots[0] = env.step_recv(0)
            steps[0].append(step)
            if t + 1 < horizon:  # on-policy: nothing is sent past the batch's end
                env.step_send(act(roots[0]), 0)  # ...while group 0 acts
            step, roots[1] = env.step_recv(1)
            steps[1].append(step)
        return torch.cat([torch.stack(group, dim=1) for group in steps], dim=0)
