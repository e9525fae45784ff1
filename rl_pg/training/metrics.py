"""What a run measures of its training episodes: their returns, as they end (the
loggers that take the run's scalars are in [`loggers`][rl_pg.training.loggers])."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase

from rl_pg.functional import discounted_return

__all__ = ["EpisodeReturns"]


class EpisodeReturns:
    """Undiscounted returns of the training episodes that end in the batches.

    With segments an episode spans batches: each environment's unfinished sum is
    carried into its next segment, and each batch's rows are summed episode by episode
    in one pass (a numba kernel). (A per-step transform such as TorchRL's
    ``RewardSum`` does this at every environment step and cost ~15 % of CartPole's
    collection time.)
    """

    def __init__(self, *, carry: bool) -> None:
        self.carry = carry
        self.partial: torch.Tensor | None = None
        self.ended: list[torch.Tensor] = []

    def reset(self) -> None:
        """The environments restarted: episodes in flight are gone."""
        self.partial = None

    def add(self, batch: TensorDictBase) -> None:
        from rl_pg._scan_kernels import episode_sums  # numba: imported where it runs

        steps = batch.shape[-1]
        rows = batch.numel() // steps
        done = batch.get(("next", "done")).reshape(rows, steps, -1).cpu().contiguous()
        # Summed in float64 (on the CPU: not every accelerator has it) whatever the
        # rewards' precision: a return of 500 in bfloat16 steps by 2.
        reward = batch.get(("next", "reward")).reshape(rows, steps, -1)
        reward = reward.to("cpu", torch.float64).contiguous().numpy()
        carried = self.partial
        if carried is None or carried.shape[0] != rows:
            carried = torch.zeros(rows, dtype=torch.float64)
        tails = np.empty(rows)
        # One pass over the rows (a kernel call, where a dozen numpy calls on these
        # small arrays cost several times the arithmetic).
        sums, check = episode_sums(reward, done.numpy(), carried.numpy(), tails)
        if check != 0.0:  # a sum is not finite: the return function's clear error
            discounted_return(torch.from_numpy(reward.sum(-1)), done.any(-1), 1.0, time_dim=-1)
        if len(sums):
            self.ended.append(torch.from_numpy(sums))
        if self.carry:  # what follows each row's last episode end is still in flight
            self.partial = torch.from_numpy(tails)

    @staticmethod
    def warm_up() -> None:
        """Loads the summing kernel (from numba's cache, or compiles it) before the
        training clock starts: the first call costs up to a second."""
        from rl_pg._scan_kernels import episode_sums

        flags = np.zeros((1, 1, 1), dtype=bool)
        episode_sums(np.zeros((1, 1, 1)), flags, np.zeros(1), np.empty(1))

    def state_dict(self) -> dict:
        return {"partial": self.partial, "ended": list(self.ended)}

    def load_state_dict(self, state: dict) -> None:
        self.partial, self.ended = state["partial"], list(state["ended"])

    def pop_mean(self) -> float:
        """Mean over the episodes ended since the last call (NaN if none)."""
        ended = torch.cat(self.ended) if self.ended else torch.zeros(0)
        self.ended = []
        return ended.double().mean().item() if ended.numel() else float("nan")
