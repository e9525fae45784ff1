"""One step's log-probability of its action as a function of the actor's parameters:
what ``torch.func`` differentiates step by step for the per-unit gradients of
[`GradientStatistics`][rl_pg.gradient_statistics.GradientStatistics]."""

from __future__ import annotations

import contextlib

import torch
from tensordict import TensorDictBase
from tensordict.nn import CompositeDistribution

__all__ = ["StepLogProb", "actor_parameters"]


def actor_parameters(loss) -> dict[str, torch.Tensor]:
    """The actor's trainable parameters by ``named_parameters`` name (for a functional
    loss, the loss's own copies)."""
    actor = loss.actor_network
    context = (
        loss.actor_network_params.to_module(actor) if loss.functional else contextlib.nullcontext()
    )
    with context:
        params = {name: p for name, p in actor.named_parameters() if p.requires_grad}
    if not params:
        raise ValueError("The loss's actor has no trainable parameter: nothing to measure.")
    return params


class StepLogProb(torch.nn.Module):
    """``log π(a|s)`` of one step (the joint over action dimensions): what
    ``torch.func`` differentiates per step. No checks here: ``vmap`` cannot branch on
    data, and ``unit_gradients`` has run the loss's own checks on the whole batch."""

    def __init__(self, loss) -> None:
        super().__init__()
        self.actor = loss.actor_network
        self.action_key = loss.tensor_keys.action
        # A composite distribution reads its actions under keys of its own: keep all.
        self.composite = any(
            isinstance(cls, type) and issubclass(cls, CompositeDistribution)
            for cls in (getattr(m, "distribution_class", None) for m in self.actor.modules())
        )

    def inputs(self, steps: TensorDictBase) -> TensorDictBase:
        """The entries of ``steps`` the policy and its log-probability read (``vmap``
        splits every entry it is given, so the rest is left behind)."""
        if self.composite:
            return steps
        keys = [k for k in (*self.actor.in_keys, self.action_key) if k in steps.keys(True)]
        return steps.select(*keys)

    def forward(self, step: TensorDictBase) -> torch.Tensor:
        step = step.unsqueeze(0)  # a batch of one, as the policy expects
        dist = self.actor.get_dist(step)
        if isinstance(dist, CompositeDistribution):
            return dist.log_prob(step).sum(dim="feature", reduce=True).sum()
        return dist.log_prob(step.get(self.action_key)).sum()
