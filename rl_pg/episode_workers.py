"""Evaluation environments that each play whole episodes in a process of their own."""

from __future__ import annotations

import contextlib
import copy
import multiprocessing
import signal
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from rl_pg._checks import check_int, require_extra
from rl_pg._process import FrozenInWorkers, frozen_heap, signal_handlers_kept
from rl_pg.evaluation import EpisodeRequest, episode_shares, play_episodes, policy_device

__all__ = ["EpisodeWorkers"]


class EpisodeWorkers:
    """Evaluation environments that each play whole episodes in a process of their own.

    Pass it to [`evaluate`][rl_pg.evaluation.evaluate] as the environment: each
    process receives a CPU copy of the policy and plays its share of the episodes
    ([`episode_shares`][rl_pg.evaluation.episode_shares], as the environments of a
    batched env do) back to back on its own environment, then sends back one result
    per episode. Nothing crosses processes at each step, unlike a ``ParallelEnv``
    (MetaDrive with random actions: 503 steps/s inside a process, 155 driven step by
    step through a one-worker ``ParallelEnv``). The environments are
    built at the first use and stay alive until ``close()``. Worker processes ignore
    Ctrl-C: the main process handles it and closes them.

    Args:
        make_envs (sequence of callables): one environment factory per process,
            picklable. Processes start with the method set by
            ``multiprocessing.set_start_method`` (as TorchRL's workers do), spawned
            when none is set.

    Keyword Args:
        distinct_episodes (int, optional): how many episodes the processes play before
            one repeats (a fixed set of scenarios played in order: its size);
            [`evaluate`][rl_pg.evaluation.evaluate] refuses to play more. Defaults to
            None (no limit).
        backend (str): ``"process"`` (the default), or ``"ray"``: each environment in a
            Ray actor, dealt round-robin over the nodes of the Ray cluster this process
            is connected to (``ray.init()`` first, or one is started: see
            [Ray](https://docs.ray.io/en/latest/ray-core/starting-ray.html)). The actors
            reserve no CPU: they play while a synchronous training's collectors wait,
            on the CPUs those reserve. Needs rl_pg[ray].

    Examples:
        >>> from functools import partial
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.episode_workers import EpisodeWorkers
        >>> env = EpisodeWorkers([partial(GridWorldEnv, max_steps=5)] * 2)
        >>> env.num_workers, env.is_closed  # processes start at the first use
        (2, True)
    """

    def __init__(
        self,
        make_envs: Sequence[Callable[[], EnvBase]],
        *,
        distinct_episodes: int | None = None,
        backend: str = "process",
    ) -> None:
        make_envs = list(make_envs)
        if not make_envs or not all(callable(make) for make in make_envs):
            raise TypeError("make_envs must be a non-empty sequence of environment factories.")
        if backend not in ("process", "ray"):
            raise ValueError(f"backend must be 'process' or 'ray', got {backend!r}.")
        if backend == "ray":
            require_extra("ray", "ray", "Evaluating on Ray actors")
        self.make_envs = make_envs
        self.backend = backend
        self.distinct_episodes = (
            None
            if distinct_episodes is None
            else check_int("distinct_episodes", distinct_episodes, low=len(make_envs))
        )
        self._workers: list[tuple[Any, Any]] = []  # (process, pipe), or Ray actors
        self._specs: dict[str, Any] = {}
        self._seed: int | None = None
        self._owns_ray = False  # a Ray instance started for these workers alone
        self.nodes: list[str] = []
        """With the Ray backend, once started: the Ray node each actor runs on."""

    @property
    def num_workers(self) -> int:
        return len(self.make_envs)

    @property
    def is_closed(self) -> bool:
        return not self._workers

    # What building a policy for these environments needs (e.g. `mlp_actor(env)`), as
    # the first one has it: each process plays one environment of this batch size.
    @property
    def batch_size(self) -> torch.Size:
        return self._started_spec("batch_size")

    @property
    def observation_spec(self):
        return self._started_spec("observation_spec")

    @property
    def action_spec(self):
        return self._started_spec("action_spec")

    def _started_spec(self, name: str) -> Any:
        self._start()
        return self._specs[name]

    def set_seed(self, seed: int | None) -> int | None:
        """Seeds every environment, and the actions sampled beside it, before each
        evaluation: process ``i`` with ``seed + i``."""
        self._seed = seed
        return seed

    def play(
        self, policy: TensorDictModuleBase, request: EpisodeRequest
    ) -> dict[str, torch.Tensor]:
        """One entry per episode, as the processes played them; see ``evaluate``."""
        self._start()
        policy = _cpu_copy(policy)
        shares = episode_shares(request.episodes, self.num_workers)
        seeds = [None if self._seed is None else self._seed + i for i in range(len(shares))]
        if self.backend == "ray":
            results = self._ray_play(policy, request, shares, seeds)
        else:
            for (_, pipe), share, seed in zip(self._workers, shares, seeds, strict=True):
                if share:
                    pipe.send((policy, seed, request._replace(episodes=share)))
            results = [self._receive(i) for i, share in enumerate(shares) if share]
        keys = set.intersection(*(set(result) for result in results))
        return {key: torch.cat([result[key] for result in results]) for key in keys}

    def close(self) -> None:
        if self.backend == "ray":
            self._ray_close()
            return
        for _, pipe in self._workers:
            with contextlib.suppress(BrokenPipeError, OSError):
                pipe.send(None)
        for process, pipe in self._workers:
            process.join(timeout=30)
            if process.is_alive():
                process.kill()
            pipe.close()
        self._workers = []

    def _start(self) -> None:
        if self._workers:
            return
        if self.backend == "ray":
            self._ray_start()
            return
        # Spawn unless the user set a start method: fork is unsafe once torch runs threads.
        method = multiprocessing.get_start_method(allow_none=True) or "spawn"
        context = multiprocessing.get_context(method)
        for make_env in self.make_envs:
            pipe, child = context.Pipe()
            process = context.Process(target=_episode_worker, args=(make_env, child), daemon=True)
            process.start()
            child.close()
            self._workers.append((process, pipe))
        ready = [self._receive(i) for i in range(len(self._workers))]  # each built its env
        self._specs = ready[0]

    def _receive(self, i: int) -> Any:
        process, pipe = self._workers[i]
        try:
            status, payload = pipe.recv()
        except EOFError:
            process.join(timeout=5)
            self.close()
            raise RuntimeError(
                f"Evaluation worker {i} died (exit code {process.exitcode})."
            ) from None
        if status == "error":
            self.close()
            raise RuntimeError(f"Evaluation worker {i} failed:\n{payload}")
        return payload

    def _ray_start(self) -> None:
        import ray

        if not ray.is_initialized():  # RAY_ADDRESS's cluster, or a local instance
            with signal_handlers_kept():  # Ray's own would end a training run's stop
                ray.init(log_to_driver=False)
            self._owns_ray = True
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        # Round-robin over the nodes with CPUs (Ray's "SPREAD" packs actors that reserve
        # none onto one node).
        alive = [n for n in ray.nodes() if n["Alive"]]
        nodes = sorted(n["NodeID"] for n in alive if n["Resources"].get("CPU"))
        nodes = nodes or sorted(n["NodeID"] for n in alive)  # a cluster of CPU-less nodes
        actor = ray.remote(_RayEpisodeWorker)
        self._workers = [
            actor.options(
                num_cpus=0,
                # Hard: a soft affinity let Ray place both actors of the two-node test
                # on one node now and then.
                scheduling_strategy=NodeAffinitySchedulingStrategy(
                    nodes[i % len(nodes)], soft=False
                ),
            ).remote(FrozenInWorkers(make_env))  # as frozen_heap does for a process
            for i, make_env in enumerate(self.make_envs)
        ]
        ready = self._ray_get([worker.specs.remote() for worker in self._workers])
        self._specs = ready[0]
        self.nodes = [specs["node"] for specs in ready]

    def _ray_play(self, policy, request, shares, seeds) -> list[dict[str, torch.Tensor]]:
        import ray

        policy = ray.put(policy)  # one copy in the object store, read by every actor
        return self._ray_get([
            worker.play.remote(policy, seed, request._replace(episodes=share))
            for worker, share, seed in zip(self._workers, shares, seeds, strict=True)
            if share
        ])  # fmt: skip

    def _ray_get(self, refs: list[Any]) -> list[Any]:
        import ray

        try:
            return ray.get(refs)
        except (ray.exceptions.RayTaskError, ray.exceptions.RayActorError) as err:
            self.close()
            raise RuntimeError(f"An evaluation worker (a Ray actor) failed:\n{err}") from None

    def _ray_close(self) -> None:
        import ray

        for worker in self._workers:
            with contextlib.suppress(Exception):  # already dead, or Ray is shut down
                ray.get(worker.close.remote(), timeout=30)
                ray.kill(worker)
        self._workers = []
        if self._owns_ray:
            ray.shutdown()
            self._owns_ray = False

    def __del__(self) -> None:
        if getattr(self, "_workers", None):
            self.close()


