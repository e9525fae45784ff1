"""The scalar baselines' update rules and state."""

from __future__ import annotations

import pytest
import torch

from rl_pg.baselines import BatchMean, ExponentialMovingAverage, RunningMean, make_baseline


class TestBatchMean:
    def test_is_the_mean_of_the_batch(self):
        assert BatchMean()(torch.tensor([1.0, 2.0, 3.0, 6.0])) == 3.0


class TestRunningMean:
    def test_answers_before_taking_the_batch_in(self):
        baseline = RunningMean()
        assert baseline(torch.tensor([2.0, 4.0])) == 0.0
        assert baseline(torch.tensor([9.0])) == 3.0
        assert baseline.value == 5.0

    def test_state_round_trip(self):
        baseline = RunningMean()
        baseline(torch.arange(10.0))
        restored = RunningMean()
        restored.load_state_dict(baseline.state_dict())
        assert restored.value == baseline.value == 4.5

    def test_eval_mode_freezes_it(self):
        baseline = RunningMean().eval()
        baseline(torch.ones(3))
        assert baseline.count == 0

    def test_answers_in_the_returns_dtype(self):
        baseline = RunningMean()
        baseline(torch.tensor([1.0, 2.0]))
        answer = baseline(torch.tensor([5.0], dtype=torch.float64))
        assert answer.dtype == torch.float64 and answer.item() == 1.5

    def test_accumulates_beyond_float32(self):
        """One large return then small ones: a float32 total would drop every 1 added
        to 2**24 (its spacing there is 2), and the mean would stay at 2**24 / n."""
        baseline = RunningMean()
        baseline(torch.tensor([2.0**24]))
        for _ in range(2):
            baseline(torch.ones(1))
        assert baseline.value.item() == (2**24 + 2) / 3
        assert baseline.count.dtype == torch.int64 and baseline.count.item() == 3


class TestExponentialMovingAverage:
    def test_matches_sequential_updates(self):
        returns = torch.randn(50, dtype=torch.float64)
        baseline = ExponentialMovingAverage(rate=0.1)
        baseline(returns[:20])
        baseline(returns[20:])
        expected = 0.0
        for value in returns.tolist():
            expected = 0.9 * expected + 0.1 * value
        # float64 throughout: the closed form agrees with the loop to rounding
        assert baseline.value.item() == pytest.approx(expected, rel=1e-6)
        assert baseline._value.item() == pytest.approx(expected, rel=1e-12, abs=1e-15)

    def test_answers_before_taking_the_batch_in(self):
        baseline = ExponentialMovingAverage(rate=0.5)
        first = baseline(torch.tensor([4.0, 8.0], dtype=torch.float64))
        second = baseline(torch.tensor([1.0]))
        assert (first.item(), first.dtype) == (0.0, torch.float64)
        assert (second.item(), second.dtype) == (5.0, torch.float32)  # 0 -> 2 -> 5
        assert baseline.value.item() == 3.0

    def test_default_rate_and_make_baseline_passes_its_rate(self):
        assert ExponentialMovingAverage().rate == make_baseline("ema").rate == 0.01
        assert make_baseline("ema", rate=0.3).rate == 0.3

    @pytest.mark.parametrize("rate", [0.0, 1.5, -0.1, float("nan")])
    def test_rate_outside_unit_interval(self, rate):
        with pytest.raises(ValueError, match=r"rate must be a finite number > 0 and <= 1"):
            ExponentialMovingAverage(rate=rate)

    @pytest.mark.parametrize("rate", [True, "0.1", None])
    def test_rate_that_is_not_a_number(self, rate):
        with pytest.raises(TypeError, match="rate must be a real number"):
            ExponentialMovingAverage(rate=rate)


class TestMakeBaseline:
    def test_unknown_name(self):
        with pytest.raises(ValueError, match="Unknown baseline 'median'"):
            make_baseline("median")

    def test_empty_returns(self):
        with pytest.raises(ValueError, match=r"^A baseline needs at least one episode return"):
            make_baseline("running_mean")(torch.zeros(0))

    @pytest.mark.parametrize("name", ["batch_mean", "running_mean", "ema"])
    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_non_finite_returns_leave_the_state_as_it_was(self, name, bad):
        baseline = make_baseline(name)
        baseline(torch.tensor([1.0, 3.0]))
        state = {k: v.clone() for k, v in baseline.state_dict().items()}
        with pytest.raises(ValueError, match="returns holds 1 non-finite value"):
            baseline(torch.tensor([2.0, bad, 4.0, 5.0]))
        for key, value in baseline.state_dict().items():
            torch.testing.assert_close(value, state[key])

    @pytest.mark.parametrize(
        ("returns", "error", "match"),
        [
            ([1.0, 2.0], TypeError, "returns must be a torch.Tensor.*Pass the episode returns"),
            (torch.tensor([1, 2]), TypeError, "returns must be a floating-point tensor"),
        ],
    )
    def test_returns_that_are_not_a_float_tensor(self, returns, error, match):
        with pytest.raises(error, match=match):
            make_baseline("running_mean")(returns)
