"""Policy distributions for bounded continuous actions."""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import distributions as D
from torch import nn

__all__ = ["BetaConcentrations", "BoundedBeta"]


class BoundedBeta(D.TransformedDistribution):
    """Independent Beta distributions stretched onto per-dimension bounds ``[low, high]``.

    A bounded action needs no squashing or clipping under a Beta policy (Chou, Maturana
    and Scherer, ICML 2017): every sample lies inside the bounds and its
    log-probability is exact, so the score-function estimator is unbiased there too.
    A Gaussian clipped by the environment puts the mass beyond a bound onto the bound
    and stops learning once its mean drifts past it; a ``TanhNormal`` keeps the samples
    inside but, past a few units of mean, rounds them to the bound in float32, where
    the log-probability the loss recomputes is no longer theirs.

    The last dimension is the action's (``event_dim=1``), as for TorchRL's
    ``IndependentNormal``. A deterministic action (greedy evaluation) is the mean.

    Args:
        concentration1 (Tensor): the Beta's alpha, > 0.
        concentration0 (Tensor): the Beta's beta, > 0.
        low (Tensor or float): the lower bound of each action dimension.
        high (Tensor or float): the upper bound of each action dimension (> low).

    Examples:
        >>> import torch
        >>> from rl_pg.distributions import BoundedBeta
        >>> dist = BoundedBeta(torch.tensor([2.0]), torch.tensor([2.0]), -2.0, 2.0)
        >>> dist.deterministic_sample
        tensor([0.])
        >>> sample = dist.sample((1000,))
        >>> bool((sample.abs() <= 2).all())
        True
        >>> round(dist.log_prob(torch.tensor([0.0])).exp().item(), 4)  # 1.5 / 4
        0.375
    """

    arg_constraints: ClassVar[dict] = {}  # the Beta checks its own
    has_rsample = True

    def __init__(self, concentration1, concentration0, low, high, validate_args=None):
        concentration1 = torch.as_tensor(concentration1)
        low = torch.as_tensor(low, dtype=concentration1.dtype, device=concentration1.device)
        high = torch.as_tensor(high, dtype=concentration1.dtype, device=concentration1.device)
        if not bool((high > low).all()):
            raise ValueError(
                f"BoundedBeta needs high > low in every dimension, got low={low.tolist()}, "
                f"high={high.tolist()}."
            )
        self.low, self.high = low, high
        base = D.Independent(D.Beta(concentration1, concentration0), 1)
        super().__init__(
            base, [D.AffineTransform(low, high - low, event_dim=1)], validate_args=False
        )

    @property
    def _beta(self) -> D.Beta:
        return self.base_dist.base_dist

    @property
    def mean(self) -> torch.Tensor:
        return self.low + (self.high - self.low) * self._beta.mean

    @property
    def variance(self) -> torch.Tensor:
        return (self.high - self.low) ** 2 * self._beta.variance

    @property
    def deterministic_sample(self) -> torch.Tensor:
        """The mean: what greedy evaluation plays."""
        return self.mean

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        # A sample can round onto a bound in float32, where a Beta with concentrations
        # above 1 has density 0: score it a float's width inside instead.
        unit = (value - self.low) / (self.high - self.low)
        eps = torch.finfo(unit.dtype).eps
        unit = unit.clamp(eps, 1 - eps)
        return self.base_dist.log_prob(unit) - torch.log(self.high - self.low).expand_as(unit).sum(
            -1
        )

    def entropy(self) -> torch.Tensor:
        return self.base_dist.entropy() + torch.log(self.high - self.low).expand(
            self.batch_shape + self.event_shape
        ).sum(-1)


class BetaConcentrations(nn.Module):
    """Splits a network's ``2 * n`` outputs into the two concentrations of ``n`` Betas,
    each ``1 + softplus(x)``: above 1, so every Beta is unimodal with density 0 at the
    bounds (never infinite), and 1.69 (about uniform) for outputs near 0.

    Examples:
        >>> import torch
        >>> from rl_pg.distributions import BetaConcentrations
        >>> alpha, beta = BetaConcentrations()(torch.zeros(3, 4))
        >>> alpha.shape, round(alpha[0, 0].item(), 3)
        (torch.Size([3, 2]), 1.693)
    """

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if x.shape[-1] % 2:
            raise ValueError(
                f"BetaConcentrations needs an even number of outputs (two per action "
                f"dimension), got {x.shape[-1]}."
            )
        alpha, beta = x.chunk(2, dim=-1)
        return 1 + nn.functional.softplus(alpha), 1 + nn.functional.softplus(beta)