def _cpu_copy(policy: TensorDictModuleBase) -> TensorDictModuleBase:
    if policy_device(policy) in (None, torch.device("cpu")):
        return policy  # pickled on its way to each process: a copy already
    return copy.deepcopy(policy).to("cpu")


def _specs(env: EnvBase) -> dict[str, Any]:
    """What a policy for ``env`` is built from, as the main process asks for it."""
    return {"batch_size": env.batch_size, "observation_spec": env.observation_spec,
            "action_spec": env.action_spec}  # fmt: skip


def _seeded_play(policy, env: EnvBase, seed: int | None, request: EpisodeRequest) -> dict:
    """A worker's share of an evaluation: its environment and the sampled actions seeded
    with ``seed`` (unless None), then the episodes ``request`` asks for."""
    if seed is not None:
        env.set_seed(seed)
        torch.manual_seed(seed)
    return play_episodes(policy, env, request)


class _RayEpisodeWorker:
    """One environment in a Ray actor, playing the episodes it is asked for."""

    def __init__(self, make_env: Callable[[], EnvBase]) -> None:
        torch.set_num_threads(1)
        self.env = make_env()

    def specs(self) -> dict[str, Any]:
        import ray

        return {**_specs(self.env), "node": ray.get_runtime_context().get_node_id()}

    def play(self, policy, seed: int | None, request: EpisodeRequest) -> dict[str, torch.Tensor]:
        return _seeded_play(policy, self.env, seed, request)

    def close(self) -> None:
        self.env.close()


def _episode_worker(make_env: Callable[[], EnvBase], pipe: Any) -> None:
    """Builds one environment, then plays the episodes it is sent until told to stop."""
    stops = ("SIGINT", "SIGTERM", "SIGHUP")  # the main process handles them and closes us
    for sig in (getattr(signal, name) for name in stops if hasattr(signal, name)):
        signal.signal(sig, signal.SIG_IGN)
    torch.set_num_threads(1)
    with frozen_heap():  # the process ends with this function: close() waits for it
        try:
            env = make_env()
            pipe.send(("ready", _specs(env)))
        except Exception:
            pipe.send(("error", traceback.format_exc()))
            return
        try:
            while (message := pipe.recv()) is not None:
                policy, seed, request = message
                try:
                    pipe.send(("done", _seeded_play(policy, env, seed, request)))
                except Exception:
                    pipe.send(("error", traceback.format_exc()))
        except EOFError:  # the main process is gone
            pass
        finally:
            env.close()
