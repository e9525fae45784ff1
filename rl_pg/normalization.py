"""Running statistics that a model keeps: observation standardisation and a PopArt
value head (both update only when the learner says so, never while acting)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torchrl.modules import PopArtValueNorm, RunningValueNorm, ValueNorm

from rl_pg._checks import check_real

__all__ = ["PopArt", "RunningNorm", "popart_output", "update_running_norms"]


class RunningNorm(nn.Module):
    """Standardises an observation with running statistics the learner keeps.

    ``(x - mean) / std`` per feature, clipped to ``[-clip, clip]``, with the mean and
    variance of every observation passed to [`update`][rl_pg.normalization.RunningNorm.update]
    (TorchRL's ``RunningValueNorm``, Welford's algorithm); the identity until the first
    update. Features of small spread (MetaDrive's heading and lane position vary by
    about 0.04 around 0.5) then weigh as much as the others from the first layer on.

    The statistics are buffers: they are saved with the model, reach collector workers
    with the weights, and change only when ``update`` is called (the training loop calls
    it after each optimiser step, on the batch's observations, see
    [`update_running_norms`][rl_pg.normalization.update_running_norms]), never while acting.

    Args:
        shape (int or tuple of int): the shape of one observation.

    Keyword Args:
        key (str): the batch entry ``update_running_norms`` reads. Defaults to
            ``"observation"``.
        clip (float): bound of the standardised values. Defaults to ``5.0``.
        min_std (float): floor of the standard deviation (a constant feature is not
            blown up). Defaults to ``1e-2``.

    Examples:
        >>> import torch
        >>> from rl_pg.normalization import RunningNorm
        >>> norm = RunningNorm(2)
        >>> x = torch.tensor([[0.5, 10.0], [0.6, 30.0]])
        >>> torch.equal(norm(x), x)  # no statistics yet
        True
        >>> norm.update(x)
        >>> norm(x)
        tensor([[-1., -1.],
                [ 1.,  1.]])
    """

    def __init__(
        self,
        shape: int | Sequence[int],
        *,
        key: str = "observation",
        clip: float = 5.0,
        min_std: float = 1e-2,
    ) -> None:
        super().__init__()
        clip = check_real(
            "clip", clip, low=0, low_open=True, hint="Values are clipped to [-clip, clip]."
        )
        min_std = check_real(
            "min_std", min_std, low=0, low_open=True,
            hint="It floors the standard deviation each feature is divided by.",
        )  # fmt: skip
        self.stats = RunningValueNorm(shape=shape, epsilon=min_std**2)
        self.key = key
        self.clip = clip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        normalised = self.stats.normalize(x).clamp(-self.clip, self.clip)
        return torch.where(self.stats.count > 0, normalised, x)

    def update(self, x: torch.Tensor) -> None:
        """Adds the observations ``x`` (``[*batch, *shape]``) to the statistics.

        Raises:
            ValueError: ``x`` holds NaN or inf; the statistics are left as they were.
        """
        x = x.detach().to(self.stats.mean.dtype)
        _refuse_non_finite(x, f"RunningNorm({self.key!r})", "observations")
        self.stats.update(x)


def _refuse_non_finite(x: torch.Tensor, who: str, what: str) -> None:
    """A batch with NaN or inf would poison running statistics for good: refused whole."""
    if not torch.isfinite(x).all():
        bad = int((~torch.isfinite(x)).sum())
        raise ValueError(
            f"{who} got {bad} non-finite {what} (NaN or inf); its statistics are left as "
            f"they were. Find where the batch's {what} became non-finite (the environment, "
            f"a reward or a return) before updating again."
        )


def update_running_norms(module: nn.Module, batch) -> None:
    """Updates every [`RunningNorm`][rl_pg.normalization.RunningNorm] inside ``module`` (each
    once, shared or not) with the batch's observations at its ``key``."""
    seen = set()
    for norm in module.modules():
        if isinstance(norm, RunningNorm) and id(norm) not in seen:
            seen.add(id(norm))
            norm.update(batch.get(norm.key))


