"""What a run measures and where it goes: training-episode returns and the loggers."""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.record.loggers import CSVLogger, Logger, TensorboardLogger

from rl_pg.checkpoint import write_atomically
from rl_pg.functional import discounted_return

__all__ = ["EpisodeReturns", "Loggers", "scalar_log_rows"]


class EpisodeReturns:
    """Undiscounted returns of the training episodes that end in the batches.

    With segments an episode spans batches: each environment's unfinished sum is
    carried into its next segment's first reward, and the same whole-episode return
    kernel reads every ended episode. (A per-step transform such as TorchRL's
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
        done = batch["next", "done"].reshape(*batch.shape, -1).any(-1)
        reward = batch["next", "reward"].reshape(*batch.shape, -1).sum(-1)
        done = done.reshape(-1, done.shape[-1])  # [environments, T]
        reward = reward.reshape(done.shape).clone()
        if self.partial is not None and self.partial.shape[0] == reward.shape[0]:
            reward[:, 0] += self.partial
        self.ended.append(discounted_return(reward, done, 1.0, time_dim=-1)[done])
        if self.carry:  # what follows each row's last episode end is still in flight
            in_flight = done.flip(-1).cumsum(-1).flip(-1) == 0
            self.partial = (reward * in_flight).sum(-1)

    def pop_mean(self) -> float:
        """Mean over the episodes ended since the last call (NaN if none)."""
        ended = torch.cat(self.ended) if self.ended else torch.zeros(0)
        self.ended = []
        return ended.float().mean().item() if ended.numel() else float("nan")


class Loggers:
    """Sends each scalar to every TorchRL logger of the run (CSV, and TensorBoard if asked).

    Args:
        log_dir (Path): the run's ``logs`` directory.

    Keyword Args:
        tensorboard (bool): also write TensorBoard event files.
        resume_at (int, optional): frames of the checkpoint a resumed run starts from;
            rows logged after it by the killed run are dropped first (they are redone).
    """

    def __init__(self, log_dir: Path, *, tensorboard: bool, resume_at: int | None) -> None:
        if resume_at is not None:
            _trim_csv_logs(log_dir, resume_at)
        self.loggers: list[Logger] = [CSVLogger(exp_name="csv", log_dir=str(log_dir))]
        if tensorboard:
            self.loggers.append(TensorboardLogger(exp_name="tensorboard", log_dir=str(log_dir)))

    def log_scalar(self, name: str, value: float, step: int) -> None:
        for logger in self.loggers:
            logger.log_scalar(name, value, step=step)


def _trim_csv_logs(log_dir: Path, frames: int) -> None:
    """Drops the rows a killed run logged after its last checkpoint (they are redone).

    Each file is replaced atomically: a run killed while trimming leaves the file as
    it was, and the next resume trims it again. A row cut short by the kill (no
    newline, or not two numbers) is dropped with the rest.
    """
    for path in log_dir.glob("csv/scalars/**/*.csv"):
        text = path.read_text()
        rows = text.split("\n")[:-1]  # what follows the last newline is a torn row
        kept = [row for row in rows if (parsed := _parse_row(row)) and parsed[0] <= frames]
        if len(kept) != len(rows) or not text.endswith("\n"):
            write_atomically(path, "".join(f"{row}\n" for row in kept))


def scalar_log_rows(text: str) -> list[tuple[float, float]]:
    """The complete ``step,value`` rows of a CSV scalar log.

    What follows the last newline, or a row that is not two numbers, was cut short by
    a killed run and is left out.

    Examples:
        >>> from rl_pg.training import scalar_log_rows
        >>> scalar_log_rows("64,0.5\\n128,0.75\\n19")
        [(64.0, 0.5), (128.0, 0.75)]
    """
    return [parsed for row in text.split("\n")[:-1] if (parsed := _parse_row(row))]


def _parse_row(row: str) -> tuple[float, float] | None:
    fields = row.split(",")
    if len(fields) != 2:
        return None
    try:
        return float(fields[0]), float(fields[1])
    except ValueError:
        return None
