"""Return estimators as pure tensor functions.

Both functions take TorchRL's layout: ``done[t]`` is ``("next", "done")`` of step
``t``, i.e. it marks the **last** step of an episode, and a row may hold several
episodes back to back. Within an episode the reward-to-go is

    G_t = r_t + γ_t G_{t+1}

At an episode's last step `G_{t+1}` is replaced by the bootstrap value
`V(s_{t+1})` (``next_value``) when the episode did not really end there:

* a step that is ``done`` but not ``terminated`` (a truncation, e.g. a time limit);
* the last step of a row that is not ``done`` (an episode cut by the batch).

A ``terminated`` step never bootstraps. Without ``next_value`` nothing is
bootstrapped: a cut or truncated episode simply stops collecting reward there.
"""

from __future__ import annotations

import numbers

import torch

from rl_pg._checks import check_real
from rl_pg._scan import backward_scan

__all__ = ["discounted_return", "reward_to_go"]


def reward_to_go(
    reward: torch.Tensor,
    done: torch.Tensor,
    gamma: float | torch.Tensor,
    *,
    time_dim: int = -2,
    terminated: torch.Tensor | None = None,
    next_value: torch.Tensor | None = None,
) -> torch.Tensor:
    """Discounted reward-to-go `G_t = Σ_{k≥t} γ^(k−t) r_k` inside each episode.

    This is the "causality" return of REINFORCE: an action answers only for the
    rewards that follow it.

    Args:
        reward (torch.Tensor): rewards, ``[*B, T, 1]`` (TorchRL's layout) or ``[*B, T]``
            with ``time_dim=-1``; float32 or float64 (other floating types are computed
            by the torch fallback).
        done (torch.Tensor): same shape as ``reward``; ``True`` on the last step of an
            episode.
        gamma (float or torch.Tensor): discount in ``[0, 1]``, a number or a tensor
            broadcastable to ``reward`` (a per-step or per-row discount).

    Keyword Args:
        time_dim (int): the time dimension of ``reward``. Defaults to ``-2``.
        terminated (torch.Tensor, optional): same shape as ``reward``; ``True`` where
            the episode really ended (no bootstrap). Defaults to ``None``, meaning
            ``terminated = done``.
        next_value (torch.Tensor, optional): same shape as ``reward``; the value of the
            next state, read only where an episode is truncated or cut by the batch.
            Values at terminated steps are ignored and may be NaN. Defaults to
            ``None``: no bootstrap.

    Returns:
        A tensor of the shape and dtype of ``reward``.

    Raises:
        TypeError: for a ``reward`` that is not a floating-point tensor, a ``time_dim``
            that is not an integer, or a ``gamma`` that is not a real number.
        ValueError: on an empty batch, mismatched shapes or devices, ``gamma`` outside
            ``[0, 1]``, an out-of-range ``time_dim``, ``done`` / ``terminated`` holding
            values other than 0 and 1, or non-finite ``reward`` / ``next_value`` where
            they are read.

    Examples:
        >>> import torch
        >>> from rl_pg.functional import reward_to_go
        >>> reward = torch.ones(1, 5, 1)
        >>> done = torch.tensor([[0, 1, 0, 0, 0]], dtype=torch.bool).unsqueeze(-1)
        >>> reward_to_go(reward, done, 0.5).squeeze(-1)
        tensor([[1.5000, 1.0000, 1.7500, 1.5000, 1.0000]])
        >>> # the second episode is cut by the batch: bootstrap it from V(s_5) = 8
        >>> next_value = torch.full_like(reward, 8.0)
        >>> reward_to_go(reward, done, 0.5, next_value=next_value).squeeze(-1)
        tensor([[1.5000, 1.0000, 2.7500, 3.5000, 5.0000]])
    """
    return _returns(reward, done, gamma, time_dim, terminated, next_value, whole_episode=False)


