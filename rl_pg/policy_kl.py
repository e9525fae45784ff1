"""How far a policy moved: the KL divergence between two of its distributions on the
states of a batch, step by step.

In closed form where torch knows it (categorical, normal, beta, ...); otherwise
estimated from the batch's stored actions, which the old policy sampled:
``E_old[(r − 1) − log r]`` with ``r = π_new(a|s) / π_old(a|s)`` (an unbiased estimate
that is never negative; Schulman 2020, "Approximating KL divergence").
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

__all__ = ["has_closed_form_kl", "kl_per_step", "log_prob_per_step", "masked_mean"]


def has_closed_form_kl(dist: torch.distributions.Distribution) -> bool:
    """Whether torch has the KL divergence between two distributions of ``dist``'s type.

    Examples:
        >>> import torch
        >>> from rl_pg.policy_kl import has_closed_form_kl
        >>> has_closed_form_kl(torch.distributions.Categorical(logits=torch.zeros(3)))
        True
    """
    try:
        torch.distributions.kl_divergence(dist, dist)
    except NotImplementedError:
        return False
    return True


def log_prob_per_step(
    dist: torch.distributions.Distribution, action: torch.Tensor, batch_shape: torch.Size
) -> torch.Tensor:
    """``log π(a|s)`` of the stored actions, one per step (``batch_shape``): summed over
    independent action dimensions.

    Raises:
        ValueError: a log-probability that does not come one per step.
    """
    log_prob = dist.log_prob(action)
    if log_prob.shape[: len(batch_shape)] != batch_shape:
        raise ValueError(
            f"The policy's log-probabilities have shape {tuple(log_prob.shape)}, the batch "
            f"{tuple(batch_shape)}: there must be one action per step."
        )
    return log_prob.reshape(*batch_shape, -1).sum(-1)


def kl_per_step(
    old: torch.distributions.Distribution,
    new: torch.distributions.Distribution,
    tensordict: TensorDictBase,
    *,
    action_key="action",
) -> torch.Tensor:
    """`KL(π_old(·|s_t) ‖ π_new(·|s_t))` at every step of ``tensordict``.

    Args:
        old (Distribution): the policy before, on the batch's states (detached).
        new (Distribution): the policy now, on the same states.
        tensordict (TensorDictBase): the batch, whose ``action_key`` holds the actions
            ``old`` sampled (read only where there is no closed form).

    Keyword Args:
        action_key (NestedKey): the stored actions. Defaults to ``"action"``.

    Returns:
        A tensor of the batch's shape.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rl_pg.policy_kl import kl_per_step
        >>> old = torch.distributions.Categorical(probs=torch.tensor([[0.5, 0.5]]))
        >>> new = torch.distributions.Categorical(probs=torch.tensor([[0.9, 0.1]]))
        >>> batch = TensorDict({"action": torch.tensor([0])}, batch_size=[1])
        >>> kl_per_step(old, new, batch)
        tensor([0.5108])
    """
    shape = tensordict.batch_size
    try:
        kl = torch.distributions.kl_divergence(old, new)
    except NotImplementedError:  # no closed form for this pair: the stored actions
        pass
    else:
        return kl.reshape(*shape, -1).sum(-1)
    action = tensordict.get(action_key)
    log_ratio = log_prob_per_step(new, action, shape) - log_prob_per_step(old, action, shape)
    return torch.expm1(log_ratio) - log_ratio


def masked_mean(values: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
    """The mean of ``values`` (one per step) over the ``valid`` steps (all if None).

    Examples:
        >>> import torch
        >>> from rl_pg.policy_kl import masked_mean
        >>> masked_mean(torch.tensor([1.0, 2.0, 9.0]), torch.tensor([True, True, False]))
        tensor(1.5000)
    """
    if valid is None:
        return values.mean()
    return values[valid.reshape(values.shape)].mean()