class PopArt(ValueNorm):
    """A critic's output layer that learns in normalised units and answers in real ones.

    The layer ``linear`` predicts the standardised value `ν = (V − μ) / σ`; the module
    returns `V = σ ν + μ` with the running mean `μ` and scale `σ` of the value targets
    (PopArt: van Hasselt et al., 2016, "Learning values across many orders of
    magnitude"). Each [`update`][rl_pg.normalization.PopArt.update] moves `μ` and `σ` and
    rescales ``linear`` so that every output stays exactly what it was ("preserving
    outputs precisely"). Returns in the hundreds then cost the critic no more steps
    than returns near one: Adam moves each weight by about the learning rate, and the
    last layer's weights need only reach `ν`, of order one.

    A [`ReinforceLoss`][rl_pg.ReinforceLoss] given this module as ``value_norm``
    updates it once per batch, from the batch's value targets, and regresses `ν` on the
    standardised targets; advantages and bootstraps use `V`, at the rewards' scale.

    It is a TorchRL ``ValueNorm`` (``update``, ``normalize``, ``denormalize``,
    ``scale``); the statistics are those of ``stats``.

    Args:
        linear (nn.Linear): the output layer, one output per value (usually 1).

    Keyword Args:
        stats (ValueNorm, optional): the running statistics. Defaults to TorchRL's
            ``PopArtValueNorm(beta=0.99)``: an exponential average over about the last
            hundred batches, unbiased from the first.

    Examples:
        >>> import torch
        >>> from rl_pg.normalization import PopArt
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> head = PopArt(torch.nn.Linear(4, 1))
        >>> x = torch.randn(8, 4)
        >>> head.update(100 + 50 * torch.randn(256, 1))  # the first: no outputs to keep
        >>> before = head(x)
        >>> head.update(300 + 80 * torch.randn(256, 1))
        >>> torch.allclose(head(x), before, atol=1e-4)  # the outputs are preserved
        True
        >>> round(head.scale().item(), -1)  # σ of the targets seen so far
        120.0
    """

    def __init__(self, linear: nn.Linear, *, stats: ValueNorm | None = None) -> None:
        if not isinstance(linear, nn.Linear):
            raise TypeError(
                f"PopArt rescales an nn.Linear output layer, got {type(linear).__name__}."
            )
        if stats is None:
            stats = PopArtValueNorm(shape=linear.out_features, beta=0.99)
        if not isinstance(stats, ValueNorm):
            raise TypeError(
                f"stats must be a torchrl.modules.ValueNorm (e.g. PopArtValueNorm), got "
                f"{type(stats).__name__}."
            )
        if tuple(stats.shape) != (linear.out_features,):
            raise ValueError(
                f"stats has shape {tuple(stats.shape)} but the layer has "
                f"{linear.out_features} output(s): build stats with shape={linear.out_features}."
            )
        super().__init__(shape=stats.shape, epsilon=stats.epsilon)
        self.linear = linear
        self.stats = stats
        # denormalize(ν) = σ ν + μ, read from ``stats`` at each update: the identity until
        # the first, which has no trained outputs to preserve.
        self.register_buffer("mean", linear.weight.new_zeros(self.shape))
        self.register_buffer("std", linear.weight.new_ones(self.shape))
        self.register_buffer("updated", torch.zeros((), dtype=torch.bool))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.denormalize(self.linear(x))

    @torch.no_grad()
    def update(self, value_target: torch.Tensor) -> None:
        """Adds the targets ``value_target`` (``[*batch, out_features]``) to the
        statistics and rescales the layer so that its outputs do not change."""
        value_target = value_target.detach().to(self.mean.dtype)
        _refuse_non_finite(value_target, "PopArt", "value targets")
        old_mean, old_std = self.mean.clone(), self.std.clone()
        self.stats.update(value_target)
        zero = torch.zeros_like(self.mean)
        self.mean.copy_(self.stats.denormalize(zero))
        self.std.copy_(self.stats.denormalize(zero + 1) - self.mean)
        if not bool(self.updated):
            self.updated.fill_(True)
            return
        self.linear.weight.mul_((old_std / self.std).unsqueeze(-1))
        if self.linear.bias is not None:
            self.linear.bias.mul_(old_std).add_(old_mean - self.mean).div_(self.std)

    def normalize(self, value_target: torch.Tensor) -> torch.Tensor:
        return (value_target - self.mean) / self.std

    def denormalize(self, normalised_value: torch.Tensor) -> torch.Tensor:
        return normalised_value * self.std + self.mean

    def scale(self) -> torch.Tensor:
        return self.std


def popart_output(critic: nn.Module) -> PopArt:
    """Makes the critic's output layer a [`PopArt`][rl_pg.normalization.PopArt] one, in place.

    The last ``nn.Linear`` in ``critic`` (its output layer, in any critic built from
    TorchRL's ``MLP`` or ``nn.Sequential``) is wrapped with its current weights; a
    critic whose output layer is already ``PopArt`` is left as it is. Give the result to
    [`ReinforceLoss`][rl_pg.ReinforceLoss] as ``value_norm``. Wrap a critic before it
    trains: the first update sets the statistics without preserving the outputs (a
    fresh critic's are noise near 0, and preserving them would leave its normalised
    output as far from the targets as the raw one was).

    Raises:
        ValueError: the critic has no ``nn.Linear`` layer.

    Examples:
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_critic
        >>> from rl_pg.normalization import popart_output
        >>> critic = mlp_critic(GridWorldEnv(), hidden=(8,))
        >>> head = popart_output(critic)
        >>> head is popart_output(critic), type(head).__name__
        (True, 'PopArt')
    """
    existing = [module for module in critic.modules() if isinstance(module, PopArt)]
    if existing:
        return existing[-1]
    last = None
    for name, module in critic.named_modules():
        if isinstance(module, nn.Linear):
            last = name
    if last is None:
        raise ValueError(
            f"popart_output needs a critic whose output layer is an nn.Linear; "
            f"{type(critic).__name__} has none."
        )
    parent_name, _, child = last.rpartition(".")
    parent = critic.get_submodule(parent_name)
    head = PopArt(getattr(parent, child))
    setattr(parent, child, head)
    return head