def discounted_return(
    reward: torch.Tensor,
    done: torch.Tensor,
    gamma: float | torch.Tensor,
    *,
    time_dim: int = -2,
    terminated: torch.Tensor | None = None,
    next_value: torch.Tensor | None = None,
) -> torch.Tensor:
    """The episode's whole discounted return `R(τ) = Σ_k γ^k r_k` at every step.

    This is the "no causality" return of REINFORCE: every action of an episode is
    credited with the same number. It equals
    [`reward_to_go`][rl_pg.functional.reward_to_go] at each episode's first step. An
    episode that starts before the row does (a segment cut by the previous batch) gets
    the return from the row's first step on.

    Args:
        reward (torch.Tensor): rewards, ``[*B, T, 1]`` or ``[*B, T]`` with ``time_dim=-1``.
        done (torch.Tensor): same shape as ``reward``; ``True`` on the last step of an
            episode.
        gamma (float or torch.Tensor): discount in ``[0, 1]``, a number or a tensor
            broadcastable to ``reward``.

    Keyword Args:
        time_dim (int): the time dimension of ``reward``. Defaults to ``-2``.
        terminated (torch.Tensor, optional): ``True`` where the episode really ended.
            Defaults to ``None``, meaning ``terminated = done``.
        next_value (torch.Tensor, optional): the next state's value, read only where an
            episode is truncated or cut by the batch. Defaults to ``None``: no bootstrap.

    Returns:
        A tensor of the shape and dtype of ``reward``.

    Raises:
        ValueError: as [`reward_to_go`][rl_pg.functional.reward_to_go].

    Examples:
        >>> import torch
        >>> from rl_pg.functional import discounted_return
        >>> reward = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0])
        >>> done = torch.tensor([False, True, False, False, True])
        >>> discounted_return(reward, done, 0.5, time_dim=-1)
        tensor([2.0000, 2.0000, 6.2500, 6.2500, 6.2500])
    """
    return _returns(reward, done, gamma, time_dim, terminated, next_value, whole_episode=True)


def _returns(reward, done, gamma, time_dim, terminated, next_value, *, whole_episode):
    gamma = _check_inputs(reward, done, gamma, time_dim, terminated, next_value)
    shape = reward.shape
    time_dim = time_dim % reward.ndim

    def rows(tensor):
        # [*B, T, *F] -> [N, T]: time last so each row is one contiguous sequence.
        if tensor is None:
            return None
        return tensor.movedim(time_dim, -1).reshape(-1, shape[time_dim])

    if isinstance(gamma, torch.Tensor):
        gamma = rows(torch.broadcast_to(gamma, shape))
    out, finite = backward_scan(
        rows(reward),
        rows(_as_bool(done)),
        None if terminated is None else rows(_as_bool(terminated)),
        rows(next_value),
        gamma,
        whole_episode=whole_episode,
    )
    if not finite:
        _raise_non_finite(reward, done, terminated, next_value, time_dim)
    moved = list(shape)
    moved.append(moved.pop(time_dim))
    return out.view(moved).movedim(-1, time_dim)


def _as_bool(mask: torch.Tensor) -> torch.Tensor:
    return mask if mask.dtype == torch.bool else mask != 0


def _check_inputs(reward, done, gamma, time_dim, terminated, next_value):
    """Validates the arguments of both return functions; returns ``gamma`` as a float or
    a floating-point tensor."""
    if not isinstance(reward, torch.Tensor) or not reward.is_floating_point():
        raise TypeError(
            f"reward must be a floating-point tensor, got {type(reward).__name__}"
            f"{'' if not isinstance(reward, torch.Tensor) else ' of dtype ' + str(reward.dtype)}."
            " Cast it with reward.float()."
        )
    if isinstance(time_dim, bool) or not isinstance(time_dim, numbers.Integral):
        raise TypeError(
            f"time_dim must be an integer, got {time_dim!r} ({type(time_dim).__name__}). "
            "Rewards are [*B, T, 1] with time_dim=-2, or [*B, T] with time_dim=-1."
        )
    if reward.ndim == 0 or not -reward.ndim <= time_dim < reward.ndim:
        raise ValueError(
            f"time_dim={time_dim} is out of range for a reward of shape {tuple(reward.shape)}."
            " Rewards are [*B, T, 1] with time_dim=-2, or [*B, T] with time_dim=-1."
        )
    if reward.numel() == 0:
        raise ValueError(
            f"Cannot compute returns of an empty batch (reward shape {tuple(reward.shape)})."
        )
    _check_mask("done", done, reward)
    if terminated is not None:
        _check_mask("terminated", terminated, reward)
    if next_value is not None:
        _check_like_reward("next_value", next_value, reward)
        if not next_value.is_floating_point():
            raise TypeError(
                f"next_value must be a floating-point tensor, got dtype {next_value.dtype}."
            )
    return _check_gamma(gamma, reward)


