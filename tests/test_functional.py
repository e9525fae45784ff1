"""The return kernels against a plain Python loop, and their input checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rl_pg.functional import discounted_return, reward_to_go


def reference_returns(reward, done, terminated, next_value, gamma, whole_episode):
    """Forward sums over explicitly segmented episodes, on ``[N, T]`` float64 lists.

    Deliberately not the kernels' backward recurrence: each return is the sum
    ``sum_k (prod_{j<k} gamma_j) r_k`` over its episode, plus the discounted bootstrap.
    """
    out = []
    for r, d, term, nv, g in zip(reward, done, terminated, next_value, gamma, strict=True):
        n_steps = len(r)
        ends = [t for t in range(n_steps) if d[t] or term[t]]
        if not ends or ends[-1] != n_steps - 1:
            ends.append(n_steps - 1)
        row = [0.0] * n_steps
        start = 0
        for end in ends:
            boot = 0.0 if term[end] or nv is None else nv[end]
            for t in range(start, end + 1):
                total, discount = 0.0, 1.0
                for k in range(t, end + 1):
                    total += discount * r[k]
                    discount *= g[k]
                row[t] = total + discount * boot
            if whole_episode:
                row[start : end + 1] = [row[start]] * (end + 1 - start)
            start = end + 1
        out.append(row)
    return out


@st.composite
def return_problems(draw):
    """Random batches: layouts, episode boundaries, truncations, cut rows and discounts."""
    batch = draw(st.lists(st.integers(1, 3), min_size=0, max_size=2))
    n_steps = draw(st.integers(1, 24))
    feature_dim = draw(st.booleans())  # TorchRL's trailing singleton
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    generator = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    p_done = draw(st.sampled_from([0.0, 0.05, 0.3, 1.0]))
    canonical = (*batch, n_steps)
    reward = torch.randn(canonical, generator=generator, dtype=torch.float64)
    done = torch.rand(canonical, generator=generator) < p_done
    terminated = done & (torch.rand(canonical, generator=generator) < 0.5)
    with_terminated = draw(st.booleans())
    if not with_terminated:
        terminated = done.clone()
    next_value = None
    if draw(st.booleans()):
        next_value = torch.randn(canonical, generator=generator, dtype=torch.float64)
        # Values at terminated steps are never read, so NaN there must be harmless.
        next_value = next_value.masked_fill(terminated, float("nan"))
    gamma_kind = draw(st.sampled_from(["0", "0.5", "0.99", "1", "per_step", "per_row"]))
    if gamma_kind == "per_step":
        gamma = torch.rand(canonical, generator=generator, dtype=torch.float64)
    elif gamma_kind == "per_row":
        gamma = torch.rand((*batch, 1), generator=generator, dtype=torch.float64)
    else:
        gamma = float(gamma_kind)
    gamma_full = torch.broadcast_to(torch.as_tensor(gamma, dtype=torch.float64), canonical)

    def rows(x):
        return None if x is None else x.reshape(-1, n_steps).tolist()

    expected = {
        whole: torch.tensor(
            reference_returns(
                rows(reward),
                rows(done),
                rows(terminated),
                rows(next_value) or [None] * max(1, math.prod(batch)),
                rows(gamma_full),
                whole,
            ),
            dtype=torch.float64,
        ).reshape(canonical)
        for whole in (False, True)
    }

    # Lay the tensors out as the caller would: time at a random position, optional
    # trailing feature dimension.
    time_pos = draw(st.integers(0, len(batch)))

    def layout(x):
        if x is None or (isinstance(x, float)):
            return x
        x = x.movedim(-1, time_pos)
        return x.unsqueeze(-1) if feature_dim else x

    ndim = len(canonical) + feature_dim
    time_dim = time_pos - ndim if draw(st.booleans()) else time_pos
    if isinstance(gamma, torch.Tensor):
        gamma = layout(gamma_full).to(dtype)
    kwargs = {
        "time_dim": time_dim,
        "terminated": layout(terminated) if with_terminated else None,
        "next_value": None if next_value is None else layout(next_value).to(dtype),
    }
    args = (layout(reward).to(dtype), layout(done), gamma)
    return args, kwargs, {k: layout(v) for k, v in expected.items()}, dtype


def _tolerance(dtype):
    return (
        {"rtol": 1e-4, "atol": 1e-4} if dtype == torch.float32 else {"rtol": 1e-10, "atol": 1e-10}
    )


KERNELS = [(reward_to_go, False), (discounted_return, True)]


@pytest.mark.parametrize(("fn", "whole_episode"), KERNELS)
class TestAgainstPlainLoop:
    @settings(max_examples=300, deadline=None)
    @given(problem=return_problems())
    def test_fast_path(self, fn, whole_episode, problem):
        args, kwargs, expected, dtype = problem
        out = fn(*args, **kwargs)
        assert out.dtype == dtype and out.shape == args[0].shape
        torch.testing.assert_close(out.double(), expected[whole_episode], **_tolerance(dtype))

    @settings(max_examples=100, deadline=None)
    @given(problem=return_problems())
    def test_autograd_path(self, fn, whole_episode, problem):
        args, kwargs, expected, dtype = problem
        reward = args[0].clone().requires_grad_(True)
        out = fn(reward, *args[1:], **kwargs)
        torch.testing.assert_close(
            out.double().detach(), expected[whole_episode], **_tolerance(dtype)
        )


class TestRewardToGo:
    def test_gradient_flows_into_next_value(self):
        reward = torch.zeros(1, 3, 1)
        done = torch.zeros(1, 3, 1, dtype=torch.bool)
        next_value = torch.ones(1, 3, 1, requires_grad=True)
        reward_to_go(reward, done, 0.5, next_value=next_value).sum().backward()
        # Only the cut last step bootstraps: G = (0.125, 0.25, 0.5) * V.
        assert next_value.grad.squeeze().tolist() == [0.0, 0.0, 0.875]

    def test_half_precision_runs_on_the_fallback(self):
        reward = torch.ones(2, 4, 1, dtype=torch.bfloat16)
        done = torch.zeros(2, 4, 1, dtype=torch.bool)
        out = reward_to_go(reward, done, 1.0)
        assert out.dtype == torch.bfloat16
        assert out[0, :, 0].tolist() == [4.0, 3.0, 2.0, 1.0]

    def test_integer_done_is_accepted(self):
        reward = torch.ones(3, 1)
        done = torch.tensor([[0], [1], [0]])
        assert reward_to_go(reward, done, 1.0).squeeze(-1).tolist() == [2.0, 1.0, 1.0]


class TestDiscountedReturn:
    def test_every_step_gets_its_episode_return(self):
        reward = torch.tensor([[1.0, 1.0, 1.0, 1.0]])
        done = torch.tensor([[False, True, False, True]])
        out = discounted_return(reward, done, 1.0, time_dim=-1)
        assert out.tolist() == [[2.0, 2.0, 2.0, 2.0]]


@pytest.mark.parametrize("fn", [reward_to_go, discounted_return])
class TestBadInput:
    def test_empty_batch(self, fn):
        with pytest.raises(ValueError, match="empty batch"):
            fn(torch.zeros(0, 5, 1), torch.zeros(0, 5, 1, dtype=torch.bool), 0.9)

    def test_done_shape_mismatch(self, fn):
        with pytest.raises(ValueError, match=r"done must have the shape of reward \(4, 5, 1\)"):
            fn(torch.zeros(4, 5, 1), torch.zeros(4, 5, dtype=torch.bool), 0.9)

    def test_next_value_shape_mismatch(self, fn):
        with pytest.raises(ValueError, match="next_value must have the shape"):
            fn(
                torch.zeros(4, 5, 1),
                torch.zeros(4, 5, 1, dtype=torch.bool),
                0.9,
                next_value=torch.zeros(4, 6, 1),
            )

    @pytest.mark.parametrize("gamma", [-0.1, 1.5, float("nan"), float("inf")])
    def test_gamma_outside_unit_interval(self, fn, gamma):
        with pytest.raises(ValueError, match=r"gamma must be a finite number >= 0 and <= 1"):
            fn(torch.zeros(2, 3, 1), torch.zeros(2, 3, 1, dtype=torch.bool), gamma)

    @pytest.mark.parametrize("gamma", ["0.9", True, None, [0.9]])
    def test_gamma_that_is_not_a_number(self, fn, gamma):
        with pytest.raises(TypeError, match="gamma must be a real number"):
            fn(torch.zeros(2, 3, 1), torch.zeros(2, 3, 1, dtype=torch.bool), gamma)

    @pytest.mark.parametrize(
        "gamma", [np.float32(0.9), np.float64(0.9), torch.tensor(0.9), np.array(0.9)]
    )
    def test_gamma_as_a_numpy_or_torch_scalar(self, fn, gamma):
        reward = torch.ones(2, 3, 1)
        done = torch.zeros(2, 3, 1, dtype=torch.bool)
        torch.testing.assert_close(fn(reward, done, gamma), fn(reward, done, 0.9))

    @pytest.mark.parametrize("bad", [1.01, float("nan")])
    def test_gamma_tensor_outside_unit_interval(self, fn, bad):
        gamma = torch.full((2, 1, 1), 0.5)
        gamma[1] = bad
        with pytest.raises(ValueError, match=r"gamma must lie in \[0, 1\], got a value of"):
            fn(torch.zeros(2, 3, 1), torch.zeros(2, 3, 1, dtype=torch.bool), gamma)

    def test_gamma_tensor_that_does_not_broadcast(self, fn):
        with pytest.raises(ValueError, match="does not broadcast"):
            fn(torch.zeros(2, 3, 1), torch.zeros(2, 3, 1, dtype=torch.bool), torch.ones(4))

    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_non_finite_reward(self, fn, bad):
        reward = torch.zeros(2, 3, 1)
        reward[1, 2, 0] = bad
        with pytest.raises(ValueError, match=r"reward holds 1 non-finite value\(s\) .*\(1, 2, 0\)"):
            fn(reward, torch.zeros(2, 3, 1, dtype=torch.bool), 0.9)

    @pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
    @pytest.mark.parametrize("with_next_value", [False, True])
    def test_non_finite_reward_in_a_row_of_one_step(self, fn, bad, with_next_value):
        # The last step of a row is computed apart from the others: it is checked too.
        reward = torch.tensor([[[1.0]], [[bad]]])
        done = torch.tensor([[[False]], [[True]]])
        next_value = torch.zeros_like(reward) if with_next_value else None
        with pytest.raises(ValueError, match=r"reward holds 1 non-finite value\(s\)"):
            fn(reward, done, 0.9, next_value=next_value)

    @pytest.mark.parametrize("last_done", [False, True])
    def test_non_finite_reward_on_the_last_step_with_a_bootstrap(self, fn, last_done):
        reward = torch.ones(2, 4, 1)
        reward[0, 3, 0] = float("inf")
        done = torch.zeros(2, 4, 1, dtype=torch.bool)
        done[:, 2] = True  # the last step is an episode of its own: nothing carries inf back
        done[:, 3] = last_done
        with pytest.raises(ValueError, match=r"reward holds 1 non-finite .*\(0, 3, 0\)"):
            fn(reward, done, 0.9, next_value=torch.zeros(2, 4, 1))

    def test_non_finite_next_value_where_it_bootstraps(self, fn):
        next_value = torch.zeros(2, 3, 1)
        next_value[0, 2, 0] = float("nan")
        with pytest.raises(
            ValueError, match=r"next_value holds 1 non-finite value\(s\) .*\(0, 2, 0\)"
        ):
            fn(
                torch.zeros(2, 3, 1),
                torch.zeros(2, 3, 1, dtype=torch.bool),
                0.9,
                next_value=next_value,
            )

    def test_non_finite_next_value_where_it_is_not_read(self, fn):
        # Mid-episode and at terminated steps V(s') is never used (TorchRL leaves NaN there).
        next_value = torch.full((1, 4, 1), float("nan"))
        next_value[0, 3] = 2.0
        done = torch.tensor([[[False], [True], [False], [False]]])
        result = fn(torch.ones(1, 4, 1), done, 0.5, next_value=next_value)
        assert torch.isfinite(result).all()

    @pytest.mark.parametrize("name", ["done", "terminated"])
    @pytest.mark.parametrize("bad", [0.3, float("nan"), 2.0, -1.0])
    def test_mask_that_is_not_zero_or_one(self, fn, name, bad):
        mask = torch.zeros(2, 3, 1)
        mask[1, 1] = bad
        masks = {"done": torch.zeros(2, 3, 1, dtype=torch.bool), "terminated": None}
        masks[name] = mask
        with pytest.raises(ValueError, match=f"{name} must be boolean \\(or hold only 0 and 1\\)"):
            fn(torch.ones(2, 3, 1), masks["done"], 0.9, terminated=masks["terminated"])

    @pytest.mark.parametrize("dtype", [torch.float32, torch.int64, torch.uint8])
    def test_zero_one_masks_of_any_dtype(self, fn, dtype):
        done = torch.tensor([[[0], [1], [0]]])
        expected = fn(torch.ones(1, 3, 1), done.bool(), 0.5)
        torch.testing.assert_close(fn(torch.ones(1, 3, 1), done.to(dtype), 0.5), expected)

    @pytest.mark.parametrize("time_dim", [None, 1.0, "-2", True])
    def test_time_dim_that_is_not_an_integer(self, fn, time_dim):
        with pytest.raises(TypeError, match="time_dim must be an integer"):
            fn(torch.zeros(2, 3, 1), torch.zeros(2, 3, 1, dtype=torch.bool), 0.9, time_dim=time_dim)

    def test_time_dim_as_a_numpy_integer(self, fn):
        reward, done = torch.ones(2, 3), torch.zeros(2, 3, dtype=torch.bool)
        torch.testing.assert_close(
            fn(reward, done, 0.9, time_dim=np.int64(-1)), fn(reward, done, 0.9, time_dim=-1)
        )

    def test_done_that_is_not_a_tensor(self, fn):
        with pytest.raises(TypeError, match=r"done must be a tensor shaped like reward"):
            fn(torch.zeros(1, 3), [[0, 0, 1]], 0.9, time_dim=-1)

    def test_integer_next_value(self, fn):
        with pytest.raises(TypeError, match="next_value must be a floating-point tensor"):
            fn(
                torch.zeros(1, 3),
                torch.zeros(1, 3, dtype=torch.bool),
                0.9,
                time_dim=-1,
                next_value=torch.zeros(1, 3, dtype=torch.long),
            )

    def test_overflow(self, fn):
        with pytest.raises(ValueError, match="The returns overflowed to inf"):
            fn(torch.full((1, 3), 3e38), torch.zeros(1, 3, dtype=torch.bool), 1.0, time_dim=-1)

    def test_time_dim_out_of_range(self, fn):
        with pytest.raises(ValueError, match="time_dim=-2 is out of range"):
            fn(torch.zeros(5), torch.zeros(5, dtype=torch.bool), 0.9)

    def test_time_dim_one_past_the_last_dimension(self, fn):
        with pytest.raises(ValueError, match="time_dim=2 is out of range"):
            fn(torch.zeros(2, 3), torch.zeros(2, 3, dtype=torch.bool), 0.9, time_dim=2)

    def test_gamma_tensor_on_the_bounds_is_accepted(self, fn):
        # 0 and 1 belong to [0, 1]: a row of each, as per-row discounts.
        reward, done = torch.ones(2, 3, 1), torch.zeros(2, 3, 1, dtype=torch.bool)
        both = fn(reward, done, torch.tensor([[[1.0]], [[0.0]]]))
        torch.testing.assert_close(both[0], fn(reward, done, 1.0)[0])
        torch.testing.assert_close(both[1], fn(reward, done, 0.0)[1])

    def test_gamma_tensor_names_its_first_value_outside_the_bounds(self, fn):
        gamma = torch.tensor([1.0, 0.0, 2.0, 3.0]).reshape(4, 1, 1)
        with pytest.raises(ValueError, match=r"got a value of 2\.0\."):
            fn(torch.zeros(4, 3, 1), torch.zeros(4, 3, 1, dtype=torch.bool), gamma)

    @pytest.mark.parametrize("dtype", [torch.bool, torch.complex64])
    def test_gamma_tensor_of_booleans_or_complex_numbers(self, fn, dtype):
        gamma = torch.ones(2, 1, 1, dtype=dtype)
        with pytest.raises(TypeError, match="gamma must hold real numbers"):
            fn(torch.zeros(2, 3, 1), torch.zeros(2, 3, 1, dtype=torch.bool), gamma)

    def test_a_one_element_gamma_tensor_is_a_number_whatever_its_shape(self, fn):
        reward, done = torch.ones(2, 3, 1), torch.zeros(2, 3, 1, dtype=torch.bool)
        gamma = torch.full((1, 1, 1, 1), 0.5)  # more dimensions than the rewards
        torch.testing.assert_close(fn(reward, done, gamma), fn(reward, done, 0.5))

    def test_a_mask_names_its_first_value_that_is_not_zero_or_one(self, fn):
        done = torch.tensor([[[0.0], [1.0], [0.5]]])
        with pytest.raises(ValueError, match=r"with value 0\.5\."):
            fn(torch.ones(1, 3, 1), done, 0.9)

    def test_integer_reward(self, fn):
        with pytest.raises(TypeError, match="reward must be a floating-point tensor"):
            fn(torch.zeros(2, 3, 1, dtype=torch.long), torch.zeros(2, 3, 1, dtype=torch.bool), 0.9)


# ---------------------------------------------------------------------------------------
# Malformed inputs: a correct result or an error that names what was wrong, never a
# non-finite (or silently wrong) result from inputs that look fine.

_CORRUPTIONS = (
    "nan_reward",
    "inf_reward",
    "int_reward",
    "fractional_done",
    "nan_done",
    "zero_one_float_done",
    "zero_one_int_done",
    "done_shape",
    "fractional_terminated",
    "bad_gamma",
    "numpy_gamma",
    "tensor_gamma",
    "bad_time_dim",
    "nan_next_value_read",
    "nan_next_value_unread",
    "int_next_value",
)
_VALID = {"zero_one_float_done", "zero_one_int_done", "numpy_gamma", "tensor_gamma"}
_VALID |= {"nan_next_value_unread"}
_NAMES = {  # the argument an error must name for each corruption
    "nan_reward": "reward",
    "inf_reward": "reward",
    "int_reward": "reward",
    "fractional_done": "done",
    "nan_done": "done",
    "done_shape": "done",
    "fractional_terminated": "terminated",
    "bad_gamma": "gamma",
    "bad_time_dim": "time_dim",
    "nan_next_value_read": "next_value",
    "int_next_value": "next_value",
}


@st.composite
def malformed_problems(draw):
    rows, n_steps = draw(st.integers(1, 4)), draw(st.integers(1, 12))
    generator = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    reward = torch.randn(rows, n_steps, generator=generator)
    done = torch.rand(rows, n_steps, generator=generator) < 0.3
    terminated = done & (torch.rand(rows, n_steps, generator=generator) < 0.5)
    next_value = torch.randn(rows, n_steps, generator=generator)
    kwargs = {"time_dim": -1, "terminated": terminated, "next_value": next_value}
    gamma = draw(st.sampled_from([0.0, 0.9, 1.0]))
    corruptions = draw(st.lists(st.sampled_from(_CORRUPTIONS), max_size=3, unique=True))
    at = (draw(st.integers(0, rows - 1)), draw(st.integers(0, n_steps - 1)))
    # Where V(s') is read: an episode's truncation or the row's end, unless terminated.
    read = (done | (torch.arange(n_steps) == n_steps - 1)) & ~terminated
    unread = ~read

    def next_is_float():
        return kwargs["next_value"].is_floating_point()

    applied = []
    for corruption in corruptions:
        if corruption == "nan_reward" and reward.is_floating_point():
            reward[at] = float("nan")
        elif corruption == "inf_reward" and reward.is_floating_point():
            reward[at] = draw(st.sampled_from([float("inf"), -float("inf")]))
        elif corruption == "int_reward":
            reward = reward.round().long()
        elif corruption in ("fractional_done", "nan_done"):
            done = done.float()
            done[at] = 0.3 if corruption == "fractional_done" else float("nan")
        elif corruption == "zero_one_float_done" and done.dtype == torch.bool:
            done = done.float()
        elif corruption == "zero_one_int_done" and done.dtype == torch.bool:
            done = done.to(torch.uint8)
        elif corruption == "done_shape":
            done = done.unsqueeze(-1)
        elif corruption == "fractional_terminated":
            kwargs["terminated"] = terminated.float()
            kwargs["terminated"][at] = 0.5
        elif corruption == "bad_gamma":
            bad = [float("nan"), -0.1, 1.5, float("inf"), "0.9", None, True]
            gamma = draw(st.sampled_from(bad))
        elif corruption == "numpy_gamma" and isinstance(gamma, float):
            gamma = np.float32(gamma)
        elif corruption == "tensor_gamma" and isinstance(gamma, float):
            gamma = torch.tensor(gamma)
        elif corruption == "bad_time_dim":
            kwargs["time_dim"] = draw(st.sampled_from([None, 1.0, True, 2, -3]))
        elif corruption == "nan_next_value_read" and read.any() and next_is_float():
            kwargs["next_value"][tuple(read.nonzero()[0])] = float("nan")
        elif corruption == "nan_next_value_unread" and unread.any() and next_is_float():
            kwargs["next_value"][tuple(unread.nonzero()[0])] = float("nan")
        elif corruption == "int_next_value":
            kwargs["next_value"] = kwargs["next_value"].round().long()
        else:
            continue  # does not apply to this problem
        applied.append(corruption)
    return reward, done, gamma, kwargs, applied


@settings(max_examples=400, deadline=None)
@given(problem=malformed_problems(), whole_episode=st.booleans())
def test_malformed_inputs_give_a_correct_result_or_a_clear_error(problem, whole_episode):
    reward, done, gamma, kwargs, corruptions = problem
    fn = discounted_return if whole_episode else reward_to_go
    invalid = [c for c in corruptions if c not in _VALID]
    try:
        result = fn(reward, done, gamma, **kwargs)
    except (TypeError, ValueError) as err:
        assert invalid, f"valid inputs {corruptions} were refused: {err}"
        names = {_NAMES[c] for c in invalid}
        assert any(name in str(err) for name in names), (names, str(err))
        return
    assert not invalid, f"{invalid} went through and gave {result}"
    assert torch.isfinite(result).all()
    as_list = lambda x: x.double().reshape(reward.shape).tolist()  # noqa: E731
    n_rows, n_steps = reward.shape
    expected = reference_returns(
        as_list(reward),
        as_list(done.bool()),
        as_list(kwargs["terminated"].bool()),
        as_list(torch.nan_to_num(kwargs["next_value"], nan=0.0)),
        torch.full((n_rows, n_steps), float(gamma), dtype=torch.float64).tolist(),
        whole_episode,
    )
    expected = torch.tensor(expected, dtype=torch.float64)
    torch.testing.assert_close(result.double(), expected, rtol=1e-4, atol=1e-4)
