"""Scalar baselines for REINFORCE, as modules whose state lives in buffers.

A baseline ``b`` is subtracted from the return before it weights ``log pi``. Any
``b`` that does not depend on the current batch's actions leaves the gradient
unbiased, which is why the stateful baselines answer with their value *before* they
take in the batch's returns. [`BatchMean`][rl_pg.baselines.BatchMean] is the exception
(it uses the batch itself) and carries an `O(1/N)` bias for a batch of ``N`` episodes.

Each baseline is called with the batch's episode returns, answers the ``b`` to
subtract, and, in training mode, then updates its state. The state is saved in the
module's ``state_dict``, so a resumed run continues with the same baseline.
"""

from __future__ import annotations

import torch
from torch import nn

from rl_pg._checks import check_real, check_tensor

__all__ = ["BASELINES", "BatchMean", "ExponentialMovingAverage", "RunningMean", "make_baseline"]


class BatchMean(nn.Module):
    """The mean of the current batch's episode returns.

    Examples:
        >>> import torch
        >>> from rl_pg.baselines import BatchMean
        >>> BatchMean()(torch.tensor([1.0, 2.0, 6.0]))
        tensor(3.)
    """

    def forward(self, returns: torch.Tensor) -> torch.Tensor:
        """Returns ``returns.mean()``."""
        _check_returns(returns)
        return returns.detach().mean()


class RunningMean(nn.Module):
    """The mean of every episode return seen so far (0 before the first batch).

    Examples:
        >>> import torch
        >>> from rl_pg.baselines import RunningMean
        >>> baseline = RunningMean()
        >>> baseline(torch.tensor([1.0, 3.0]))  # nothing seen yet
        tensor(0.)
        >>> baseline(torch.tensor([8.0]))  # mean of 1, 3
        tensor(2.)
        >>> baseline.value
        tensor(4.)
    """

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("total", torch.zeros((), dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.int64))

    @property
    def value(self) -> torch.Tensor:
        """The current baseline."""
        if self.count == 0:
            return torch.zeros((), dtype=torch.float32, device=self.total.device)
        return (self.total / self.count).float()

    def forward(self, returns: torch.Tensor) -> torch.Tensor:
        """Returns the baseline before ``returns``, then (in training mode) takes them in."""
        _check_returns(returns)
        baseline = self.value.to(returns.dtype)
        if self.training:
            self.total += returns.detach().double().sum()
            self.count += returns.numel()
        return baseline


class ExponentialMovingAverage(nn.Module):
    """`b ← (1 − α) b + α R` per episode return ``R``, from 0.

    The episodes of a batch are taken in order, which is the same as applying the
    update once per episode.

    Keyword Args:
        rate (float): `α`, in ``(0, 1]``. Defaults to ``0.01``.

    Examples:
        >>> import torch
        >>> from rl_pg.baselines import ExponentialMovingAverage
        >>> baseline = ExponentialMovingAverage(rate=0.5)
        >>> baseline(torch.tensor([4.0, 8.0]))
        tensor(0.)
        >>> baseline.value  # 0 -> 2 -> 5
        tensor(5.)
    """

    def __init__(self, *, rate: float = 0.01) -> None:
        super().__init__()
        self.rate = check_real("rate", rate, low=0, low_open=True, high=1)
        self.register_buffer("_value", torch.zeros((), dtype=torch.float64))

    @property
    def value(self) -> torch.Tensor:
        """The current baseline."""
        return self._value.float()

    def forward(self, returns: torch.Tensor) -> torch.Tensor:
        """Returns the baseline before ``returns``, then (in training mode) takes them in."""
        _check_returns(returns)
        baseline = self.value.to(returns.dtype)
        if self.training:
            returns = returns.detach().double().flatten()
            n = returns.numel()
            keep = 1.0 - self.rate
            # Closed form of n sequential updates: the i-th return is discounted by
            # keep ** (n - 1 - i).
            weights = self.rate * keep ** torch.arange(
                n - 1, -1, -1, dtype=torch.float64, device=returns.device
            )
            self._value.mul_(keep**n).add_((weights * returns).sum())
        return baseline


BASELINES = {
    "batch_mean": BatchMean,
    "running_mean": RunningMean,
    "ema": ExponentialMovingAverage,
}


def make_baseline(name: str, *, rate: float = 0.01) -> nn.Module:
    """Builds the scalar baseline called ``name`` (a key of ``BASELINES``).

    Keyword Args:
        rate (float): the rate of ``"ema"``. Defaults to ``0.01``.

    Examples:
        >>> from rl_pg.baselines import make_baseline
        >>> make_baseline("ema", rate=0.1).rate
        0.1
    """
    if name not in BASELINES:
        raise ValueError(f"Unknown baseline {name!r}; expected one of {sorted(BASELINES)}.")
    return BASELINES[name](rate=rate) if name == "ema" else BASELINES[name]()


def _check_returns(returns: torch.Tensor) -> None:
    check_tensor("returns", returns, hint="Pass the episode returns as a tensor.")
    if not returns.is_floating_point():
        raise TypeError(f"returns must be a floating-point tensor, got dtype {returns.dtype}.")
    if returns.numel() == 0:
        raise ValueError("A baseline needs at least one episode return, got an empty tensor.")
    if not bool(torch.isfinite(returns).all()):
        # Taken in, a single NaN would be the baseline of every later batch.
        raise ValueError(
            f"returns holds {int((~torch.isfinite(returns)).sum())} non-finite value(s); the "
            f"baseline was left as it was. Check the rewards that produced them."
        )