def _check_like_reward(name: str, tensor, reward: torch.Tensor) -> None:
    if not isinstance(tensor, torch.Tensor):
        raise TypeError(
            f"{name} must be a tensor shaped like reward {tuple(reward.shape)}, got "
            f"{type(tensor).__name__}."
        )
    if tensor.shape != reward.shape:
        raise ValueError(
            f"{name} must have the shape of reward {tuple(reward.shape)}, got "
            f"{tuple(tensor.shape)}."
        )
    if tensor.device != reward.device:
        raise ValueError(
            f"{name} is on {tensor.device} but reward is on {reward.device}: move them to "
            f"one device."
        )


def _check_mask(name: str, mask, reward: torch.Tensor) -> None:
    """A boolean mask, or numbers that are all exactly 0 or 1 (never 0.3 or NaN)."""
    _check_like_reward(name, mask, reward)
    if mask.dtype == torch.bool:
        return
    if mask.dtype.is_complex or not bool(((mask == 0) | (mask == 1)).all()):
        bad = mask[(mask != 0) & (mask != 1)] if not mask.dtype.is_complex else mask
        raise ValueError(
            f"{name} must be boolean (or hold only 0 and 1), got dtype {mask.dtype} with "
            f"value {bad.reshape(-1)[0].item()!r}. Episode ends are yes/no: pass "
            f"{name}.bool() if its non-zero values mean True."
        )


def _check_gamma(gamma, reward: torch.Tensor) -> float | torch.Tensor:
    if isinstance(gamma, torch.Tensor) and gamma.numel() > 1:
        if gamma.dtype == torch.bool or gamma.dtype.is_complex:
            raise TypeError(f"gamma must hold real numbers, got dtype {gamma.dtype}.")
        if gamma.device != reward.device:
            raise ValueError(
                f"gamma is on {gamma.device} but reward is on {reward.device}: move them to "
                f"one device."
            )
        try:
            broadcast = torch.broadcast_shapes(gamma.shape, reward.shape)
        except RuntimeError:
            broadcast = None
        if broadcast != reward.shape:
            raise ValueError(
                f"gamma of shape {tuple(gamma.shape)} does not broadcast to reward of shape "
                f"{tuple(reward.shape)}. Pass a number or a tensor such as [*B, 1, 1]."
            )
        if not bool(((gamma >= 0) & (gamma <= 1)).all()):
            bad = gamma[~((gamma >= 0) & (gamma <= 1))].reshape(-1)[0].item()
            raise ValueError(f"gamma must lie in [0, 1], got a value of {bad!r}.")
        return gamma if gamma.is_floating_point() else gamma.to(reward.dtype)
    return check_real("gamma", gamma, low=0, high=1)


def _raise_non_finite(reward, done, terminated, next_value, time_dim):
    """Names the input that made the returns non-finite."""
    bad = ~torch.isfinite(reward)
    if bad.any():
        first = tuple(bad.nonzero()[0].tolist())
        raise ValueError(
            f"reward holds {int(bad.sum())} non-finite value(s) (the first at index {first}):"
            " returns would be NaN. Check the environment's reward or its wrappers."
        )
    if next_value is not None:
        # next_value is read where an episode is truncated or cut by the row's end.
        ended = _as_bool(done).clone()
        ended.narrow(time_dim, ended.shape[time_dim] - 1, 1).fill_(True)
        if terminated is not None:
            ended |= _as_bool(terminated)
        terminal = _as_bool(done if terminated is None else terminated)
        bad = ~torch.isfinite(next_value) & ended & ~terminal
        if bad.any():
            first = tuple(bad.nonzero()[0].tolist())
            raise ValueError(
                f"next_value holds {int(bad.sum())} non-finite value(s) at steps that "
                f"bootstrap (the first at index {first}). Check the value network's output."
            )
    raise ValueError(
        "The returns overflowed to inf: the rewards are too large for the dtype "
        f"({reward.dtype}). Scale the rewards down or use float64."
    )
