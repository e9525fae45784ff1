"""What the loss requires of a batch before it scores ``log π``: one action per step,
shaped as the policy writes it and inside its support, per-step quantities in the
returns' ``[*B, 1]`` shape, and the entries it reads present. Each check names what was
wrong and how to fix it; none lets a batch through to a silently wrong loss."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictModule
from torchrl.data import Bounded, Composite
from torchrl.modules import MaskedOneHotCategorical, OneHotCategorical

__all__ = [
    "ONE_HOT_DISTRIBUTIONS",
    "check_action_shape",
    "check_not_empty",
    "check_support",
    "declares_bounds",
    "per_step",
    "required",
    "step_column",
]

ONE_HOT_DISTRIBUTIONS = (
    torch.distributions.OneHotCategorical,
    OneHotCategorical,
    MaskedOneHotCategorical,
)
"""Policies whose actions are one-hot rows (TorchRL's declare no event shape)."""


def check_not_empty(tensordict: TensorDictBase) -> None:
    # ``TensorDict.numel()`` is 1 for a batch of zero rows: count the batch itself.
    if tensordict.batch_size.numel() == 0:
        raise ValueError(
            f"ReinforceLoss got an empty batch (batch_size={tuple(tensordict.batch_size)}):"
            " there is no step to learn from. Collect at least one step."
        )


def required(tensordict: TensorDictBase, key, hint: str, lead: str = "") -> torch.Tensor:
    """``tensordict[key]``, or a KeyError in TorchRL's words (``lead``, then ``hint``)."""
    value = tensordict.get(key, None)
    if value is None:
        raise KeyError(f"{lead}the key {key} was not found in the input tensordict. {hint}")
    return value


def step_column(value: torch.Tensor, batch_size: torch.Size, key) -> torch.Tensor:
    """A per-step quantity as ``[*batch_size, ..., 1]`` (one column per step)."""
    if value.shape == batch_size:
        return value.unsqueeze(-1)
    if value.shape[: len(batch_size)] == batch_size and value.shape[len(batch_size) :][-1:] == (1,):
        return value
    raise ValueError(
        f"{key!r} has shape {tuple(value.shape)}, but the batch is {tuple(batch_size)}: "
        f"expected {(*batch_size, 1)} (or {tuple(batch_size)}), one value per step."
    )


def declares_bounds(actor) -> bool:
    """Whether the policy declares action bounds: a bounded action spec, or ``low`` /
    ``high`` given to its distribution.

    TorchRL's own tests score actions drawn from ``randn`` under a ``TanhNormal`` whose
    spec is unbounded; only bounds the user stated are enforced, so that they pass.
    """
    spec = getattr(actor, "spec", None)
    if spec is not None and any(
        isinstance(leaf, Bounded) and leaf.dtype.is_floating_point
        for leaf in (spec.values(True, True) if isinstance(spec, Composite) else [spec])
    ):
        return True
    return any(
        {"low", "high"} & set(getattr(module, "distribution_kwargs", None) or {})
        for module in actor.modules()
        if isinstance(module, ProbabilisticTensorDictModule)
    )


def check_action_shape(dist, action: torch.Tensor, key, batch: torch.Size) -> None:
    """Refuses stored actions shaped unlike the ones the policy's distribution scores.

    ``log_prob`` broadcasts them instead: a categorical policy's ``[*B, 1]`` actions
    against its ``[*B]`` batch give a ``[*B, *B]``-like table of wrong log-probabilities,
    or a shape error that names neither. A distribution that does not declare the
    batch's shape (a custom one without ``batch_shape``) is left to its own checks.
    """
    if isinstance(dist, ONE_HOT_DISTRIBUTIONS):  # TorchRL's declare no event shape
        expected = dist.logits.shape
    else:
        expected = dist.batch_shape + dist.event_shape
    if expected[: len(batch)] == batch and action.shape != expected:
        raise ValueError(
            f"The stored actions at {key!r} have shape {tuple(action.shape)}, but the "
            f"policy's {type(dist).__name__} scores actions of shape {tuple(expected)}: "
            f"store each step's action as the policy writes it (for a categorical policy, "
            f"an index per step without a trailing dimension of 1)."
        )


def check_support(dist, action: torch.Tensor, key, declared_bounds: bool) -> None:
    """Refuses stored actions the policy cannot have taken.

    ``log_prob`` does not: a categorical policy truncates ``1.7`` to ``1`` and a bounded
    continuous policy scores an action beyond its bounds as if it were on them.
    """
    if type(dist) is torch.distributions.Categorical and not action.is_floating_point():
        # Integer indices: inside the support iff within [0, K); one pass over them
        # instead of the support's three comparisons (the full check below names a miss).
        low, high = action.aminmax()
        if bool((low >= 0) & (high < dist.logits.shape[-1])):
            return
    low, high = getattr(dist, "low", None), getattr(dist, "high", None)
    if isinstance(dist, ONE_HOT_DISTRIBUTIONS):
        # TorchRL's one-hot categorical reports Categorical's integer support.
        inside = ((action == 0) | (action == 1)).all(-1) & (action.sum(-1) == 1)
        expected = "one-hot rows (a single 1, zeros elsewhere)"
    elif isinstance(low, torch.Tensor) and isinstance(high, torch.Tensor):
        if not declared_bounds:
            return
        inside = (action >= low) & (action <= high)
        expected = f"inside the policy's bounds [{low.min().item():g}, {high.max().item():g}]"
    else:
        try:
            inside = dist.support.check(action)
        except (NotImplementedError, TypeError, AttributeError, RuntimeError):
            return  # no usable support: nothing to check against
        expected = f"in the policy's support ({dist.support})"
    if not bool(inside.all()):
        bad = action.reshape(-1, *action.shape[inside.ndim :])[~inside.reshape(-1)]
        raise ValueError(
            f"{int((~inside).sum())} stored action(s) at {key!r} are not {expected}: for "
            f"example {bad[0].tolist()}. log pi would be meaningless. Store the actions the "
            f"policy sampled (integer indices for a categorical policy, one-hot rows for "
            f"a one-hot one, values within the action bounds for a continuous one)."
        )


def per_step(values: torch.Tensor, shape: torch.Size, what: str) -> torch.Tensor:
    """Brings per-step policy quantities to the ``[*B, 1]`` shape of the returns."""
    batch_shape = shape[:-1]
    if values.shape == batch_shape:
        values = values.unsqueeze(-1)
    elif values.shape[: len(batch_shape)] == batch_shape and values.ndim > len(batch_shape):
        # One number per independent action dimension: the joint is their sum.
        values = values.flatten(len(batch_shape)).sum(-1, keepdim=True)
    if values.shape == shape:
        return values
    raise ValueError(
        f"The policy's {what} have shape {tuple(values.shape)} but the returns have shape "
        f"{tuple(shape)}: there must be one action per step."
    )
