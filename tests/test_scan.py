"""rl_pg._scan and its numba kernels: every path (one block, several, a partial last one;
the serial and the parallel kernel; the torch scan) against the plain loop of
tests/test_functional.py, on batches large enough to reach them."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from test_functional import reference_returns

from rl_pg import _scan, _scan_kernels
from rl_pg._scan import PARALLEL_MIN_ELEMENTS, backward_scan, kernel_threads
from rl_pg._scan_kernels import ROWS_PER_BLOCK
from rl_pg.functional import reward_to_go


def _problem(seed, n_rows, n_steps, *, p_done, gamma_kind, bootstrap, terminated_mask):
    generator = torch.Generator().manual_seed(seed)
    shape = (n_rows, n_steps)
    reward = torch.randn(shape, generator=generator, dtype=torch.float64)
    done = torch.rand(shape, generator=generator) < p_done
    terminated = done & (torch.rand(shape, generator=generator) < 0.5)
    if not terminated_mask:
        terminated = done.clone()
    next_value = None
    if bootstrap:
        next_value = torch.randn(shape, generator=generator, dtype=torch.float64)
        next_value = next_value.masked_fill(terminated, float("nan"))  # never read there
    if gamma_kind == "per_step":
        gamma = torch.rand(shape, generator=generator, dtype=torch.float64)
    else:
        gamma = float(gamma_kind)
    return reward, done, terminated if terminated_mask else None, next_value, gamma, terminated


def _expected(reward, done, terminated_full, next_value, gamma, whole_episode):
    n_rows = reward.shape[0]
    gamma_full = torch.broadcast_to(torch.as_tensor(gamma, dtype=torch.float64), reward.shape)
    rows = reference_returns(
        reward.tolist(),
        done.tolist(),
        terminated_full.tolist(),
        next_value.tolist() if next_value is not None else [None] * n_rows,
        gamma_full.tolist(),
        whole_episode,
    )
    return torch.tensor(rows, dtype=torch.float64)


def _kernel_args(reward, done, terminated, next_value, gamma, whole_episode, dtype):
    """The arguments backward_scan hands the kernels, for a kernel called directly."""
    nv = None if next_value is None else next_value.to(dtype)
    gamma = gamma.to(dtype) if isinstance(gamma, torch.Tensor) else gamma
    return _scan.kernel_args(reward.to(dtype), done, terminated, nv, gamma, whole_episode)


def _tolerance(dtype):
    return {"rtol": 1e-4, "atol": 1e-4} if dtype == torch.float32 else {"rtol": 1e-9, "atol": 1e-9}


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    # 1 to 3 blocks of rows, the last one full or partial.
    n_rows=st.integers(1, 3 * ROWS_PER_BLOCK),
    n_steps=st.integers(1, 80),
    p_done=st.sampled_from([0.0, 0.05, 0.3, 1.0]),
    gamma_kind=st.sampled_from(["0", "0.9", "1", "per_step"]),
    bootstrap=st.booleans(),
    terminated_mask=st.booleans(),
    whole_episode=st.booleans(),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_both_kernels_match_the_loop_on_every_block(
    seed, n_rows, n_steps, p_done, gamma_kind, bootstrap, terminated_mask, whole_episode, dtype
):
    reward, done, terminated, next_value, gamma, term_full = _problem(
        seed, n_rows, n_steps, p_done=p_done, gamma_kind=gamma_kind, bootstrap=bootstrap,
        terminated_mask=terminated_mask,
    )  # fmt: skip
    expected = _expected(reward, done, term_full, next_value, gamma, whole_episode)
    for kernel in (_scan_kernels.scan_serial, _scan_kernels.scan_parallel):
        args, out = _kernel_args(reward, done, terminated, next_value, gamma, whole_episode, dtype)
        check = kernel(*args)
        torch.testing.assert_close(out.double(), expected, **_tolerance(dtype))
        assert np.isfinite(check)
    # The torch scan (other devices, inputs that need a gradient) on the same problem.
    gamma_t = torch.as_tensor(gamma, dtype=torch.float64)
    torch_out = _scan._scan_torch(
        reward.to(dtype),
        done,
        terminated,
        None if next_value is None else next_value.to(dtype),
        gamma_t.to(dtype).expand(reward.shape),
        whole_episode,
    )
    torch.testing.assert_close(torch_out.double(), expected, **_tolerance(dtype))


def test_the_ways_to_pass_masks_and_discounts_share_few_kernel_signatures():
    # numba compiles each new combination of argument types (1-3 s, on a user's first
    # call and in every fresh cache): whatever form a mask or a discount arrives in, one
    # precision needs at most four (next_value or not, a number or a per-step gamma).
    n_rows, n_steps = 3, 5
    reward = torch.randn(n_rows, n_steps)
    done = torch.rand(n_rows, n_steps) < 0.3
    gammas = [
        0.9, torch.tensor(0.9), torch.full((n_rows, 1), 0.9),
        torch.rand(n_rows, n_steps), torch.rand(n_steps, n_rows).T,
    ]  # fmt: skip
    signatures = set()
    for terminated in (None, done & (torch.rand(n_rows, n_steps) < 0.5)):
        for next_value in (None, torch.randn(n_rows, n_steps, dtype=torch.float64)):
            for gamma in gammas:
                for whole_episode in (False, True):
                    args, _ = _scan.kernel_args(
                        reward, done, terminated, next_value, gamma, whole_episode
                    )
                    signatures.add(tuple(numba.typeof(arg) for arg in args))
    assert len(signatures) == 4, sorted(map(str, signatures))


def test_a_batch_past_the_parallel_threshold_runs_the_parallel_kernel_and_matches_the_loop(
    monkeypatch,
):
    # 37 rows (two full blocks and a partial one) x 1 800 steps: 66 600 elements.
    n_rows, n_steps = 2 * ROWS_PER_BLOCK + 5, 1_800
    assert n_rows * n_steps >= PARALLEL_MIN_ELEMENTS
    reward, done, terminated, next_value, gamma, term_full = _problem(
        7, n_rows, n_steps, p_done=0.03, gamma_kind="0.99", bootstrap=True,
        terminated_mask=True,
    )  # fmt: skip
    used = []
    for name in ("scan_serial", "scan_parallel"):
        kernel = getattr(_scan_kernels, name)

        def spy(*args, _kernel=kernel, _name=name):
            used.append((_name, numba.get_num_threads()))
            return _kernel(*args)

        monkeypatch.setattr(_scan_kernels, name, spy)
    threads = min(2, numba.config.NUMBA_NUM_THREADS)
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    assert kernel_threads(n_rows, n_steps) == threads
    out = reward_to_go(
        reward, done, gamma, time_dim=-1, terminated=terminated, next_value=next_value
    )
    expected = _expected(reward, done, term_full, next_value, gamma, False)
    torch.testing.assert_close(out, expected, rtol=1e-9, atol=1e-9)
    if threads > 1:  # a machine with one core has no parallel path to take
        assert used == [("scan_parallel", threads)]
    else:
        assert used == [("scan_serial", 1)]


def test_the_parallel_kernel_leaves_torchs_threads_as_it_found_them():
    # numba's OpenMP threads are torch's: starting them (once per process) set torch's
    # thread count to numba's. A fresh process, numba's count other than torch's.
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = (
        "import torch; torch.set_num_threads(2)\n"
        "from rl_pg._scan import backward_scan, kernel_threads\n"
        "reward = torch.randn(64, 4096)\n"
        "assert kernel_threads(64, 4096) == 2\n"
        "backward_scan(reward, torch.zeros(64, 4096, dtype=torch.bool), None, None, 0.9,"
        " whole_episode=False)\n"
        "print(torch.get_num_threads())\n"
    )
    # The child imports the rl_pg under test (under benchmarks/mutation.py, a mutated
    # copy, whose bytecode must not be kept for the next mutant's).
    package = str(Path(_scan.__file__).parents[1])
    path = os.pathsep.join([package, *filter(None, [os.environ.get("PYTHONPATH")])])
    env = {**os.environ, "NUMBA_NUM_THREADS": "3", "PYTHONPATH": path,
           "PYTHONDONTWRITEBYTECODE": "1"}  # fmt: skip
    # Run from the package's folder: ``python -c`` puts the working folder first on the
    # path, where another rl_pg (the checkout a mutation run starts from) would win.
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, cwd=package, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["2"]


def test_a_non_finite_result_is_flagged_from_any_block():
    # A NaN reward in the last, partial block: the flag sums over every block.
    reward = torch.randn(2 * ROWS_PER_BLOCK + 3, 10, dtype=torch.float64)
    reward[-1, 4] = float("nan")
    done = torch.zeros_like(reward, dtype=torch.bool)
    _, finite = backward_scan(reward, done, None, None, 0.9, whole_episode=False)
    assert not finite
    reward[-1, 4] = 0.0
    _, finite = backward_scan(reward, done, None, None, 0.9, whole_episode=False)
    assert finite


@pytest.mark.parametrize("wrong", ["no_bootstrap", "episode_ignored"])
def test_the_reference_tells_a_wrong_recurrence_apart(wrong):
    # Negative control: the comparison above would catch a kernel that dropped the
    # bootstrap or ran through an episode's end.
    reward, done, terminated, next_value, gamma, term_full = _problem(
        3, ROWS_PER_BLOCK + 1, 40, p_done=0.2, gamma_kind="0.9", bootstrap=True,
        terminated_mask=True,
    )  # fmt: skip
    args, out = _kernel_args(reward, done, terminated, next_value, gamma, False, torch.float64)
    _scan_kernels.scan_serial(*args)
    if wrong == "no_bootstrap":
        bad = _expected(reward, done, term_full, None, gamma, False)
    else:
        never = torch.zeros_like(done)
        bad = _expected(reward, never, never, next_value, gamma, False)
    assert not torch.allclose(out, bad, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(out, _expected(reward, done, term_full, next_value, gamma, False))
