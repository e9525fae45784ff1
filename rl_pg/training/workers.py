"""Collection over worker processes or Ray actors that survives losing them: the
workers' TorchRL collector, a watchdog for hung workers, their replacement, and the
Ray instance or cluster they run on."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase

from rl_pg._process import FrozenInWorkers
from rl_pg.episode_collector import EpisodeCollector
from rl_pg.training.cluster import start_ray
from rl_pg.training.interrupt import MainProcessInterrupts
from rl_pg.training.seeds import training_seed
from rl_pg.training.settings import CollectionSettings

__all__ = ["REPLACEMENTS", "STALL_LIMIT_S", "STARTUP_LIMIT_S", "Workers"]

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


class Workers:
    """TorchRL's collector over worker processes or Ray actors, kept running: a worker
    lost (its process killed, its node gone) or hung (no batch within a limit) is
    replaced, with the learner's weights and the update's seeds, up to
    ``REPLACEMENTS`` times in a row.

    Args:
        settings (CollectionSettings): ``workers``, ``ray``, ``batch_mode`` and
            ``episodes_per_batch`` are read.
        make_env (callable): builds an environment in a worker.
        actor (TensorDictModuleBase): the policy, whose weights the workers hold.
        kwargs (dict): TorchRL's ``Collector`` arguments (``frames_per_batch``).
        seed (int): the run's seed, which with ``updates`` seeds the workers.
        updates (int): updates already made.
    """

    def __init__(
        self,
        settings: CollectionSettings,
        make_env: Callable[[], EnvBase],
        actor: TensorDictModuleBase,
        kwargs: dict,
        *,
        seed: int,
        updates: int,
    ) -> None:
        self.settings, self.seed = settings, seed
        self._owns_ray = start_ray(settings.workers) if settings.ray else False
        self._make_env, self._actor, self._updates = make_env, actor, updates
        self._kwargs = kwargs
        self._counted = 0  # frames the current collector had counted at the last batch
        self._replaced = 0  # workers lost since the last batch
        self._slowest = 0.0  # seconds of the slowest batch so far (the stall limit's base)
        self._ended: dict[int, str] = {}  # pids of workers ended as stalled: why
        self._actors_ended: str | None = None  # why the Ray actors were, if they were
        self.collector = self._start()

    def frames_spent(self, batch: TensorDictBase) -> int:
        """Environment steps the workers took for ``batch`` (dropped steps included)."""
        if not isinstance(self.collector, EpisodeCollector):
            return batch.numel()
        count = self.collector.frames
        spent, self._counted = count - self._counted, count
        return spent

    def after_update(self, updates: int) -> None:
        """Sends the new weights to the workers (and restarts whole-episode collection:
        the episodes in flight began under the previous policy); new workers replace
        lost ones, with the new weights."""
        self._updates = updates
        try:
            if self.settings.ray:
                self._sync_weights()
            else:
                self._sync_watching_processes()
            if self.settings.batch_mode == "episodes":
                self.collector.reset()
        except Exception as err:
            self._replace_if_lost(err)

    def shutdown(self) -> None:
        """Stops the workers (and the Ray instance started for them)."""
        self.collector.shutdown()
        if self._owns_ray:
            import ray

            ray.shutdown()

    def _start(self) -> Collector | EpisodeCollector:
        """TorchRL's collector over ``workers`` worker processes or Ray actors, each
        holding the learner's weights."""
        settings, kwargs = self.settings, dict(self._kwargs)
        # Our policies need no extra environment transform (no recurrent state).
        inner = {"auto_register_policy_transforms": False}
        if settings.ray:
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
            [factory if settings.ray else MainProcessInterrupts(factory)] * settings.workers,
            self._actor,
            backend="ray" if settings.ray else "process",
            num_collectors=settings.workers,
            sync=True,
            backend_options=backend_options,
            **kwargs,
        )
        self.pool = collector
        if not settings.ray:
            collector.set_seed(training_seed(self.seed, self._updates))
        # TorchRL's weight-sync scheme of each backend (shared memory for processes, a
        # torch.distributed gloo group for Ray actors).
        self._sync_weights = collector.update_policy_weights_
        try:
            self._sync_weights()  # the workers start from the learner's weights
        except Exception as err:
            if not settings.ray or not isinstance(err, torch.distributed.DistError):
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
        if settings.batch_mode == "episodes":  # reset after every update
            return EpisodeCollector(collector, settings.episodes_per_batch, reset=False)
        return collector

    def batches(self) -> Iterator[TensorDictBase]:
        """The collector's batches; a lost worker (its process or node gone) replaces
        the workers and the batch is collected again, up to ``REPLACEMENTS`` times in a
        row."""
        collector = batches = None
        while True:
            if collector is not self.collector:  # new workers (replaced in after_update too)
                collector, batches = self.collector, iter(self.collector)
                first = True
            limit = STARTUP_LIMIT_S if first else max(STALL_LIMIT_S, 20 * self._slowest)
            watchdog = threading.Timer(limit, self._end_stalled, args=(limit,))
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

    def _end_stalled(self, limit: float) -> None:
        """Called by the watchdog when no batch came within ``limit`` seconds: a worker
        hangs (stopped, deadlocked, stuck in its simulator). Its process and the others
        are killed, which the waiting collector sees as lost workers: they are replaced
        like any lost worker, and named with why they were ended."""
        if self.settings.ray:
            import ray

            # A Ray actor's process is its node's to end: Ray kills it on request, and
            # the collector waiting on it sees the actor die. Which one hangs cannot be
            # asked of a hung actor: all are ended, as worker processes are.
            self._actors_ended = f"sent no batch in {limit:.0f} s, so rl-pg ended it"
            for actor in self.pool.remote_collectors:
                with contextlib.suppress(Exception):
                    ray.kill(actor, no_restart=True)
            return
        for proc in self.pool.procs:
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
        lost = self._lost(err)
        if lost is None:
            raise err
        self._replaced += 1
        if self._replaced > REPLACEMENTS:
            raise RuntimeError(
                f"Collection lost a worker {self._replaced} times in a row, the last time: "
                f"{lost}. {_WHERE_WORKERS_LOG[self.settings.ray]} The run stops here; its last "
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
            self.pool.shutdown()
        self._counted = 0  # the new collector counts from zero
        self.collector = self._start()

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
                self._end_stalled(STALL_LIMIT_S)  # one never acknowledges
            if thread.is_alive() and self._lost(None):
                raise ChildProcessError("a worker process is gone")
        if failed:
            raise failed[0]

    def _lost(self, err: Exception | None) -> str | None:
        """What was lost if a worker is gone (``err`` came from the collector), else None."""
        if self.settings.ray:
            import ray

            if isinstance(err, ray.exceptions.RayActorError):
                ended, self._actors_ended = self._actors_ended, None
                return _actor_lost(err, ended)
            for actor in self.pool.remote_collectors:  # e.g. a failed weight transfer
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
            for i, proc in enumerate(self.pool.procs)
            if not proc.is_alive()
            and proc.exitcode is not None
            and (proc.exitcode < 0 or (server_gone and proc.exitcode == 255))
        ]
        return "; ".join(killed) or None


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
