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

import contextlib
import math
import os
import re
import signal
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase

from rl_pg._process import FrozenInWorkers, signal_handlers_kept
from rl_pg.collectors import DoubleBufferedCollector, EpisodeCollector, SegmentCollector
from rl_pg.groups import GROUP_BASELINES, GreedyInGroups
from rl_pg.lean import lean_policy
from rl_pg.training.config import TrainConfig
from rl_pg.training.interrupt import MainProcessInterrupts
from rl_pg.training.seeds import training_seed

__all__ = ["REPLACEMENTS", "STALL_LIMIT_S", "STARTUP_LIMIT_S", "Collection", "segments_per_update"]

REPLACEMENTS = 3
"""Times in a row a run replaces its workers after losing one (a worker process killed,
a Ray node gone, a simulator crashed) before it stops."""

STARTUP_LIMIT_S = 600.0
"""Seconds new workers may take for their first batch (a simulator's start included)
before they count as hung."""
STALL_LIMIT_S = 300.0
"""Seconds without a batch after which the workers count as hung: this, or 20 times the
slowest batch so far if longer. Hung workers are ended and replaced like lost ones."""

_WHERE_WORKERS_LOG = {
    True: "A Ray worker's own output, its error included, is in the Ray session's logs "
    "on its node (/tmp/ray/session_latest/logs/worker-*.err by default).",
    False: "A crash of the environment's native code (a segmentation fault) may have "
    "printed more above.",
}


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
        if self.local:
            # The same actions as the actor, with less overhead per step where it can.
            actor = lean_policy(actor)
            if resumed and resumed["actions"]:  # only a resumed run replays: no cost otherwise
                actor = _ReplayingPolicy(actor, self._action_key)
            greedy = cfg.baseline == "greedy"
            if greedy:  # the last environment of each group plays the greedy episode
                actor = GreedyInGroups(
                    actor, group_size=cfg.group_size, action_key=self._action_key
                )
            if cfg.overlap:
                self.collector = _overlapped(env, actor, kwargs["frames_per_batch"], device)
            else:
                # TorchRL's Collector's batches, with less work around each step.
                self.collector = SegmentCollector(
                    env, actor, kwargs["frames_per_batch"], device=device
                )
                if cfg.batch_mode == "episodes":  # restarted after every update
                    grouped = cfg.baseline in GROUP_BASELINES
                    self.collector = EpisodeCollector(
                        self.collector,
                        cfg.episodes_per_batch,
                        reset=False,
                        group_size=cfg.group_size if grouped else None,
                        greedy=greedy,
                    )
            self._batches = self._record(iter(self.collector))
            self._restart(resumed["restarted_at"] if resumed else updates)
            if resumed:
                self._actions = list(resumed["actions"])
            return
        env.close()
        if cfg.ray:
            self._owns_ray = _start_ray(cfg.workers)
        self._make_env, self._actor, self._updates = make_env, actor, updates
        self._kwargs = kwargs
        self._replaced = 0  # workers lost since the last batch
        self._slowest = 0.0  # seconds of the slowest batch so far (the stall limit's base)
        self._ended: dict[int, str] = {}  # pids of workers ended as stalled: why
        self._actors_ended: str | None = None  # why the Ray actors were, if they were
        self.collector = self._remote_collector()
        self._batches = self._remote_batches()

    def _remote_collector(self) -> Collector | EpisodeCollector:
        """TorchRL's collector over ``cfg.workers`` worker processes or Ray actors, each
        holding the learner's weights."""
        cfg, kwargs = self.cfg, dict(self._kwargs)
        # Our policies need no extra environment transform (no recurrent state).
        inner = {"auto_register_policy_transforms": False}
        if cfg.ray:
            backend_options = {"collector_kwargs": inner}
            # The Ray collector reads -1 as "nothing to collect": give it no limit instead.
            kwargs["total_frames"] = 2**62
        else:
            backend_options = inner
            kwargs["total_frames"] = -1
        # The workers keep what they imported out of their garbage collector's walks;
        # worker processes leave Ctrl-C to this one, which shuts them down.
        factory = FrozenInWorkers(self._make_env)
        collector = Collector(
            [factory if cfg.ray else MainProcessInterrupts(factory)] * cfg.workers,
            self._actor,
            backend="ray" if cfg.ray else "process",
            num_collectors=cfg.workers,
            sync=True,
            backend_options=backend_options,
            **kwargs,
        )
        self._workers = collector
        if not cfg.ray:
            collector.set_seed(training_seed(cfg.seed, self._updates))
        # TorchRL's weight-sync scheme of each backend (shared memory for processes, a
        # torch.distributed gloo group for Ray actors).
        self._sync_weights = collector.update_policy_weights_
        try:
            self._sync_weights()  # the workers start from the learner's weights
        except Exception as err:
            if not cfg.ray or not isinstance(err, torch.distributed.DistError):
                raise
            with contextlib.suppress(Exception):
                collector.shutdown()
            raise RuntimeError(
                f"The Ray workers did not join the trainer's weight-sync group in time "
                f"({str(err).strip().splitlines()[0]}). TorchRL sends them the weights over "
                f"torch.distributed (gloo): each worker connects to this machine "
                f"({socket.gethostname()}) on TCP ports picked at random, so the cluster's "
                f"nodes must reach each other on any port (a firewall between them stops "
                f"it); a machine too busy to start the workers within a minute stops it too: "
                f"run fewer workers there."
            ) from err
        if cfg.batch_mode == "episodes":  # reset after every update
            return EpisodeCollector(collector, cfg.episodes_per_batch, reset=False)
        return collector

    def _remote_batches(self) -> Iterator[TensorDictBase]:
        """The collector's batches; a lost worker (its process or node gone) replaces
        the workers and the batch is collected again, up to ``REPLACEMENTS`` times in a
        row."""
        collector = batches = None
        while True:
            if collector is not self.collector:  # new workers (replaced in after_update too)
                collector, batches = self.collector, iter(self.collector)
                first = True
            limit = STARTUP_LIMIT_S if first else max(STALL_LIMIT_S, 20 * self._slowest)
            watchdog = threading.Timer(limit, self._end_stalled_workers, args=(limit,))
            watchdog.daemon = True
            watchdog.start()
            start = time.monotonic()
            try:
                batch = next(batches)
            except StopIteration:
                return
            except Exception as err:
                self._replace_if_lost(err)
                continue
            finally:
                watchdog.cancel()
            if not first:  # a first batch includes the workers' start
                self._slowest = max(self._slowest, time.monotonic() - start)
            first = False
            self._replaced = 0
            yield batch

    def _end_stalled_workers(self, limit: float) -> None:
        """Called by the watchdog when no batch came within ``limit`` seconds: a worker
        hangs (stopped, deadlocked, stuck in its simulator). Its process and the others
        are killed, which the waiting collector sees as lost workers: they are replaced
        like any lost worker, and named with why they were ended."""
        if self.cfg.ray:
            import ray

            # A Ray actor's process is its node's to end: Ray kills it on request, and
            # the collector waiting on it sees the actor die. Which one hangs cannot be
            # asked of a hung actor: all are ended, as worker processes are.
            self._actors_ended = f"sent no batch in {limit:.0f} s, so rl-pg ended it"
            for actor in self._workers.remote_collectors:
                with contextlib.suppress(Exception):
                    ray.kill(actor, no_restart=True)
            return
        for proc in self._workers.procs:
            if proc.is_alive():
                self._ended[proc.pid] = (
                    f"sent no batch in {limit:.0f} s ({_process_state(proc.pid)}), so rl-pg "
                    f"ended it"
                )
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGKILL)

    def _replace_if_lost(self, err: Exception) -> None:
        """Re-raises ``err`` unless a worker is gone; otherwise starts new workers, with
        the learner's weights."""
        lost = self._lost_worker(err)
        if lost is None:
            raise err
        self._replaced += 1
        if self._replaced > REPLACEMENTS:
            raise RuntimeError(
                f"Collection lost a worker {self._replaced} times in a row, the last time: "
                f"{lost}. {_WHERE_WORKERS_LOG[self.cfg.ray]} The run stops here; its last "
                f"checkpoint resumes it (rl-pg resume RUN_DIR)."
            ) from err
        print(
            f"rl-pg: collection lost a worker: {lost}. New workers take over, with the "
            f"learner's weights ({self._replaced} of at most {REPLACEMENTS} times in a row).",
            file=sys.stderr,
        )
        # The workers that remain are stopped (a dead one cannot answer), and new ones
        # start where the run is: the learner's weights, the update's seeds.
        with contextlib.suppress(Exception):
            self._workers.shutdown()
        self._frames_counted = 0  # the new collector counts from zero
        self.collector = self._remote_collector()

    def _sync_watching_processes(self) -> None:
        """Sends the weights to the worker processes, watching that each stays alive:
        TorchRL waits without end for a dead process to acknowledge them. A process
        lost meanwhile raises ``ChildProcessError`` (the waiting thread is left behind)."""
        failed: list[BaseException] = []

        def sync() -> None:
            try:
                self._sync_weights()
            except BaseException as err:  # handed to the main thread
                failed.append(err)

        thread = threading.Thread(target=sync, name="rl-pg weight sync", daemon=True)
        thread.start()
        start = time.monotonic()
        while thread.is_alive():
            thread.join(0.05)
            if not self._ended and time.monotonic() - start > STALL_LIMIT_S:
                self._end_stalled_workers(STALL_LIMIT_S)  # one never acknowledges
            if thread.is_alive() and self._lost_worker(None):
                raise ChildProcessError("a worker process is gone")
        if failed:
            raise failed[0]

    def _lost_worker(self, err: Exception | None) -> str | None:
        """What was lost if a worker is gone (``err`` came from the collector), else None."""
        if self.cfg.ray:
            import ray

            if isinstance(err, ray.exceptions.RayActorError):
                ended, self._actors_ended = self._actors_ended, None
                return _actor_lost(err, ended)
            for actor in self._workers.remote_collectors:  # e.g. a failed weight transfer
                try:
                    ray.get(actor.__ray_ready__.remote(), timeout=60)
                except ray.exceptions.RayActorError as dead:
                    return _actor_lost(dead)
                except ray.exceptions.GetTimeoutError:
                    continue  # busy, not gone
            return None
        # Killed by a signal (the OOM killer's SIGKILL, a simulator's SIGSEGV): lost. One
        # that exited by itself (an exception in the environment: its traceback is
        # printed) would only exit again: TorchRL's error stands.
        # Workers forked by a fork server that was killed report exit code 255 (their
        # status died with it): lost with it, not failed by themselves.
        server_gone = _fork_server_gone()
        killed = [
            _process_lost(i, proc.pid, proc.exitcode, server_gone, self._ended.get(proc.pid))
            for i, proc in enumerate(self._workers.procs)
            if not proc.is_alive()
            and proc.exitcode is not None
            and (proc.exitcode < 0 or (server_gone and proc.exitcode == 255))
        ]
        return "; ".join(killed) or None

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
            self._updates = updates
            try:
                if self.cfg.ray:
                    self._sync_weights()
                else:
                    self._sync_watching_processes()
                if self.cfg.batch_mode == "episodes":
                    self.collector.reset()
            except Exception as err:  # new workers start with the new weights
                self._replace_if_lost(err)
            return self.cfg.batch_mode == "episodes"
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


