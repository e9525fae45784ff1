"""How noisy a gradient estimate is, from the gradients of its independent units.

REINFORCE estimates `∇J` by averaging independent units (whole episodes, or one
environment's segment each): unit `u` contributes `g_u = Σ_{t∈u} Ψ_t ∇ log π(a_t|s_t)`.
From `U` such gradients of one batch, at the parameters that collected it:

* ``trace_covariance``: `tr Σ`, the unbiased per-unit variance summed over parameters;
* ``grad_norm_sq``: an unbiased estimate of `|∇J|²`, `|ḡ|² − tr Σ / U` (it can come out
  negative when the batch cannot tell the signal from zero);
* ``noise_scale``: `B = tr Σ / |∇J|²`, the batch size (in units) at which noise and
  signal are equal (McCandlish et al., 2018); NaN when ``grad_norm_sq`` is not positive;
* ``snr``: `|∇J|² / (tr Σ / U) = U / B`, the signal-to-noise ratio of the batch's mean
  gradient at the batch size used;
* ``half_cosine``: the cosine between the mean gradients of two disjoint halves of the
  units (even and odd), near 1 when the batch is large enough to agree with itself.

[`unit_index`][rl_pg.gradient_noise.unit_index] numbers the units of a batch;
[`noise_statistics`][rl_pg.gradient_noise.noise_statistics] is the pure function on a
``[…, U, P]`` tensor of unit gradients.
[`GradientStatistics`][rl_pg.gradient_statistics.GradientStatistics] computes those
gradients from a loss and a batch.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from rl_pg._checks import check_choice

__all__ = ["UNITS", "noise_statistics", "unit_index"]

UNITS = ("episode", "row", "group")
"""What one unit gradient sums: an episode's steps, a row's, or a group's episodes'."""


def noise_statistics(unit_gradients: torch.Tensor) -> TensorDict:
    """The spread of ``U`` independent unit gradients ``[..., U, P]`` (module docstring).

    Args:
        unit_gradients (torch.Tensor): one flattened gradient per unit, ``[U, P]``, or
            several sets of them ``[*S, U, P]`` (e.g. one per estimator), ``U >= 2``.

    Returns:
        A ``TensorDict(batch_size=S)`` with ``mean_gradient`` (``[*S, P]``), ``units``,
        ``mean_grad_norm_sq`` (`|ḡ|²`), ``grad_norm_sq``, ``trace_covariance``,
        ``noise_scale``, ``snr`` and ``half_cosine``.

    Raises:
        ValueError: fewer than two dimensions or two units, or non-finite entries.

    Examples:
        >>> import torch
        >>> from rl_pg.gradient_noise import noise_statistics
        >>> g = torch.tensor([[1.0, 0.0], [3.0, 0.0], [1.0, 2.0], [3.0, -2.0]])
        >>> stats = noise_statistics(g)
        >>> stats["mean_gradient"], stats["trace_covariance"].item()
        (tensor([2., 0.]), 4.0)
        >>> stats["grad_norm_sq"].item(), stats["noise_scale"].item(), stats["snr"].item()
        (3.0, 1.3333333730697632, 3.0)
    """
    if not isinstance(unit_gradients, torch.Tensor) or unit_gradients.ndim < 2:
        raise ValueError(
            f"unit_gradients must be a [..., units, parameters] tensor, got "
            f"{getattr(unit_gradients, 'shape', type(unit_gradients).__name__)}."
        )
    units = unit_gradients.shape[-2]
    if units < 2:
        raise ValueError(
            f"The spread of gradients needs at least 2 independent units, got {units}: "
            f"collect more episodes (or environments) per batch."
        )
    mean = unit_gradients.mean(-2)
    centred = torch.linalg.vector_norm(unit_gradients - mean.unsqueeze(-2), dim=(-2, -1))
    trace = centred.pow(2) / (units - 1)
    # NaN or inf anywhere reaches the mean or the spread (one pass less than a check).
    if not bool(torch.isfinite(trace).all() and torch.isfinite(mean).all()):
        raise ValueError("unit_gradients holds NaN/inf: check the returns and the policy.")
    mean_norm_sq = mean.pow(2).sum(-1)
    norm_sq = mean_norm_sq - trace / units
    halves = unit_gradients[..., 0::2, :].mean(-2), unit_gradients[..., 1::2, :].mean(-2)
    cosine = torch.nn.functional.cosine_similarity(*halves, dim=-1, eps=1e-30)
    sets = unit_gradients.shape[:-2]
    return TensorDict(
        {
            "mean_gradient": mean,
            "units": torch.full(sets, units),
            "mean_grad_norm_sq": mean_norm_sq,
            "grad_norm_sq": norm_sq,
            "trace_covariance": trace,
            "noise_scale": torch.where(norm_sq > 0, trace / norm_sq, torch.nan),
            "snr": norm_sq / (trace / units).clamp_min(torch.finfo(trace.dtype).tiny),
            "half_cosine": cosine,
        },
        batch_size=sets,
    )


def unit_index(
    batch: TensorDictBase,
    *,
    unit: str = "episode",
    done_key=("next", "done"),
    group_key="group",
    time_dim=None,
) -> tuple[torch.Tensor, int]:
    """The independent unit of every step of ``batch``: its episode, its row, or its
    episode's group.

    Args:
        batch (TensorDictBase): ``[T]`` (episodes laid end to end) or ``[*B, T]``.

    Keyword Args:
        unit (str): ``"episode"``: each episode is a unit (one cut by the batch's edge
            too); ``"row"``: each row along the time dimension (one environment's
            segment). Defaults to ``"episode"``.
        done_key (NestedKey): the end-of-episode flags. Defaults to ``("next", "done")``.
        time_dim (int, optional): the time dimension. Defaults to the one named
            ``"time"``, else the last.

    Returns:
        ``(index, units)``: a ``long`` tensor of ``batch``'s shape numbering the units
        ``0 … units − 1`` in order of appearance along each row (groups: in the
        order of their ids).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rl_pg.gradient_noise import unit_index
        >>> done = torch.tensor([[False, True, False], [True, False, False]])
        >>> batch = TensorDict({"next": {"done": done.unsqueeze(-1)}}, [2, 3])
        >>> unit_index(batch)
        (tensor([[0, 0, 1],
                [2, 3, 3]]), 4)
        >>> unit_index(batch, unit="row")[0].tolist()
        [[0, 0, 0], [1, 1, 1]]
        >>> batch["group"] = torch.tensor([[7, 7, 7], [7, 9, 9]])
        >>> unit_index(batch, unit="group")[0].tolist()
        [[0, 0, 0], [0, 1, 1]]
    """
    check_choice("unit", unit, UNITS)
    if batch.batch_dims < 1:
        raise ValueError(
            f"unit_index needs a batch with a time dimension, got batch_size "
            f"{tuple(batch.batch_size)}."
        )
    if time_dim is None:
        names = list(batch.names)
        time_dim = names.index("time") if "time" in names else batch.batch_dims - 1
    shape = batch.batch_size
    if unit == "group":
        group = batch.get(group_key, None)
        if group is None:
            raise KeyError(
                f"unit='group' reads each step's group at {group_key!r}: not found. Collect "
                f"with EpisodeCollector(..., group_size=K), which writes it."
            )
        if group.is_floating_point() or group.dtype == torch.bool:
            raise TypeError(f"{group_key!r} must hold integer group ids, got {group.dtype}.")
        if group.shape[: len(shape)] != shape or group[(0,) * len(shape)].numel() != 1:
            raise ValueError(
                f"{group_key!r} has shape {tuple(group.shape)}; it needs one id per step of "
                f"the batch {tuple(shape)}."
            )
        _, index = torch.unique(group.reshape(-1), sorted=True, return_inverse=True)
        return index.reshape(shape), int(index.max()) + 1
    done = batch.get(done_key, None) if unit == "episode" else None
    device = done.device if done is not None else batch.device
    rows = torch.arange(shape.numel() // shape[time_dim], device=device)
    rows = rows.reshape((*shape[:time_dim], *shape[time_dim + 1 :]))
    index = rows.unsqueeze(time_dim).expand(shape)
    if unit == "episode":
        if done is None:
            raise KeyError(f"unit='episode' reads the episode ends at {done_key!r}: not found.")
        done = done.reshape(*shape, -1).any(-1).movedim(time_dim, -1)
        # Episodes started before step t of its row: the ends strictly before it.
        started = done.long().cumsum(-1) - done.long()
        width = done.shape[-1]  # at most one episode per step in a row
        index = (index.movedim(time_dim, -1) * width + started).movedim(-1, time_dim)
    _, index = torch.unique(index.reshape(-1), sorted=True, return_inverse=True)
    return index.reshape(shape), int(index.max()) + 1
