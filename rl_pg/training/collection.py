"""Where experience comes from: the one place that reads workers, Ray and batch mode.

[`Collection`][rl_pg.training.collection.Collection] builds TorchRL's collector for the
config (local, multi-process or Ray) and answers every question the loop has about
it: how many frames a batch cost, what to do after an update, and what a checkpoint
must hold for a resumed run to collect exactly what the uninterrupted run would.

Local segment collection restarts every environment every ``env_restart_interval``
updates, whatever the checkpoint interval, and records the actions taken since. A
resumed run restarts the environments as that restart did and replays the recorded
actions: the environments are then where the checkpointed run left them (gymnasium and
rl_pg environments are deterministic given their seed and actions), so the results of
a run do not depend on how often, or when, it was checkpointed.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from rl_pg.collectors import DoubleBufferedCollector, SegmentCollector
from rl_pg.episode_collector import EpisodeCollector
from rl_pg.greedy_play import GreedyInGroups
from rl_pg.lean import lean_policy
from rl_pg.training.seeds import training_seed
from rl_pg.training.settings import CollectionSettings
from rl_pg.training.workers import Workers

__all__ = ["Collection", "segments_per_update"]


class Collection:
    """The collector of a run and the decisions that depend on its topology.

    Args:
        settings (CollectionSettings): the run's collection group.
        env (EnvBase): the training environment (closed and rebuilt in the workers when
            collection is not local).
        make_env (callable): builds an environment in a worker process.
        actor (TensorDictModuleBase): the policy.

    Keyword Args:
        seed (int): the run's seed, which with ``updates`` seeds the environments.
        updates (int): updates already made (a resumed run).
        group_size (int, optional): episodes per group of a group baseline, played
            from one seed (None: no groups).
        greedy (bool): the last environment of each group plays greedily (the greedy
            baseline's episode).
        device (torch.device): where the policy runs and batches are stored (local
            collection; the environment steps on its own device). Defaults to the CPU.
        resumed (dict, optional): the checkpoint's ``state_dict()`` of the collection.
    """

    def __init__(
        self,
        settings: CollectionSettings,
        env: EnvBase,
        make_env: Callable[[], EnvBase],
        actor: TensorDictModuleBase,
        *,
        seed: int,
        updates: int,
        group_size: int | None = None,
        greedy: bool = False,
        device: torch.device | None = None,
        resumed: dict | None = None,
    ) -> None:
        self.settings, self.seed = settings, seed
        self.local = settings.local
        """One collector in this process: strictly on-policy, exactly resumable."""
        self.replaying = self.local and settings.batch_mode == "segments"
        """Restarts on a fixed schedule, replays actions since the last one on resume."""
        self.workers: Workers | None = None
        """The worker processes or Ray actors that collect (None: local collection)."""
        self._frames_counted = 0
        self._restarted_at = 0
        self._actions: list[torch.Tensor] = []
        self._action_key = env.action_key
        kwargs = self._batching(max(1, math.prod(env.batch_size)))
        if self.local:
            # The same actions as the actor, with less overhead per step where it can.
            actor = lean_policy(actor)
            if resumed and resumed["actions"]:  # only a resumed run replays: no cost otherwise
                actor = _ReplayingPolicy(actor, self._action_key)
            if greedy:  # the last environment of each group plays the greedy episode
                actor = GreedyInGroups(actor, group_size=group_size, action_key=self._action_key)
            if settings.overlap:
                self.collector = _overlapped(env, actor, kwargs["frames_per_batch"], device)
            else:
                # TorchRL's Collector's batches, with less work around each step.
                self.collector = SegmentCollector(
                    env, actor, kwargs["frames_per_batch"], device=device
                )
                if settings.batch_mode == "episodes":  # restarted after every update
                    self.collector = EpisodeCollector(
                        self.collector,
                        settings.episodes_per_batch,
                        reset=False,
                        group_size=group_size,
                        greedy=greedy,
                    )
            self._batches = self._record(iter(self.collector))
            self._restart(resumed["restarted_at"] if resumed else updates)
            if resumed:
                self._actions = list(resumed["actions"])
            return
        env.close()
        self.workers = Workers(settings, make_env, actor, kwargs, seed=seed, updates=updates)
        self._batches = self.workers.batches()

    def _batching(self, n_envs: int) -> dict:
        if self.settings.batch_mode == "episodes":
            # How often EpisodeCollector checks for the episodes' ends: about 64 steps of
            # each worker, a whole number of steps of its batched environment.
            steps = n_envs * max(1, round(64 / n_envs))
            return {"frames_per_batch": steps * max(1, self.settings.workers)}
        frames = self.settings.segment_length * n_envs * max(1, self.settings.workers)
        return {"frames_per_batch": frames}

    def __iter__(self) -> Iterator[TensorDictBase]:
        return self._batches

    def join(self, first: TensorDictBase, count: int) -> TensorDictBase:
        """``first`` and the ``count - 1`` segments collected after it, joined along
        time: one longer segment of every environment, collected with the same policy
        (no update comes between them)."""
        if count == 1:
            return first
        parts = [first, *(next(self._batches) for _ in range(count - 1))]
        return torch.cat(parts, dim=first.ndim - 1)  # time is the last batch dimension

    def _record(self, batches: Iterator[TensorDictBase]) -> Iterator[TensorDictBase]:
        for batch in batches:
            if self.replaying:  # time first: [T, *environments, *action]
                actions = batch[self._action_key].movedim(batch.ndim - 1, 0)
                self._actions.append(actions.clone())
            yield batch

    def replay(self) -> int:
        """Steps the restarted environments through the actions recorded since their
        last restart (a resumed run); returns the number of batches replayed.

        The policy still runs (its outputs keep their keys) but the recorded actions
        replace its own; the caller restores the random number generators afterwards.
        """
        if not self.replaying or not self._actions:
            return 0
        recorded, self._actions = self._actions, []
        policy = self.collector.policy
        # The policy is called once per step of the environments, or once per group
        # and step in turn when they are overlapped.
        sizes = self.collector.env.group_sizes if self.settings.overlap else None
        for actions in recorded:
            for step in actions.unbind(0):
                policy.queue.extend(step.split(sizes) if sizes else [step])
            next(self._batches)
        self._frames_counted = self.collector.state_dict()["frames"]
        return len(recorded)

    def state_dict(self) -> dict:
        """What a checkpoint must hold to collect on exactly as this run does."""
        if not self.replaying:
            return {}
        return {"restarted_at": self._restarted_at, "actions": list(self._actions)}

    def frames_spent(self, batch: TensorDictBase) -> int:
        """Environment steps taken for ``batch`` (dropped steps included)."""
        if self.workers is not None:
            return self.workers.frames_spent(batch)
        if isinstance(self.collector, EpisodeCollector):
            count = self.collector.frames
        else:
            count = self.collector.state_dict()["frames"]
        spent, self._frames_counted = count - self._frames_counted, count
        return spent

    def after_update(self, updates: int) -> bool:
        """Sends the new weights to the workers, and restarts the environments: after
        every update with whole-episode batches (the episodes in flight began under the
        previous policy), every ``env_restart_interval`` updates with local segments.

        Returns:
            Whether the episodes in flight were dropped.
        """
        if self.workers is not None:
            self.workers.after_update(updates)
            return self.settings.batch_mode == "episodes"
        if self.replaying and updates % self.settings.env_restart_interval != 0:
            return False
        self._restart(updates)
        return True

    def _restart(self, updates: int) -> None:
        """Reseeds and resets the environments: the next batch depends only on (seed, updates)."""
        self.collector.set_seed(training_seed(self.seed, updates))
        self.collector.reset()
        self._restarted_at, self._actions = updates, []

    def shutdown(self) -> None:
        """Stops the collector and its workers (and the Ray instance it started)."""
        (self.collector if self.workers is None else self.workers).shutdown()


class _ReplayingPolicy(TensorDictModuleBase):
    """The actor, except that queued actions (a resumed run's replay) replace its own."""

    def __init__(self, actor: TensorDictModuleBase, action_key) -> None:
        super().__init__()
        self.actor = actor
        self.in_keys, self.out_keys = actor.in_keys, actor.out_keys
        self.action_key = action_key
        self.queue: deque[torch.Tensor] = deque()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self.actor(tensordict)
        if self.queue:
            tensordict.set(self.action_key, self.queue.popleft())
        return tensordict


def _overlapped(
    env: EnvBase, actor: TensorDictModuleBase, frames_per_batch: int, device
) -> DoubleBufferedCollector:
    if getattr(env, "groups", 1) != 2:
        raise ValueError(
            f"--overlap steps the environments in two groups, but this recipe's training "
            f"environment ({type(env).__name__}) is one: use --backend envpool (the "
            f"CartPole and LunarLander recipes build it in two groups with --overlap), "
            f"or leave --overlap out."
        )
    return DoubleBufferedCollector(env, actor, frames_per_batch, device=device)


def segments_per_update(settings: CollectionSettings, frames: int, total_frames: int) -> int:
    """Segments the update that follows ``frames`` of ``total_frames`` environment steps
    joins: 1, then ``segments_late`` from ``segments_late_start`` of the run on."""
    late = frames >= settings.segments_late_start * total_frames
    return settings.segments_late if late and settings.batch_mode == "segments" else 1
