"""The numba kernels of ``rl_pg._scan``, in a module of their own: numba is imported,
and the kernels loaded, only by a process that runs them (a worker process that only
collects never does).

The kernels read ``end = done | terminated`` (where an episode ends) in their hot loop
and ``terminated`` only at those ends. numba compiles a kernel once per combination of
argument types (1-3 s each), so the caller narrows them: ``terminated`` is always an
array (``done`` when there is no mask), ``gamma`` a number or a C-contiguous array;
``next_value=None`` stays a case of its own, since it saves a memory stream.
"""

from __future__ import annotations

import numba
import numpy as np

# Rows handled together by one thread: their recurrences are independent, so the
# CPU overlaps them instead of waiting on one multiply-add chain at a time.
ROWS_PER_BLOCK = 16


def _gamma_at(gamma, i, t):
    """Discount of step ``t`` of row ``i``: ``gamma`` is a number or an ``[N, T]`` array."""


@numba.extending.overload(_gamma_at, inline="always")
def _gamma_at_impl(gamma, i, t):
    # Specialised on the type so that a scalar discount costs no memory traffic.
    if isinstance(gamma, numba.types.Number):
        return lambda gamma, i, t: gamma
    return lambda gamma, i, t: gamma[i, t]


@numba.njit(inline="always")
def _bootstrap(terminated, next_value, i, t):
    if next_value is None or terminated[i, t]:
        return 0.0
    return next_value[i, t]


@numba.njit(inline="always", nogil=True)
def _scan_block(reward, end, terminated, next_value, gamma, whole_episode, out, block):
    """Rows ``[16 * block, 16 * block + 16)``; returns the sum of ``x - x`` over them."""
    n_rows, n_steps = reward.shape
    lo = block * ROWS_PER_BLOCK
    hi = min(lo + ROWS_PER_BLOCK, n_rows)
    carry = np.zeros(ROWS_PER_BLOCK, dtype=out.dtype)
    # ``x - x`` is 0 for finite x and NaN otherwise: summing it flags a non-finite
    # result without a second pass over memory.
    lane_check = np.zeros(ROWS_PER_BLOCK, dtype=out.dtype)
    last = n_steps - 1
    for j in range(hi - lo):
        i = lo + j
        boot = _bootstrap(terminated, next_value, i, last)
        carry[j] = reward[i, last] + _gamma_at(gamma, i, last) * boot
        out[i, last] = carry[j]
        lane_check[j] += carry[j] - carry[j]
    # Selects rather than branches inside this loop: it is the hot path.
    for t in range(n_steps - 2, -1, -1):
        for j in range(hi - lo):
            i = lo + j
            ended = end[i, t]
            if next_value is None:
                following = carry[j] * (1 - ended)
            else:
                following = _bootstrap(terminated, next_value, i, t) if ended else carry[j]
            carry[j] = reward[i, t] + _gamma_at(gamma, i, t) * following
            out[i, t] = carry[j]
            lane_check[j] += carry[j] - carry[j]
    if whole_episode:
        for j in range(hi - lo):
            i = lo + j
            first = out[i, 0]
            for t in range(1, n_steps):
                if end[i, t - 1]:
                    first = out[i, t]
                else:
                    out[i, t] = first
    return lane_check.sum()


# Two entry points over one body: the serial one runs in the caller's thread, so that
# a busy machine cannot stall it on worker threads the OS has descheduled.
@numba.njit(cache=True, nogil=True)
def scan_serial(reward, end, terminated, next_value, gamma, whole_episode, out):
    n_blocks = (reward.shape[0] + ROWS_PER_BLOCK - 1) // ROWS_PER_BLOCK
    finite_check = 0.0
    for block in range(n_blocks):
        finite_check += _scan_block(
            reward, end, terminated, next_value, gamma, whole_episode, out, block
        )
    return finite_check


@numba.njit(parallel=True, cache=True, nogil=True)
def scan_parallel(reward, end, terminated, next_value, gamma, whole_episode, out):
    n_blocks = (reward.shape[0] + ROWS_PER_BLOCK - 1) // ROWS_PER_BLOCK
    finite_check = 0.0
    for block in numba.prange(n_blocks):
        finite_check += _scan_block(
            reward, end, terminated, next_value, gamma, whole_episode, out, block
        )
    return finite_check


@numba.njit(cache=True, nogil=True)
def episode_sums(reward, done, carried, tails):
    """Each episode's sum of ``reward`` ``[R, T, F]`` over its steps and features, rows
    read one after the other, each starting from its ``carried`` sum (an episode begun
    in an earlier segment); an episode ends after a step where any of ``done[r, t]``
    is set. Returns the sums of the episodes that ended, row by row, and the ``x - x``
    check of every sum (NaN if one is not finite); ``tails`` gets each row's sum after
    its last episode end (0 where the row's last step ended one)."""
    rows, steps, features = reward.shape
    flags = done.shape[2]
    ended = np.empty(rows * steps, dtype=np.float64)
    count = 0
    check = 0.0
    for i in range(rows):
        total = carried[i]
        for t in range(steps):
            for f in range(features):
                total += reward[i, t, f]
            end = False
            for f in range(flags):
                end = end or done[i, t, f]
            if end:
                ended[count] = total
                count += 1
                check += total - total
                total = 0.0
        tails[i] = total
        check += total - total
    return ended[:count], check
