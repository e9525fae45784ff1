"""Where experience comes from: the one place that reads workers, Ray and batch mode.

[`Collection`][rl_pg.training.collection.Collection] builds TorchRL's collector for the
config (local, multi-process or Ray) and answers every question the loop has about
it: how many frames a batch cost, what to do after an update, what to do after a
checkpoint.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase

from rl_pg.training.config import TrainConfig

__all__ = ["Collection"]


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
    ) -> None:
        self.cfg = cfg
        self.local = cfg.workers == 1 and not cfg.ray
        """One collector in this process: strictly on-policy, exactly resumable."""
        self._frames_counted = 0
        self._sync_weights: Callable[[], object] | None = None
        kwargs = self._batching(max(1, math.prod(env.batch_size)))
        # Our policies need no extra environment transform (no recurrent state).
        inner = {"auto_register_policy_transforms": False}
        if self.local:
            if device is not None and device != env.device:
                kwargs.update(policy_device=device, storing_device=device, env_device=env.device)
            self.collector = Collector(env, actor, total_frames=-1, **kwargs, **inner)
            self._restart(updates)
            return
        env.close()
        if cfg.ray:
            backend_options = {
                "ray_init_config": {
                    "num_cpus": cfg.workers,
                    "include_dashboard": False,
                    # Actors import the recipe's make_env the way this process does.
                    "runtime_env": {"env_vars": {"PYTHONPATH": os.pathsep.join(sys.path)}},
                },
                "collector_kwargs": inner,
            }
            # The Ray collector reads -1 as "nothing to collect": give it no limit instead.
            kwargs["total_frames"] = 2**62
        else:
            backend_options = inner
            kwargs["total_frames"] = -1
        self.collector = Collector(
            [make_env] * cfg.workers,
            actor,
            backend="ray" if cfg.ray else "process",
            num_collectors=cfg.workers,
            sync=True,
            backend_options=backend_options,
            **kwargs,
        )
        if not cfg.ray:
            self.collector.set_seed(_derived_seed(cfg.seed, updates))
        # TorchRL's weight-sync scheme of each backend (shared memory for processes, a
        # torch.distributed gloo group for Ray actors).
        self._sync_weights = self.collector.update_policy_weights_

    def _batching(self, n_envs: int) -> dict:
        if self.cfg.batch_mode == "episodes":
            return {
                # Polling granularity only (with trajs_per_batch): about 64 steps, a whole
                # number of steps of the batched environment.
                "frames_per_batch": n_envs * max(1, round(64 / n_envs)),
                "trajs_per_batch": self.cfg.episodes_per_batch,
                "traj_format": "cat",
            }
        frames = self.cfg.segment_length * n_envs * max(1, self.cfg.workers)
        return {"frames_per_batch": frames}

    def __iter__(self) -> Iterator[TensorDictBase]:
        return iter(self.collector)

    def frames_spent(self, batch: TensorDictBase) -> int:
        """Environment steps taken for ``batch`` (dropped in-flight steps included)."""
        if not self.local:
            return batch.numel()
        count = self.collector.state_dict()["frames"]
        spent, self._frames_counted = count - self._frames_counted, count
        return spent

    def after_update(self, updates: int) -> None:
        """Sends the new weights to the workers, or (local whole-episode batches) drops
        the episodes in flight, whose first steps the previous policy chose."""
        if self._sync_weights is not None:
            self._sync_weights()
        elif self.cfg.batch_mode == "episodes":
            self._restart(updates)

    def after_checkpoint(self, updates: int) -> bool:
        """Restarts local segment collection where a resumed run would restart it.

        Returns:
            Whether the episodes in flight were dropped.
        """
        if not (self.local and self.cfg.batch_mode == "segments"):
            return False
        self._restart(updates)
        return True

    def _restart(self, updates: int) -> None:
        """Reseeds and resets the environments: the next batch depends only on (seed, updates)."""
        self.collector.set_seed(_derived_seed(self.cfg.seed, updates))
        self.collector.reset()

    def shutdown(self) -> None:
        """Stops the collector and its workers."""
        self.collector.shutdown()


def _derived_seed(seed: int, updates: int) -> int:
    # Spread runs apart so that run s at update u never replays run s + 1 at update u - 1.
    return (seed * 1_000_003 + updates) % 2**31
