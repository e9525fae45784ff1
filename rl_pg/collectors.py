"""Collection that overlaps the environments' step with the policy's, strictly on-policy."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["DoubleBufferedCollector"]


class DoubleBufferedCollector:
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
        num_envs = env.batch_size[0]
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
        self._first = env.group_sizes[0]  # environments of group 0; group 1 has the rest
        self._frames = 0
        self._roots: list[TensorDictBase] | None = None

    def set_seed(self, seed: int) -> int:
        """Seeds the environments (they are reset with it at the next batch)."""
        self.env.set_seed(seed)
        self._roots = None
        return seed

    def reset(self) -> None:
        """Resets every environment: the next batch starts new episodes."""
        self._roots = None

    def _start(self) -> list[TensorDictBase]:
        root = self.env.reset()
        return [root[: self._first], root[self._first :]]

    def __iter__(self) -> Iterator[TensorDictBase]:
        while self.total_frames < 0 or self._frames < self.total_frames:
            yield self.next()

    def next(self) -> TensorDictBase:
        """Collects one batch."""
        roots = self._roots if self._roots is not None else self._start()
        steps: tuple[list, list] = ([], [])
        env, device = self.env, self.device
        policy = self.policy if device is None else lambda root: self.policy(root.to(device))
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            env.step_send(policy(roots[0]), 0)
            horizon = self.frames_per_batch // self.env.batch_size[0]
            for t in range(horizon):
                env.step_send(policy(roots[1]), 1)  # group 1 steps from here...
                step, roots[0] = env.step_recv(0)
                steps[0].append(step)
                if t + 1 < horizon:  # on-policy: nothing is sent past the batch's end
                    env.step_send(policy(roots[0]), 0)  # ...while group 0 acts
                step, roots[1] = env.step_recv(1)
                steps[1].append(step)
        self._roots = roots
        self._frames += self.frames_per_batch
        batch = torch.cat([torch.stack(group, dim=1) for group in steps], dim=0)
        return batch if device is None else batch.to(device)

    def state_dict(self) -> dict:
        """The frames collected so far (as TorchRL's collectors report them)."""
        return {"frames": self._frames}

    def shutdown(self) -> None:
        """Closes the environments."""
        if not self.env.is_closed:
            self.env.close()
