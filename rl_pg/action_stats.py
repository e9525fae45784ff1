"""How a policy acts. A discrete policy over an evaluation's episodes: the share of
each action, how often it switched action, how often it played its most probable one,
and its entropy (``evaluate(..., action_stats=True)``). A Gaussian policy on bounded
actions over a batch: how often its mean lies beyond the bounds
([`means_beyond_bounds`][rl_pg.action_stats.means_beyond_bounds])."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.modules import IndependentNormal

__all__ = ["action_steps", "describe_actions", "means_beyond_bounds"]


def describe_actions(stats: dict[str, torch.Tensor]) -> dict[str, Any]:
    """The action statistics ``evaluate`` reports, from its per-episode tallies of
    [`action_steps`][rl_pg.action_stats.action_steps]."""
    counts = stats["action_counts"].sum(0)
    steps = counts.sum().clamp(min=1)
    after_first = (stats["length"].sum() - (stats["length"] > 0).sum()).clamp(min=1)
    return {
        "action_shares": (counts / steps).tolist(),
        "action_switch_rate": (stats["action_switches"].sum() / after_first).item(),
        "greedy_action_rate": (stats["action_greedy"].sum() / steps).item(),
        "mean_entropy": (stats["action_entropy"].sum() / steps).item(),
    }


def action_steps(
    tensordict: TensorDictBase, n: int, steps: int, previous: torch.Tensor
) -> tuple[dict[str, torch.Tensor], torch.Tensor] | None:
    """What each step of an ``[n, steps]`` rollout adds to ``evaluate``'s action
    statistics (a one-hot of the discrete action; whether it differs from the one before
    in its episode; whether it is the policy's most probable; the policy's entropy), and
    each environment's last action. ``previous`` holds each environment's action before
    the rollout (-1: its episode starts with it). None for a policy without logits."""
    logits, action = tensordict.get("logits", None), tensordict.get("action", None)
    if logits is None or action is None or logits.numel() != n * steps * logits.shape[-1]:
        return None
    logits = logits.reshape(n, steps, logits.shape[-1]).float()
    num_actions = logits.shape[-1]
    action = action.reshape(n, steps, -1)
    if action.shape[-1] == num_actions and num_actions > 1:  # one-hot
        index = action.argmax(-1)
    elif action.shape[-1] == 1:
        index = action[..., 0].long()
    else:
        return None
    done = tensordict.get(("next", "done")).reshape(n, steps, -1).any(-1)
    starts = torch.cat([torch.zeros_like(done[:, :1]), done[:, :-1]], dim=1)
    before = torch.cat([previous.to(index.device)[:, None], index[:, :-1]], dim=1)
    before = before.masked_fill(starts, -1)
    per_step = {
        "action_counts": torch.nn.functional.one_hot(index, num_actions).float(),
        "action_switches": ((before >= 0) & (before != index)).float(),
        "action_greedy": (index == logits.argmax(-1)).float(),
        "action_entropy": torch.distributions.Categorical(logits=logits).entropy(),
    }
    return per_step, index[:, -1]


def means_beyond_bounds(actor, batch: TensorDictBase) -> float | None:
    """For a Gaussian policy on a bounded action whose samples the environment clips
    (``mlp_actor(bounded="normal")``): the largest share, over the action's dimensions,
    of the batch's steps whose mean lies outside the bounds; None for other policies.

    Where the mean is far past a bound, almost every sample is clipped to it and the
    policy learns nothing more about that dimension (a MetaDrive driver stuck at full
    throttle showed 0.97-0.99 here); a Beta policy (``bounded="beta"``) keeps its
    mean inside.

    Examples:
        >>> import torch
        >>> from rl_pg.envs import gym_env
        >>> from rl_pg.models import mlp_actor
        >>> env = gym_env("Pendulum-v1")  # torque in [-2, 2]
        >>> actor = mlp_actor(env, bounded="normal")
        >>> batch = env.rollout(4, actor)
        >>> batch["loc"] = torch.tensor([[3.0], [0.0], [-2.5], [1.0]])
        >>> means_beyond_bounds(actor, batch)
        0.5
    """
    head = getattr(actor, "module", [None])[-1]
    if getattr(head, "distribution_class", None) is not IndependentNormal:
        return None
    spec = getattr(actor, "spec", None)
    action = spec.get("action", None) if spec is not None else None
    space = getattr(action, "space", None)
    loc = batch.get("loc", None)
    if loc is None or not hasattr(space, "low"):
        return None
    low, high = (_like(bound.to(loc.device), loc) for bound in (space.low, space.high))
    beyond = ((loc < low) | (loc > high)).reshape(-1, loc.shape[-1]).float().mean(0)
    return beyond.max().item()


def _like(bound: torch.Tensor, loc: torch.Tensor) -> torch.Tensor:
    """A batched environment's bounds (``[envs, dims]``) laid against a batch of its
    steps: ``[envs, time, dims]`` segments, or steps flattened to ``[n, dims]``."""
    if bound.dim() > 1 and loc.dim() == bound.dim() + 1 and loc.shape[:-2] == bound.shape[:-1]:
        return bound.unsqueeze(-2)  # the time dimension of each environment's segment
    if bound.dim() > 1 and loc.shape[:-1] != bound.shape[:-1]:
        return bound.reshape(-1, bound.shape[-1])[0]  # copies of one environment
    return bound
