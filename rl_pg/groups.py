"""Group baselines: episodes that share their randomness are each other's baseline.

A *group* is a set of episodes played from the same start: the same environment seed
(the same terrain and initial push of a lander, the same map and traffic of a driving
scenario), so that the episodes differ only by the policy's own draws. Each episode's
return is then weighed against the returns of the others:

* ``"leave_one_out"``: the mean of the *other* episodes of its group (Kool et al.
  2019, "Buy 4 REINFORCE samples, get a baseline for free"; RLOO, Ahmadian et al.
  2024). Given the start, the other episodes are independent of this one's actions, so
  the gradient stays unbiased.
* ``"group_mean"``: the mean of the whole group, the episode itself included (GRPO).
  Its own return inside the baseline shrinks the expected gradient by exactly
  ``1 − 1/K`` for groups of ``K`` episodes: the direction is kept, the length is not.
* ``"greedy"``: the return of one episode per group in which the policy acted greedily
  (self-critical training, Rennie et al. 2017; ReMax, Li et al. 2023). It does not
  depend on the sampled episodes, so the gradient stays unbiased; a sampled episode
  gets a positive weight only where it did better than the policy's own greedy play.

``scale=True`` further divides by the standard deviation of the group's returns (GRPO's
normalised advantage). That standard deviation depends on the episode's own return,
so the expected gradient is no longer proportional to the policy gradient (Liu et al.
2025, "Understanding R1-Zero-like training"): it reweights groups by how much their
outcomes vary. Offered because it is widely used, and measured as biased in the tests.

Returns are compared *position by position*: the baseline of step ``t`` of an episode
is built from the other episodes' values at their own step ``t``. For reward-to-go,
a finished episode's value past its end is 0 (nothing left to earn); for the
whole-episode return, one value per episode (``returns`` of width 1) is the natural
layout.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from rl_pg.gradient_noise import unit_index
from rl_pg.greedy_play import GreedyInGroups  # noqa: F401 (its import path before)
from rl_pg.loss_checks import required

__all__ = [
    "GROUP_BASELINES",
    "batch_group_advantage",
    "greedy_flags",
    "group_advantage",
]

GROUP_BASELINES = ("leave_one_out", "group_mean", "greedy")


def group_advantage(
    returns: torch.Tensor,
    group: torch.Tensor,
    *,
    baseline: str = "leave_one_out",
    greedy: torch.Tensor | None = None,
    scale: bool = False,
    eps: float = 1e-8,
) -> torch.Tensor:
    """The advantage of every episode against the other episodes of its group.

    Args:
        returns (torch.Tensor): ``[E, L]``, one row per episode, its value at each of
            ``L`` positions (step ``t`` of the episode; zero past its end for a
            reward-to-go; ``L = 1`` for one value per episode). Floating point.
        group (torch.Tensor): ``[E]`` integers, the group of each episode (any values;
            episodes with equal values form a group).

    Keyword Args:
        baseline (str): ``"leave_one_out"``, ``"group_mean"`` or ``"greedy"``.
            Defaults to ``"leave_one_out"``.
        greedy (torch.Tensor, optional): ``[E]`` booleans, the greedy episode of each
            group (exactly one per group with ``baseline="greedy"``; none otherwise).
            Defaults to ``None``: every episode is sampled.
        scale (bool): divide by the standard deviation (``K − 1`` in the denominator)
            of the group's sampled returns at each position, plus ``eps``. Defaults to
            ``False``.
        eps (float): added to the standard deviation. Defaults to ``1e-8``.

    Returns:
        ``[E, L]``: ``returns − b`` (divided by the group's standard deviation with
        ``scale=True``); 0 on the rows of greedy episodes.

    Raises:
        ValueError: for an unknown ``baseline``, mismatched shapes, a group with fewer
            than two sampled episodes where the baseline (or ``scale``) needs two, or
            greedy episodes that are not exactly one per group.
        TypeError: for a ``returns`` that is not floating point or a ``group`` that is
            not integer.

    Examples:
        >>> import torch
        >>> from rl_pg.groups import group_advantage
        >>> returns = torch.tensor([[1.0], [3.0], [5.0], [10.0], [20.0], [30.0]])
        >>> group = torch.tensor([0, 0, 0, 1, 1, 1])
        >>> group_advantage(returns, group).squeeze(-1)  # minus the others' mean
        tensor([ -3.,   0.,   3., -15.,   0.,  15.])
        >>> group_advantage(returns, group, baseline="group_mean").squeeze(-1)
        tensor([ -2.,   0.,   2., -10.,   0.,  10.])
        >>> greedy = torch.tensor([False, False, True, False, True, False])
        >>> group_advantage(returns, group, baseline="greedy", greedy=greedy).squeeze(-1)
        tensor([ -4.,  -2.,   0., -10.,   0.,  10.])
    """
    if baseline not in GROUP_BASELINES:
        raise ValueError(f"baseline must be one of {GROUP_BASELINES}, got {baseline!r}.")
    if not isinstance(returns, torch.Tensor) or not returns.is_floating_point():
        raise TypeError(f"returns must be a floating-point tensor, got {_describe(returns)}.")
    if not isinstance(group, torch.Tensor) or group.is_floating_point() or group.is_complex():
        raise TypeError(f"group must be an integer tensor, got {_describe(group)}.")
    if returns.ndim != 2 or group.shape != returns.shape[:1]:
        raise ValueError(
            f"returns must be [episodes, positions] and group [episodes]: got "
            f"{tuple(returns.shape)} and {tuple(group.shape)}."
        )
    if greedy is None:
        greedy = torch.zeros_like(group, dtype=torch.bool)
    elif greedy.shape != group.shape or greedy.dtype != torch.bool:
        raise ValueError(
            f"greedy must be a boolean tensor shaped like group {tuple(group.shape)}, got "
            f"{greedy.dtype} {tuple(greedy.shape)}."
        )
    _, index = torch.unique(group, return_inverse=True)
    groups = int(index.max()) + 1
    sampled = (~greedy).to(returns.dtype)
    count = torch.zeros(groups, dtype=returns.dtype, device=returns.device)
    count.index_add_(0, index, sampled)
    greedy_count = torch.zeros(groups, dtype=torch.long, device=returns.device)
    greedy_count.index_add_(0, index, greedy.long())
    if baseline == "greedy":
        if bool((greedy_count != 1).any()):
            bad = int((greedy_count != 1).nonzero()[0])
            raise ValueError(
                f"baseline='greedy' needs exactly one greedy episode in each group; a group "
                f"has {int(greedy_count[bad])}. Play one greedy episode per group (rl_pg's "
                f"EpisodeCollector(..., greedy=True) does)."
            )
    elif bool(greedy_count.any()):
        raise ValueError(
            f"The batch marks greedy episodes, which only baseline='greedy' reads; with "
            f"baseline={baseline!r} drop them (or their flags) from the batch."
        )
    needed = 2 if (baseline != "greedy" or scale) else 1
    if bool((count < needed).any()):
        raise ValueError(
            f"baseline={baseline!r}{' with scale' if scale else ''} needs at least "
            f"{needed} sampled episodes in every group; a group has "
            f"{int(count.min())}. Play K >= {needed} episodes from each start "
            f"(EpisodeCollector(..., group_size=K))."
        )
    weighted = returns * sampled.unsqueeze(-1)
    total = torch.zeros(groups, returns.shape[1], dtype=returns.dtype, device=returns.device)
    total.index_add_(0, index, weighted)
    k = count[index].unsqueeze(-1)
    if baseline == "leave_one_out":
        b = (total[index] - returns) / (k - 1)
    elif baseline == "group_mean":
        b = total[index] / k
    else:
        greedy_returns = torch.zeros_like(total)
        greedy_returns.index_add_(0, index[greedy], returns[greedy])
        b = greedy_returns[index]
    advantage = returns - b
    if scale:
        mean = total / count.unsqueeze(-1)
        squares = torch.zeros_like(total)
        squares.index_add_(0, index, (returns - mean[index]).square() * sampled.unsqueeze(-1))
        std = (squares / (count.unsqueeze(-1) - 1)).sqrt()
        advantage = advantage / (std[index] + eps)
    return advantage.masked_fill(greedy.unsqueeze(-1), 0.0)


def batch_group_advantage(
    batch: TensorDictBase,
    returns: torch.Tensor,
    *,
    baseline: str = "leave_one_out",
    scale: bool = False,
    per_episode: bool = False,
    group_key="group",
    greedy_key="greedy",
    done_key=("next", "done"),
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """[`group_advantage`][rl_pg.groups.group_advantage] on a batch of steps: every
    step's return minus its group's baseline.

    The batch holds whole episodes (``[T]`` laid end to end or ``[*B, T]``), each ending
    on ``done_key``, with its group id at ``group_key`` on every step (and, for
    ``baseline="greedy"``, the greedy flags at ``greedy_key``), as
    [`EpisodeCollector`][rl_pg.episode_collector.EpisodeCollector] ``(..., group_size=K)``
    writes them.

    Args:
        batch (TensorDictBase): the steps.
        returns (torch.Tensor): each step's return, ``[*batch_size, 1]``: a
            reward-to-go, compared position by position (step ``t`` of an episode with
            step ``t`` of the others, 0 past their end), or with ``per_episode=True`` a
            return that is one value per episode (its first step's counts).

    Keyword Args:
        baseline (str): one of ``GROUP_BASELINES``. Defaults to ``"leave_one_out"``.
        scale (bool): divide by the group's standard deviation. Defaults to ``False``.
        per_episode (bool): one return per episode. Defaults to ``False``.
        group_key, greedy_key, done_key (NestedKey): where the batch holds them.
        mask (torch.Tensor, optional): ``[*batch_size, 1]`` booleans, False on padding
            steps, which are left out and get 0. Defaults to ``None``: every step.

    Returns:
        ``[*batch_size, 1]``: the advantages; 0 on greedy episodes and padding.

    Raises:
        KeyError: the group ids (or greedy flags) are missing.
        TypeError: group ids that are not integers, greedy flags that are not boolean.
        ValueError: an episode cut by the batch, a group id or greedy flag changing
            inside an episode, and what ``group_advantage`` refuses.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rl_pg.groups import batch_group_advantage
        >>> done = torch.tensor([False, True, True, False, True, True]).unsqueeze(-1)
        >>> batch = TensorDict({"group": torch.tensor([0, 0, 0, 0, 0, 0]).unsqueeze(-1),
        ...                     "next": {"done": done}}, [6])
        >>> to_go = torch.tensor([3.0, 1.0, 2.0, 6.0, 4.0, 0.0]).unsqueeze(-1)
        >>> # Four episodes, one group; first steps' mean 2.75, second steps' 1.25 (0s count)
        >>> batch_group_advantage(batch, to_go, baseline="group_mean").squeeze(-1)
        tensor([ 0.2500, -0.2500, -0.7500,  3.2500,  2.7500, -2.7500])
    """
    lead = f"baseline={baseline!r}: "
    group = required(
        batch,
        group_key,
        f"A group baseline ({baseline!r}) compares each episode with the others "
        f"played from the same start: collect with EpisodeCollector(..., group_size=K), "
        f"which writes it, or point the key at your group ids (loss.set_keys(group=...)).",
        lead,
    )
    group = _per_step(batch, group_key, group, torch.long)
    shape = batch.batch_size
    time_dim = len(shape) - 1
    if "time" in batch.names:
        time_dim = batch.names.index("time")
    episode, _ = unit_index(batch, done_key=done_key, time_dim=time_dim)
    done = batch.get(done_key).reshape(*shape, -1).any(-1)

    def flat(x: torch.Tensor) -> torch.Tensor:  # time last, then row after row
        return x.reshape(shape).movedim(time_dim, -1).reshape(-1)

    steps = flat(mask) if mask is not None else None
    columns = [flat(x) for x in (episode, returns, done, group)]
    if baseline == "greedy":
        columns.append(flat(greedy_flags(batch, greedy_key)))
    if steps is not None:
        columns = [x[steps] for x in columns]
    episode, values, done, group, *greedy = columns
    _, episode = torch.unique_consecutive(episode, return_inverse=True)
    count = int(episode[-1]) + 1
    order = torch.arange(episode.numel(), device=episode.device)
    first = torch.zeros(count, dtype=torch.long, device=episode.device)
    first = first.scatter_reduce(0, episode, order, "amin", include_self=False)
    last = torch.zeros_like(first).scatter_reduce(0, episode, order, "amax")
    if not bool(done[last].all()):
        raise ValueError(
            f"A group baseline ({baseline!r}) compares whole episodes, but "
            f"{int((~done[last]).sum())} episode(s) of the batch do not end on "
            f"{done_key!r}: cut by the batch. Collect whole episodes "
            f"(EpisodeCollector), or pad and mask the unfinished ones."
        )
    by_episode = [x[first] for x in (group, *greedy)]
    for name, column, per_episode_value in zip(
        (group_key, greedy_key), (group, *greedy), by_episode, strict=False
    ):
        if not bool((column == per_episode_value[episode]).all()):
            raise ValueError(
                f"{name!r} changes inside an episode: every step of an episode must "
                f"carry its episode's value (the group of its start)."
            )
    position = order - first[episode]
    if per_episode:
        position = torch.zeros_like(position)  # one return per episode
    table = values.new_zeros(count, int(position.max()) + 1)
    table[episode, position] = values
    advantage = group_advantage(
        table,
        by_episode[0],
        baseline=baseline,
        greedy=by_episode[1] if greedy else None,
        scale=scale,
    )[episode, position]
    if steps is not None:
        advantage = advantage.new_zeros(steps.shape).masked_scatter(steps, advantage)
    moved = list(shape)
    moved.append(moved.pop(time_dim))
    return advantage.reshape(moved).movedim(-1, time_dim).unsqueeze(-1)


def greedy_flags(batch: TensorDictBase, key="greedy") -> torch.Tensor:
    """The greedy-episode flags of every step, ``[*batch_size, 1]`` booleans.

    Raises:
        KeyError: the batch has no flags at ``key``.
        TypeError, ValueError: flags that are not boolean, or not one per step.
    """
    flags = required(
        batch,
        key,
        "baseline='greedy' reads which steps belong to each group's greedy episode "
        "there: collect with EpisodeCollector(..., greedy=True), or point the key at "
        "your flags (loss.set_keys(greedy=...)).",
        "baseline='greedy': ",
    )
    return _per_step(batch, key, flags, torch.bool)


def _per_step(batch: TensorDictBase, key, value: torch.Tensor, dtype) -> torch.Tensor:
    """``value`` checked to hold one entry per step, as ``[*batch, 1]``; ``dtype`` is
    ``torch.bool`` or ``torch.long`` (any integer type)."""
    shape = batch.batch_size
    if value.shape[: len(shape)] != shape or value[(0,) * len(shape)].numel() != 1:
        raise ValueError(
            f"{key!r} has shape {tuple(value.shape)}; it needs one value per step of the "
            f"batch {tuple(shape)}."
        )
    if dtype is torch.bool and value.dtype != torch.bool:
        raise TypeError(f"{key!r} must be boolean, got dtype {value.dtype}.")
    if dtype is torch.long and (value.is_floating_point() or value.dtype == torch.bool):
        raise TypeError(
            f"{key!r} must hold integer group ids, got dtype {value.dtype}. Pass .long()."
        )
    return value.reshape(*shape, 1)


def _describe(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"a {value.dtype} tensor"
    return type(value).__name__