def _process_lost(
    index: int, pid: int, code: int, server_gone: bool = False, ended: str | None = None
) -> str:
    """A worker process killed by signal ``-code`` (or gone with its fork server, or
    ended by the watchdog: ``ended`` says why), in one line."""
    if ended is not None:
        return f"worker process {index} (pid {pid}) {ended}"
    if code == 255 and server_gone:
        return (
            f"worker process {index} (pid {pid}) is gone with the fork server that started "
            f"it (killed)"
        )
    try:
        name = signal.Signals(-code).name
    except ValueError:
        name = f"signal {-code}"
    return f"worker process {index} (pid {pid}) was killed by {name}"


def _process_state(pid: int) -> str:
    """What a live process is doing, as the kernel says (Linux), for a message."""
    states = {"T": "stopped", "t": "stopped by a debugger", "D": "waiting on a device",
              "S": "waiting", "R": "running"}  # fmt: skip
    try:
        with open(f"/proc/{pid}/stat") as stat:
            state = stat.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "state unknown"
    return states.get(state, f"state {state}")


def _fork_server_gone() -> bool:
    """Whether the fork server that starts this process's workers was started and has
    died since (multiprocessing starts a new one for the next workers)."""
    from multiprocessing import forkserver

    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)
    if pid is None:
        return False
    try:
        with open(f"/proc/{pid}/stat") as stat:  # a dead child is a zombie until reaped
            return stat.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True
    except OSError:  # no /proc (not Linux): whether the process can still be signalled
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        return False


def _actor_lost(err: Exception, ended: str | None = None) -> str:
    """The Ray worker an error names, and why it is gone (``ended``: why rl-pg ended
    it), in one line."""
    text = str(err)
    found = dict(re.findall(r"^\s*(class_name|pid|ip): (\S+)", text, re.MULTILINE))
    detail = re.search(r"Worker exit detail: ([^.]*)", text)
    why = detail.group(1) if detail else text.strip().splitlines()[0] if text.strip() else ""
    where = f" (pid {found['pid']} on {found['ip']})" if {"pid", "ip"} <= found.keys() else ""
    why = ended or why.rstrip(".") or type(err).__name__
    name = f" {found['class_name']}" if "class_name" in found else ""
    return f"Ray actor{name}{where}: {why}"


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
            with signal_handlers_kept():  # Ray's own would lose the run's stop
                ray.init(address="local", num_cpus=workers, include_dashboard=False,
                         log_to_driver=False)  # fmt: skip
        finally:
            if previous is None:
                del os.environ["PYTHONPATH"]
            else:
                os.environ["PYTHONPATH"] = previous
        return True
    _check_reachable(address)
    with signal_handlers_kept():
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
