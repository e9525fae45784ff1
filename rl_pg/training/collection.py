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
import os
import socket
import sys
from collections import deque
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase

from rl_pg._process import FrozenInWorkers
from rl_pg.collectors import DoubleBufferedCollector, EpisodeCollector, SegmentCollector
from rl_pg.lean import lean_policy
from rl_pg.training.config import TrainConfig
from rl_pg.training.interrupt import MainProcessInterrupts
from rl_pg.training.seeds import training_seed

__all__ = ["Collection", "segments_per_update"]


class Collection:
    """The collector of a run and the decisions that depend on its topology.

    Args:
        cfg (TrainConfig): ``workers``, ``ray``, ``batch_mode``, ``segment_length``,
            ``episodes_per_batch`` and ``seed`` are read.
        env (EnvBase): the training environment (closed and rebuilt in the workers when
            collection is not local).
        make_env (callable): builds an environment in a worker process.
        actor (TensorDictModuleBase): the policy.

    Keyword Args:
        updates (int): updates already made (a resumed run), which seed the environments.
        device (torch.device): where the policy runs and batches are stored (local
            collection; the environment steps on its own device). Defaults to the CPU.
        resumed (dict, optional): the checkpoint's ``state_dict()`` of the collection.
    """

    def __init__(
        self,
        cfg: TrainConfig,
        env: EnvBase,
        make_env: Callable[[], EnvBase],
        actor: TensorDictModuleBase,
        *,
        updates: int,
        device: torch.device | None = None,
        resumed: dict | None = None,
    ) -> None:
        self.cfg = cfg
        self._owns_ray = False  # set when this run starts a Ray instance of its own
        self.local = cfg.workers == 1 and not cfg.ray
        """One collector in this process: strictly on-policy, exactly resumable."""
        self.replaying = self.local and cfg.batch_mode == "segments"
        """Restarts on a fixed schedule, replays actions since the last one on resume."""
        self._frames_counted = 0
        self._sync_weights: Callable[[], object] | None = None
        self._restarted_at = 0
        self._actions: list[torch.Tensor] = []
        self._action_key = env.action_key
        kwargs = self._batching(max(1, math.prod(env.batch_size)))
        # Our policies need no extra environment transform (no recurrent state).
        inner = {"auto_register_policy_transforms": False}
        if self.local:
            # The same actions as the actor, with less overhead per step where it can.
            actor = lean_policy(actor)
            if resumed and resumed["actions"]:  # only a resumed run replays: no cost otherwise
                actor = _ReplayingPolicy(actor, self._action_key)
            if cfg.overlap:
                self.collector = _overlapped(env, actor, kwargs["frames_per_batch"], device)
            else:
                # TorchRL's Collector's batches, with less work around each step.
                self.collector = SegmentCollector(
                    env, actor, kwargs["frames_per_batch"], device=device
                )
                if cfg.batch_mode == "episodes":  # restarted after every update
                    self.collector = EpisodeCollector(
                        self.collector, cfg.episodes_per_batch, reset=False
                    )
            self._batches = self._record(iter(self.collector))
            self._restart(resumed["restarted_at"] if resumed else updates)
            if resumed:
                self._actions = list(resumed["actions"])
            return
        env.close()
        if cfg.ray:
            self._owns_ray = _start_ray(cfg.workers)
            backend_options = {"collector_kwargs": inner}
            # The Ray collector reads -1 as "nothing to collect": give it no limit instead.
            kwargs["total_frames"] = 2**62
        else:
            backend_options = inner
            kwargs["total_frames"] = -1
        # The workers keep what they imported out of their garbage collector's walks;
        # worker processes leave Ctrl-C to this one, which shuts them down.
        factory = FrozenInWorkers(make_env)
        self.collector = Collector(
            [factory if cfg.ray else MainProcessInterrupts(factory)] * cfg.workers,
            actor,
            backend="ray" if cfg.ray else "process",
            num_collectors=cfg.workers,
            sync=True,
            backend_options=backend_options,
            **kwargs,
        )
        if not cfg.ray:
            self.collector.set_seed(training_seed(cfg.seed, updates))
        # TorchRL's weight-sync scheme of each backend (shared memory for processes, a
        # torch.distributed gloo group for Ray actors).
        self._sync_weights = self.collector.update_policy_weights_
        self._sync_weights()  # the workers start from the learner's weights
        if cfg.batch_mode == "episodes":  # reset after every update
            self.collector = EpisodeCollector(self.collector, cfg.episodes_per_batch, reset=False)
        self._batches = iter(self.collector)

    def _batching(self, n_envs: int) -> dict:
        if self.cfg.batch_mode == "episodes":
            # How often EpisodeCollector checks for the episodes' ends: about 64 steps of
            # each worker, a whole number of steps of its batched environment.
            steps = n_envs * max(1, round(64 / n_envs))
            return {"frames_per_batch": steps * max(1, self.cfg.workers)}
        frames = self.cfg.segment_length * n_envs * max(1, self.cfg.workers)
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
        sizes = self.collector.env.group_sizes if self.cfg.overlap else None
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
        if isinstance(self.collector, EpisodeCollector):
            count = self.collector.frames
        elif self.local:
            count = self.collector.state_dict()["frames"]
        else:
            return batch.numel()
        spent, self._frames_counted = count - self._frames_counted, count
        return spent

    def after_update(self, updates: int) -> bool:
        """Sends the new weights to the workers, and restarts the environments: after
        every update with whole-episode batches (the episodes in flight began under the
        previous policy), every ``env_restart_interval`` updates with local segments.

        Returns:
            Whether the episodes in flight were dropped.
        """
        if self._sync_weights is not None:
            self._sync_weights()
            if self.cfg.batch_mode == "episodes":
                self.collector.reset()
                return True
            return False
        if self.replaying and updates % self.cfg.env_restart_interval != 0:
            return False
        self._restart(updates)
        return True

    def _restart(self, updates: int) -> None:
        """Reseeds and resets the environments: the next batch depends only on (seed, updates)."""
        self.collector.set_seed(training_seed(self.cfg.seed, updates))
        self.collector.reset()
        self._restarted_at, self._actions = updates, []

    def shutdown(self) -> None:
        """Stops the collector and its workers (and the Ray instance it started)."""
        self.collector.shutdown()
        if self._owns_ray:
            import ray

            ray.shutdown()


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


