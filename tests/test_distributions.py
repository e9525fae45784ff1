"""BoundedBeta: an exact density on the bounds, and REINFORCE's gradient through it."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from rl_pg import ReinforceLoss
from rl_pg.distributions import BetaConcentrations, BoundedBeta

LOW, HIGH = torch.tensor([-2.0, 0.0]), torch.tensor([2.0, 5.0])


def _dist(alpha=(2.0, 0.7), beta=(3.0, 1.5), dtype=torch.float64):
    return BoundedBeta(
        torch.tensor(alpha, dtype=dtype), torch.tensor(beta, dtype=dtype),
        LOW.to(dtype), HIGH.to(dtype),
    )  # fmt: skip


class TestBoundedBeta:
    def test_density_is_the_betas_on_the_bounds(self):
        dist = _dist()
        value = torch.tensor([[0.5, 1.0], [-1.9, 4.9]], dtype=torch.float64)
        unit = (value - LOW) / (HIGH - LOW)
        reference = torch.distributions.Beta(
            torch.tensor([2.0, 0.7], dtype=torch.float64),
            torch.tensor([3.0, 1.5], dtype=torch.float64),
        )
        expected = (reference.log_prob(unit) - torch.log(HIGH - LOW)).sum(-1)
        torch.testing.assert_close(dist.log_prob(value), expected)

    def test_density_integrates_to_one_in_each_dimension(self):
        for dim in range(2):
            one = BoundedBeta(
                torch.tensor([[2.0, 0.7][dim]]), torch.tensor([[3.0, 1.5][dim]]),
                LOW[dim : dim + 1], HIGH[dim : dim + 1],
            )  # fmt: skip
            grid = torch.linspace(LOW[dim], HIGH[dim], 200_001)[1:-1].unsqueeze(-1)
            mass = torch.trapezoid(one.log_prob(grid).exp(), grid.squeeze(-1))
            assert mass.item() == pytest.approx(1.0, abs=2e-3)

    def test_samples_mean_and_entropy(self):
        torch.manual_seed(0)
        dist = _dist()
        sample = dist.sample((200_000,))
        assert bool((sample >= LOW).all() and (sample <= HIGH).all())
        n = sample.shape[0]
        standard_error = (dist.variance / n).sqrt()  # of the sample mean, per dimension
        assert bool(((sample.mean(0) - dist.mean).abs() < 4 * standard_error).all())
        # the variance, against the sample's (SE of a variance ~ sqrt((m4 - s^4) / n))
        centred = sample - sample.mean(0)
        spread = ((centred**4).mean(0) - centred.var(0) ** 2).sqrt() / n**0.5
        assert bool(((centred.var(0) - dist.variance).abs() < 4 * spread).all())
        assert torch.equal(dist.deterministic_sample, dist.mean)
        surprise = -dist.log_prob(sample)  # its mean estimates the entropy
        standard_error = surprise.std() / n**0.5
        assert abs(dist.entropy().item() - surprise.mean().item()) < 4 * standard_error

    def test_a_sample_on_a_bound_keeps_a_finite_log_probability(self):
        dist = _dist(dtype=torch.float32)
        assert torch.isfinite(dist.log_prob(torch.stack([LOW, HIGH]))).all()

    def test_bad_bounds_and_outputs(self):
        with pytest.raises(ValueError, match="high > low in every dimension"):
            BoundedBeta(torch.ones(2), torch.ones(2), torch.tensor([0.0, 1.0]), torch.ones(2))
        with pytest.raises(ValueError, match="even number of outputs"):
            BetaConcentrations()(torch.zeros(3))

    def test_greedy_action_is_the_mean(self):
        actor = _constant_actor(torch.tensor([0.3, -0.4]))
        td = TensorDict({"observation": torch.zeros(1)})
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            action = actor(td)["action"]
        alpha, beta = BetaConcentrations()(torch.tensor([0.3, -0.4]))
        torch.testing.assert_close(action, -2 + 4 * alpha / (alpha + beta))


class _Constant(nn.Module):
    """Concentrations that do not depend on the observation: the bandit's policy."""

    def __init__(self, raw: torch.Tensor):
        super().__init__()
        self.raw = nn.Parameter(raw.clone())

    def forward(self, observation):
        return BetaConcentrations()(self.raw.expand(*observation.shape[:-1], 2))


def _constant_actor(raw: torch.Tensor) -> ProbabilisticActor:
    return ProbabilisticActor(
        TensorDictModule(_Constant(raw), ["observation"], ["concentration1", "concentration0"]),
        in_keys=["concentration1", "concentration0"],
        distribution_class=BoundedBeta,
        distribution_kwargs={"low": torch.tensor(-2.0), "high": torch.tensor(2.0)},
        return_log_prob=False,
    )


def test_reinforce_gradient_matches_the_exact_one_on_a_continuous_bandit():
    """One step, a in [-2, 2], reward -(a - c)^2: J = -(Var a + (E a - c)^2) in closed
    form, so autograd gives the exact gradient; the mean of K REINFORCE estimates
    through ReinforceLoss must lie within 5 standard errors of it."""
    torch.manual_seed(0)
    raw, target = torch.tensor([0.3, -0.4], dtype=torch.float64), 1.2
    exact_raw = raw.clone().requires_grad_()
    alpha, beta = BetaConcentrations()(exact_raw)
    mean = -2 + 4 * alpha / (alpha + beta)
    var = 16 * alpha * beta / ((alpha + beta) ** 2 * (alpha + beta + 1))
    (exact,) = torch.autograd.grad(-(var + (mean - target) ** 2), exact_raw)

    actor = _constant_actor(raw).double()
    loss = ReinforceLoss(actor, baseline="none")
    loss.make_value_estimator("reward_to_go", gamma=1.0)
    param = next(actor.parameters())
    estimates = []
    n = 64
    for _ in range(200):
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            observation = torch.zeros(n, 1, 1, dtype=torch.float64)
            td = actor(TensorDict({"observation": observation}, [n, 1]))
        reward = -((td["action"] - target) ** 2)
        done = torch.ones(n, 1, 1, dtype=torch.bool)
        td["next"] = TensorDict(
            {"reward": reward, "done": done, "terminated": done, "truncated": ~done,
             "observation": td["observation"]}, [n, 1],
        )  # fmt: skip
        (grad,) = torch.autograd.grad(loss(td)["loss_actor"], param)
        estimates.append(-grad)
    estimates = torch.stack(estimates)
    z = (estimates.mean(0) - exact) / (estimates.std(0) / len(estimates) ** 0.5)
    assert z.abs().max() <= 5, (estimates.mean(0), exact)
    assert exact.abs().min() > 5 * estimates.std(0).max() / len(estimates) ** 0.5
