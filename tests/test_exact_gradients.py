"""ReinforceLoss's gradient estimates against exact policy gradients.

On a bandit and on a tabular 4x4 gridworld, J(theta) is computed in closed form (a
sum over arms; a linear solve for the gridworld's values), so autograd gives the
exact gradient. Each variant of the estimator (return x baseline) produces K
independent estimates, each from its own batch, through the real ``ReinforceLoss``
and autograd; their mean must match the exact gradient.

Tolerance: the mean of K estimates has per-component standard error SE = s / sqrt(K).
By the central limit theorem each component's z = (mean - exact) / SE is close to
N(0, 1); we require |z| <= 5 for every component (P(|z| > 5) ~ 6e-7 per component,
< 1e-3 over all components and variants). The seeds are fixed, so the test is
deterministic; the negative control shows that the same check does reject a biased
estimator.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ProbabilisticActor, ValueOperator

from rl_pg import DiscountedReturn, ReinforceLoss, RewardToGo

Z_MAX = 5.0


def _tabular_actor(n_states: int, n_actions: int, logits: torch.Tensor) -> ProbabilisticActor:
    """Softmax policy whose logits for state s are ``logits[s]`` (one-hot observations)."""
    linear = nn.Linear(n_states, n_actions, bias=False, dtype=torch.float64)
    with torch.no_grad():
        linear.weight.copy_(logits.T)
    return ProbabilisticActor(
        TensorDictModule(linear, ["observation"], ["logits"]),
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
    )


def _tabular_critic(values: torch.Tensor) -> ValueOperator:
    linear = nn.Linear(values.numel(), 1, bias=False, dtype=torch.float64)
    with torch.no_grad():
        linear.weight.copy_(values.unsqueeze(0))
    return ValueOperator(linear, in_keys=["observation"])


def _estimates(loss: ReinforceLoss, batches: list[TensorDict], n_episodes: int) -> torch.Tensor:
    """One gradient-ascent direction per batch: -d(sum of actor losses)/d(theta) / episodes."""
    weight = loss.actor_network_params["module", "0", "module", "weight"]
    out = []
    for batch in batches:
        losses = loss(batch.clone())
        (grad,) = torch.autograd.grad(losses["loss_actor"], weight)
        out.append(-grad.flatten() / n_episodes)
    return torch.stack(out)


def _z_scores(estimates: torch.Tensor, exact: torch.Tensor) -> torch.Tensor:
    se = estimates.std(0) / estimates.shape[0] ** 0.5
    return (estimates.mean(0) - exact.flatten()) / se.clamp_min(1e-12)


def _make_loss(actor, critic, value_type, baseline, gamma=1.0):
    loss = ReinforceLoss(actor, critic, baseline=baseline, reduction="sum", baseline_rate=0.1)
    loss.make_value_estimator(value_type, gamma=gamma)
    return loss


# --------------------------------------------------------------------- bandit ---
N_ARMS = 10
ARM_REWARDS = torch.tensor([1.0] + [0.9] * (N_ARMS // 2 - 1) + [0.0] * (N_ARMS // 2)).double()


def _bandit_batches(logits, n_batches, n_samples, seed):
    generator = torch.Generator().manual_seed(seed)
    probs = logits.softmax(-1)
    batches = []
    for _ in range(n_batches):
        action = torch.multinomial(probs[0], n_samples, replacement=True, generator=generator)
        batches.append(
            TensorDict(
                {
                    "observation": torch.ones(n_samples, 1, dtype=torch.float64),
                    "action": action,
                    "next": {
                        "observation": torch.ones(n_samples, 1, dtype=torch.float64),
                        "reward": ARM_REWARDS[action].unsqueeze(-1),
                        "done": torch.ones(n_samples, 1, dtype=torch.bool),
                    },
                },
                batch_size=[n_samples],
            )
        )
    return batches


@pytest.fixture(scope="module")
def bandit():
    torch.manual_seed(0)
    logits = torch.randn(1, N_ARMS, dtype=torch.float64)
    theta = logits.clone().requires_grad_(True)
    (exact,) = torch.autograd.grad((theta.softmax(-1) * ARM_REWARDS).sum(), theta)
    return logits, exact


BANDIT_VARIANTS = [
    ("none", None),
    ("running_mean", None),
    ("ema", None),
    ("critic", "oracle"),
    ("critic", "arbitrary"),
]


class TestBanditGradient:
    @pytest.mark.parametrize(("baseline", "critic_kind"), BANDIT_VARIANTS)
    def test_unbiased(self, bandit, baseline, critic_kind):
        logits, exact = bandit
        critic = None
        if critic_kind is not None:
            value = (logits.softmax(-1) * ARM_REWARDS).sum() if critic_kind == "oracle" else 5.0
            critic = _tabular_critic(torch.tensor([float(value)], dtype=torch.float64))
        loss = _make_loss(_tabular_actor(1, N_ARMS, logits), critic, RewardToGo, baseline)
        # 16 000 pulls, 32 per estimate: the power depends on the total, the cost on
        # the number of estimates (one loss call each).
        estimates = _estimates(loss, _bandit_batches(logits, 500, 32, seed=1), 32)
        assert _z_scores(estimates, exact).abs().max() <= Z_MAX

    def test_batch_mean_shrinks_the_gradient_by_one_over_n(self, bandit):
        # b = mean of the batch including the sample itself: E[g] = (1 - 1/N) grad J.
        logits, exact = bandit
        n = 4
        loss = _make_loss(_tabular_actor(1, N_ARMS, logits), None, RewardToGo, "batch_mean")
        estimates = _estimates(loss, _bandit_batches(logits, 2000, n, seed=2), n)
        assert _z_scores(estimates, (1 - 1 / n) * exact).abs().max() <= Z_MAX
        # Negative control: the check has the power to see that 25% bias.
        assert _z_scores(estimates, exact).abs().max() > Z_MAX

    def test_baselines_lower_the_variance(self, bandit):
        logits, _ = bandit
        batches = _bandit_batches(logits, 400, 8, seed=3)
        variance = {}
        for baseline in ("none", "running_mean"):
            loss = _make_loss(_tabular_actor(1, N_ARMS, logits), None, RewardToGo, baseline)
            variance[baseline] = _estimates(loss, batches, 8).var(0).sum()
        assert variance["running_mean"] < 0.5 * variance["none"]


# ------------------------------------------------------------------ gridworld ---
SIDE = 4
START, PIT, GOAL = 0, 10, 15
STEP_REWARD = -0.1
MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1))  # up, down, left, right


def _gridworld_tables():
    """Next state and reward of every (state, action); terminal cells absorb."""
    next_state = torch.zeros(SIDE * SIDE, len(MOVES), dtype=torch.long)
    for s in range(SIDE * SIDE):
        row, col = divmod(s, SIDE)
        for a, (dr, dc) in enumerate(MOVES):
            r, c = row + dr, col + dc
            next_state[s, a] = r * SIDE + c if 0 <= r < SIDE and 0 <= c < SIDE else s
    reward = torch.full(next_state.shape, STEP_REWARD, dtype=torch.float64)
    reward[next_state == GOAL] = 1.0
    reward[next_state == PIT] = -1.0
    return next_state, reward


NEXT_STATE, REWARD = _gridworld_tables()
TERMINAL = torch.zeros(SIDE * SIDE, dtype=torch.bool)
TERMINAL[[PIT, GOAL]] = True


def _state_values(logits: torch.Tensor) -> torch.Tensor:
    """v_pi by solving (I - P_pi) v = r_pi over the non-terminal states (gamma = 1)."""
    probs = logits.softmax(-1)
    n = SIDE * SIDE
    transition = torch.zeros(n, n, dtype=torch.float64)
    transition = transition.index_put((torch.arange(n).unsqueeze(-1), NEXT_STATE), probs, True)
    transition[:, TERMINAL] = 0.0
    transition[TERMINAL] = 0.0
    expected_reward = (probs * REWARD).sum(-1).masked_fill(TERMINAL, 0.0)
    return torch.linalg.solve(torch.eye(n, dtype=torch.float64) - transition, expected_reward)


def _gridworld_batches(logits, n_batches, n_episodes, seed, max_steps=2000):
    """Episodes laid back to back in flat batches, sampled from the tabular policy."""
    generator = torch.Generator().manual_seed(seed)
    n = n_batches * n_episodes
    probs = logits.softmax(-1)
    state = torch.full((n,), START)
    alive = torch.ones(n, dtype=torch.bool)
    columns = []
    for _ in range(max_steps):
        action = torch.multinomial(probs[state], 1, generator=generator).squeeze(-1)
        next_state = NEXT_STATE[state, action]
        done = TERMINAL[next_state]
        columns.append((state, action, REWARD[state, action], done, alive))
        state, alive = next_state, alive & ~done
        if not alive.any():
            break
    assert not alive.any(), "an episode outlived max_steps; the estimate would be truncated"
    state, action, reward, done, valid = (torch.stack(x, 1) for x in zip(*columns, strict=True))
    eye = torch.eye(SIDE * SIDE, dtype=torch.float64)
    batches = []
    for k in range(n_batches):
        rows = slice(k * n_episodes, (k + 1) * n_episodes)
        mask = valid[rows]  # row-major: episode after episode
        batches.append(
            TensorDict(
                {
                    "observation": eye[state[rows][mask]],
                    "action": action[rows][mask],
                    "next": {
                        "observation": eye[NEXT_STATE[state[rows][mask], action[rows][mask]]],
                        "reward": reward[rows][mask].unsqueeze(-1),
                        "done": done[rows][mask].unsqueeze(-1),
                    },
                },
                batch_size=[int(mask.sum())],
            )
        )
    return batches


# 6 000 episodes in all, 16 per gradient estimate: the z-test's power depends on the
# total, its cost on the number of estimates (one loss call each).
GRID_ESTIMATES, GRID_EPISODES = 375, 16


# Session-scoped: a test process (pytest-xdist) that is handed this module's tests in
# several chunks would otherwise tear these down between chunks and rebuild them.
@pytest.fixture(scope="session")
def gridworld():
    torch.manual_seed(0)
    logits = 0.5 * torch.randn(SIDE * SIDE, len(MOVES), dtype=torch.float64)
    theta = logits.clone().requires_grad_(True)
    values = _state_values(theta)
    (exact,) = torch.autograd.grad(values[START], theta)
    batches = _gridworld_batches(logits, GRID_ESTIMATES, GRID_EPISODES, seed=1)
    return logits, exact.T.contiguous(), values.detach(), batches


GRIDWORLD_VARIANTS = [
    (value_type, baseline)
    for value_type in (DiscountedReturn, RewardToGo)
    for baseline in ("none", "running_mean", "ema", "critic")
]


def _gridworld_estimates(gridworld, value_type, baseline, critic_values=None):
    logits, _, values, batches = gridworld
    critic = None
    if baseline == "critic":
        critic = _tabular_critic(values if critic_values is None else critic_values)
    actor = _tabular_actor(SIDE * SIDE, len(MOVES), logits)
    return _estimates(_make_loss(actor, critic, value_type, baseline), batches, GRID_EPISODES)


@pytest.fixture(scope="session")
def gridworld_estimates(gridworld):
    return {
        (value_type.__name__, baseline): _gridworld_estimates(gridworld, value_type, baseline)
        for value_type, baseline in GRIDWORLD_VARIANTS
    }


class TestGridworldGradient:
    @pytest.mark.parametrize(("value_type", "baseline"), GRIDWORLD_VARIANTS)
    def test_unbiased(self, gridworld, gridworld_estimates, value_type, baseline):
        estimates = gridworld_estimates[value_type.__name__, baseline]
        assert _z_scores(estimates, gridworld[1]).abs().max() <= Z_MAX

    def test_any_state_only_critic_is_unbiased(self, gridworld):
        arbitrary = torch.linspace(-3, 3, SIDE * SIDE, dtype=torch.float64)
        estimates = _gridworld_estimates(gridworld, RewardToGo, "critic", arbitrary)
        assert _z_scores(estimates, gridworld[1]).abs().max() <= Z_MAX

    def test_reward_to_go_and_baselines_lower_the_variance(self, gridworld_estimates):
        variance = {key: value.var(0).sum() for key, value in gridworld_estimates.items()}
        # The table quoted in README.md: pytest tests/test_exact_gradients.py -s -k variance
        for (value_type, baseline), total in variance.items():
            print(f"{value_type:16s} {baseline:12s} total variance {total:9.4f}")
        for baseline in ("none", "running_mean", "critic"):
            assert variance["RewardToGo", baseline] < variance["DiscountedReturn", baseline]
        for value_type in ("DiscountedReturn", "RewardToGo"):
            assert variance[value_type, "critic"] < variance[value_type, "none"]
            assert variance[value_type, "running_mean"] < variance[value_type, "none"]
