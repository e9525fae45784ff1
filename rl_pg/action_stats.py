"""How a discrete policy acted over an evaluation's episodes: the share of each
action, how often it switched action, how often it played its most probable one, and
its entropy (``evaluate(..., action_stats=True)``)."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

__all__ = ["action_steps", "describe_actions"]


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
