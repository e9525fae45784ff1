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


class TestExponentialMovingAverage:
    def test_matches_sequential_updates(self):
        returns = torch.randn(50, dtype=torch.float64)
        baseline = ExponentialMovingAverage(rate=0.1)
        baseline(returns[:20])
        baseline(returns[20:])
        expected = 0.0
        for value in returns.tolist():
            expected = 0.9 * expected + 0.1 * value
        assert baseline.value.item() == pytest.approx(expected, rel=1e-6)

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
        with pytest.raises(ValueError, match="at least one episode return"):
            make_baseline("running_mean")(torch.zeros(0))

    @pytest.mark.parametrize("name", ["batch_mean", "running_mean", "ema"])
    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_non_finite_returns_leave_the_state_as_it_was(self, name, bad):
        baseline = make_baseline(name)
        baseline(torch.tensor([1.0, 3.0]))
        state = {k: v.clone() for k, v in baseline.state_dict().items()}
        with pytest.raises(ValueError, match="returns holds 1 non-finite value"):
            baseline(torch.tensor([2.0, bad]))
        for key, value in baseline.state_dict().items():
            torch.testing.assert_close(value, state[key])

    @pytest.mark.parametrize(
        ("returns", "error", "match"),
        [
            ([1.0, 2.0], TypeError, "returns must be a torch.Tensor"),
            (torch.tensor([1, 2]), TypeError, "returns must be a floating-point tensor"),
        ],
    )
    def test_returns_that_are_not_a_float_tensor(self, returns, error, match):
        with pytest.raises(error, match=match):
            make_baseline("running_mean")(returns)
