"""Backward linear scans behind [`rl_pg.functional`][rl_pg.functional].

Two implementations of one recurrence, both on ``[N, T]`` tensors (time last)::

    end[t]  = done[t] or terminated[t] or t == T - 1
    carry   = (next_value[t] if not terminated[t] else 0) if end[t] else G[t + 1]
    G[t]    = reward[t] + gamma[t] * carry

``terminated=None`` means ``terminated = done``.

* a numba kernel (``rl_pg._scan_kernels``, imported on first use), one sequential
  pass per row, used for CPU tensors that need no gradient: a collector batch is
  reduced at memory speed (see ``benchmarks/returns.py``). Large scans spread their
  rows over threads (see ``kernel_threads``); small ones, such as a training batch,
  stay on the calling thread;
* a log-depth (Hillis-Steele) scan in plain torch, used on other devices and when an
  input requires a gradient, so that autograd and CUDA keep working.

``whole_episode=True`` then copies each episode's first ``G`` to all of its steps.
Callers validate their inputs; these functions trust them.
"""

from __future__ import annotations

import numpy as np
import torch

_NUMBA_DTYPES = (torch.float32, torch.float64)
PARALLEL_MIN_ELEMENTS = 1 << 16
"""Scans smaller than this (in elements) run on the calling thread alone."""


def kernel_threads(n_rows: int, n_steps: int) -> int:
    """Threads the numba kernel uses for an ``[n_rows, n_steps]`` scan.

    At most ``torch.get_num_threads()`` (which ``TrainConfig.threads`` sets), at most one
    per block of rows, and one below ``PARALLEL_MIN_ELEMENTS``: a thread pool only pays
    for itself on large batches, and on an oversubscribed machine every extra thread is
    one more that the scan may wait for.
    """
    if n_rows * n_steps < PARALLEL_MIN_ELEMENTS:
        return 1
    import numba

    from rl_pg._scan_kernels import ROWS_PER_BLOCK

    n_blocks = (n_rows + ROWS_PER_BLOCK - 1) // ROWS_PER_BLOCK
    return max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS, n_blocks))


def _as_numpy(tensor: torch.Tensor | None) -> np.ndarray | None:
    if tensor is None:
        return None
    if tensor.dtype == torch.bool:
        return tensor.contiguous().numpy().view(np.uint8)
    return tensor.contiguous().numpy()


def _scan_torch(reward, done, terminated, next_value, gamma, whole_episode):
    terminated = done if terminated is None else terminated
    end = done | terminated
    end[:, -1] = True
    bootstrap = end & ~terminated
    if next_value is not None:
        # ``where`` rather than a product: next values at terminated steps may be NaN
        # (TorchRL's compact observations) and must not leak into the result.
        reward = reward + torch.where(bootstrap, gamma * next_value, 0.0)
    decay = torch.where(end, 0.0, gamma).to(reward.dtype)
    value = reward
    n_steps = reward.shape[-1]
    shift = 1
    while shift < n_steps:
        # Out of place so that autograd can trace the scan.
        value = torch.cat(
            [value[:, :-shift] + decay[:, :-shift] * value[:, shift:], value[:, -shift:]],
            dim=-1,
        )
        decay = torch.cat(
            [decay[:, :-shift] * decay[:, shift:], decay.new_zeros(decay.shape[0], shift)],
            dim=-1,
        )
        shift *= 2
    if whole_episode:
        start = torch.zeros_like(end)
        start[:, 1:] = end[:, :-1]
        start[:, 0] = True
        steps = torch.arange(n_steps, device=reward.device).expand_as(start)
        first = torch.where(start, steps, 0).cummax(-1).values
        value = value.gather(-1, first)
    return value


def kernel_args(reward, done, terminated, next_value, gamma, whole_episode):
    """The numba kernels' arguments for ``backward_scan``'s (CPU tensors), and the tensor
    the kernel writes into. The argument types are narrowed (see
    ``rl_pg._scan_kernels``): each new combination of them is a compilation."""
    if isinstance(gamma, torch.Tensor) and gamma.numel() == 1:
        gamma = gamma.item()
    if isinstance(gamma, torch.Tensor):
        gamma = np.ascontiguousarray(gamma.to(reward.dtype).expand_as(reward).numpy())
    else:
        # In the rewards' precision, so that float32 batches are not promoted per step.
        gamma = _as_numpy(reward[:0]).dtype.type(gamma)
    if next_value is not None:
        next_value = next_value.to(reward.dtype)
    out = torch.empty_like(reward, memory_format=torch.contiguous_format)
    end = done if terminated is None else done | terminated
    args = (
        _as_numpy(reward),
        _as_numpy(end),
        _as_numpy(done if terminated is None else terminated),
        _as_numpy(next_value),
        gamma,
        whole_episode,
        out.numpy(),
    )
    return args, out


def backward_scan(
    reward: torch.Tensor,
    done: torch.Tensor,
    terminated: torch.Tensor | None,
    next_value: torch.Tensor | None,
    gamma: torch.Tensor | float,
    *,
    whole_episode: bool,
) -> tuple[torch.Tensor, bool]:
    """Solves the recurrence of this module on ``[N, T]`` inputs (see the module doc).

    ``gamma`` is a float or a tensor broadcastable to ``reward``. Returns the result
    and whether all of it is finite.
    """
    needs_grad = torch.is_grad_enabled() and any(
        isinstance(x, torch.Tensor) and x.requires_grad for x in (reward, next_value, gamma)
    )
    if reward.device.type != "cpu" or needs_grad or reward.dtype not in _NUMBA_DTYPES:
        if not isinstance(gamma, torch.Tensor):
            gamma = torch.tensor(gamma, dtype=reward.dtype, device=reward.device)
        gamma = gamma.to(reward.dtype).expand_as(reward)
        out = _scan_torch(reward, done, terminated, next_value, gamma, whole_episode)
        return out, bool(torch.isfinite(out).all())

    args, out = kernel_args(reward, done, terminated, next_value, gamma, whole_episode)
    import numba

    from rl_pg import _scan_kernels

    threads = kernel_threads(*reward.shape)
    if threads == 1:
        finite_check = _scan_kernels.scan_serial(*args)
    else:
        # numba's first thread call in a process starts its OpenMP threads, which are
        # torch's too: that sets torch's thread count to numba's (every core), for good.
        torch_threads = torch.get_num_threads()
        previous = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            finite_check = _scan_kernels.scan_parallel(*args)
        finally:
            numba.set_num_threads(previous)
            if torch.get_num_threads() != torch_threads:
                torch.set_num_threads(torch_threads)
    return out, bool(np.isfinite(finite_check))