def _start_ray(workers: int) -> bool:
    """Connects to the Ray cluster ``RAY_ADDRESS`` names, which brings its own resources,
    or else starts a Ray instance of ``workers`` CPUs in this process (never another
    instance found running on this machine); True if it started one."""
    import ray

    if ray.is_initialized():
        return False
    # Actors import the recipe's make_env the way this process does: they need its
    # sys.path. Their output stays in Ray's logs: Ray would prefix every line of it with
    # the collector's repr, dozens of lines each (an actor's error still reaches here).
    path = os.pathsep.join(sys.path)
    address = os.environ.get("RAY_ADDRESS", "")
    if not address:
        # A local instance's processes inherit this environment, so the path goes there
        # rather than into a runtime_env: Ray would set up a worker process of its own
        # for each actor and leave the ones it starts with (one per CPU) idle.
        previous = os.environ.get("PYTHONPATH")
        os.environ["PYTHONPATH"] = path
        try:
            ray.init(address="local", num_cpus=workers, include_dashboard=False,
                     log_to_driver=False)  # fmt: skip
        finally:
            if previous is None:
                del os.environ["PYTHONPATH"]
            else:
                os.environ["PYTHONPATH"] = previous
        return True
    _check_reachable(address)
    ray.init(address=address, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": path}})  # fmt: skip
    nodes = [node for node in ray.nodes() if node["Alive"]]
    cpus = sum(node["Resources"].get("CPU", 0) for node in nodes)
    print(
        f"Ray: collecting on the cluster at {address} ({len(nodes)} nodes, {cpus:g} CPUs; "
        f"each worker takes one CPU).",
        file=sys.stderr,
    )
    return False


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """Fails at once, naming ``RAY_ADDRESS``, when nothing answers at its ``host:port``
    (Ray itself retries in silence for minutes). Other forms (``auto``, ``ray://``) are
    left to Ray."""
    host, _, port = address.rpartition(":")
    if not host or "://" in address or not port.isdigit():
        return
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as err:
        raise ConnectionError(
            f"RAY_ADDRESS={address}: nothing answers there ({err}). Start the cluster's "
            f"head with `ray start --head --port {port}` on {host}, correct RAY_ADDRESS, or "
            f"unset it to collect on a Ray instance of this process."
        ) from None


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


def segments_per_update(cfg: TrainConfig, frames: int) -> int:
    """Segments the update that follows ``frames`` environment steps joins: 1, then
    ``segments_late`` from ``segments_late_start`` of the run on."""
    late = frames >= cfg.segments_late_start * cfg.total_frames
    return cfg.segments_late if late and cfg.batch_mode == "segments" else 1
