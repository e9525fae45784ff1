"""How a segment of experience is laid out from its steps, as TorchRL's collectors lay
it out: the root the policy acts on at a step, and the steps stacked into a batch
``[environments, T]`` with their ``"next"`` entries (what rl_pg's segment collectors
share)."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

__all__ = ["cleared_flags", "observations_of", "root_of", "segment_of", "stacked"]


def observations_of(env: EnvBase, root: TensorDictBase) -> dict[str, torch.Tensor]:
    return {key: root.get(key) for key in env.observation_spec.keys()}


def cleared_flags(size: torch.Size, device) -> torch.Tensor:
    """Done flags of a root: every root's are False (the environments that finished
    were reset)."""
    return torch.zeros((*size, 1), dtype=torch.bool, device=device)


def root_of(observations: dict, clear: torch.Tensor, size: torch.Size, device) -> TensorDictBase:
    entries = {**observations, "done": clear, "terminated": clear, "truncated": clear}
    return TensorDict._new_unsafe(entries, batch_size=size, device=device)


def segment_of(
    roots: list[TensorDictBase | dict], nexts: list[dict], size: torch.Size, env_device
) -> TensorDictBase:
    """The batch ``[environments, T]`` of a segment's roots (with the policy's outputs;
    TensorDicts, or dicts of tensors of batch size ``size`` on ``env_device``) and
    ``"next"`` entries, as TorchRL's collectors lay it out."""
    # On the policy's device.
    batch = stacked(roots, size, env_device, cleared=("done", "terminated", "truncated"))
    following = TensorDict._new_unsafe(
        {key: torch.stack([step[key] for step in nexts], dim=1) for key in nexts[0]},
        batch_size=batch.batch_size,
        device=env_device,
    )
    return batch.set("next", following.to(batch.device) if batch.device else following)


def stacked(
    roots: list[TensorDictBase | dict], size: torch.Size, device, cleared: tuple[str, ...] = ()
) -> TensorDictBase:
    """``torch.stack(roots, dim=1)``, entry by entry when every entry is a tensor at the
    top level (a tenth of the time for a batch of small steps). The ``cleared`` entries
    are the same all-False tensor in every root (``root_of``'s done flags): one new
    tensor of the stacked shape stands for them. Roots that are dicts of tensors are
    those of batch size ``size`` on ``device``."""
    first = roots[0]
    if isinstance(first, dict):
        entries = roots
    else:
        # A plain TensorDict's own mapping: its entries without a get() call each, which
        # for a segment of small steps cost more than the stacking.
        entries = (
            [root._tensordict for root in roots]
            if all(type(root) is TensorDict for root in roots)
            else [dict(root.items()) for root in roots]
        )
        size, device = first.batch_size, first.device
    values = entries[0]
    if not all(isinstance(value, torch.Tensor) for value in values.values()):
        return torch.stack(roots, dim=1)
    stacked = {}
    for key, value in values.items():
        if key in cleared and all(e.get(key) is value for e in entries) and not value.any():
            shape = (value.shape[0], len(roots), *value.shape[1:])
            stacked[key] = torch.zeros(shape, dtype=value.dtype, device=value.device)
        else:
            stacked[key] = torch.stack([e[key] for e in entries], dim=1)
    return TensorDict._new_unsafe(
        stacked, batch_size=torch.Size([size[0], len(roots)]), device=device
    )
