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

import json
import os
from pathlib import Path

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


# -------------------------------------------------------------- group baselines ---
# Groups of GROUP episodes from the same start: on these environments every episode
# starts alike, so consecutive episodes of a batch form the groups. The greedy
# baseline adds one greedy episode per group, which the loss leaves out of its terms.
GROUP = 4


def _with_groups(batch: TensorDict, k: int = GROUP) -> TensorDict:
    """Consecutive episodes of a flat batch in groups of ``k``."""
    done = batch["next", "done"].squeeze(-1).long()
    return batch.set("group", (done.cumsum(0) - done) // k)


def _with_greedy(batch: TensorDict, greedy_episode: TensorDict, k: int = GROUP) -> TensorDict:
    """Groups of ``k`` episodes, each followed by a copy of the greedy episode."""
    batch = _with_groups(batch, k).set("greedy", torch.zeros(batch.shape, dtype=torch.bool))
    groups = int(batch["group"].max()) + 1
    steps = greedy_episode.shape
    extra = [
        greedy_episode.clone().update({"group": torch.full(steps, g),
                                       "greedy": torch.ones(steps, dtype=torch.bool)})
        for g in range(groups)
    ]  # fmt: skip
    return torch.cat([batch, *extra])


def _not_proportional_z(estimates: torch.Tensor, exact: torch.Tensor) -> torch.Tensor:
    """z-scores of the mean estimate against the multiple of ``exact`` closest to it:
    large when the estimator's expectation is no multiple of the policy gradient."""
    mean = estimates.mean(0)
    scale = (mean @ exact.flatten()) / exact.flatten().pow(2).sum()
    return _z_scores(estimates, scale * exact)


class TestBanditGroupGradient:
    def _estimates(self, bandit, baseline, *, greedy=False, scale=False, seed=6):
        logits, _ = bandit
        loss = _make_loss(_tabular_actor(1, N_ARMS, logits), None, RewardToGo, baseline)
        loss.group_scale = scale
        batches = _bandit_batches(logits, 500, 8 * GROUP, seed=seed)
        if greedy:
            (arm,) = logits.argmax(-1)
            (episode,) = _bandit_batches(logits, 1, 1, seed=0)
            episode["action"] = arm.reshape(1)
            episode["next", "reward"] = ARM_REWARDS[arm].reshape(1, 1)
            batches = [_with_greedy(b, episode) for b in batches]
        else:
            batches = [_with_groups(b) for b in batches]
        return _estimates(loss, batches, 8 * GROUP)

    @pytest.mark.parametrize(("baseline", "greedy"), [("leave_one_out", False), ("greedy", True)])
    def test_unbiased(self, bandit, baseline, greedy):
        estimates = self._estimates(bandit, baseline, greedy=greedy)
        assert _z_scores(estimates, bandit[1]).abs().max() <= Z_MAX

    def test_the_group_mean_shrinks_the_gradient_by_one_over_k(self, bandit):
        estimates = self._estimates(bandit, "group_mean")
        assert _z_scores(estimates, (1 - 1 / GROUP) * bandit[1]).abs().max() <= Z_MAX
        # Negative control: the check sees the 25 % shrinkage.
        assert _z_scores(estimates, bandit[1]).abs().max() > Z_MAX

    def test_scaling_by_the_group_std_bends_the_gradient(self, bandit):
        # GRPO's normalisation: no multiple of grad J. Leave-one-out on the same batches
        # is one (the control that the check does not reject every estimator).
        scaled = self._estimates(bandit, "group_mean", scale=True)
        assert _not_proportional_z(scaled, bandit[1]).abs().max() > Z_MAX
        plain = self._estimates(bandit, "leave_one_out")
        assert _not_proportional_z(plain, bandit[1]).abs().max() <= Z_MAX


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


def _gridworld_episodes(logits, n, seed, max_steps=2000):
    """``n`` episodes sampled from the tabular policy, padded to the longest:
    ``(state, action, reward, done, valid)``, each ``[n, T]``."""
    generator = torch.Generator().manual_seed(seed)
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
    return tuple(torch.stack(x, 1) for x in zip(*columns, strict=True))


def _gridworld_batches(logits, n_batches, n_episodes, seed):
    """Episodes laid back to back in flat batches, sampled from the tabular policy."""
    state, action, reward, done, valid = _gridworld_episodes(logits, n_batches * n_episodes, seed)
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


# 6 000 episodes in all, 48 per gradient estimate: the z-test's power depends on the
# total, its cost on the number of estimates (one loss call each; 375 of 16 took three
# times as long).
GRID_ESTIMATES, GRID_EPISODES = 125, 48


# Session-scoped: a test process (pytest-xdist) that is handed this module's tests in
# several chunks would otherwise tear these down between chunks and rebuild them. The
# tests that use them run in one test process (SHARED_FIXTURES in tests/conftest.py).
@pytest.fixture(scope="session")
def gridworld():
    torch.manual_seed(0)
    logits = 0.5 * torch.randn(SIDE * SIDE, len(MOVES), dtype=torch.float64)
    theta = logits.clone().requires_grad_(True)
    values = _state_values(theta)
    (exact,) = torch.autograd.grad(values[START], theta)
    batches = _gridworld_batches(logits, GRID_ESTIMATES, GRID_EPISODES, seed=1)
    return logits, exact.T.contiguous(), values.detach(), batches


def _greedy_gridworld_episode(logits, max_steps=100) -> TensorDict:
    """The tabular policy's greedy episode from the start, as a flat batch (cut after
    ``max_steps`` if the greedy policy walks in circles)."""
    eye = torch.eye(SIDE * SIDE, dtype=torch.float64)
    state, steps = START, []
    for _ in range(max_steps):
        action = int(logits[state].argmax())
        steps.append((state, action))
        state = int(NEXT_STATE[state, action])
        if TERMINAL[state]:
            break
    states, actions = (torch.tensor(x) for x in zip(*steps, strict=True))
    done = torch.zeros(len(steps), 1, dtype=torch.bool)
    done[-1] = True
    return TensorDict(
        {
            "observation": eye[states],
            "action": actions,
            "next": {
                "observation": eye[NEXT_STATE[states, actions]],
                "reward": REWARD[states, actions].unsqueeze(-1),
                "done": done,
            },
        },
        batch_size=[len(steps)],
    )


GROUP_VARIANTS = [
    (value_type, baseline)
    for value_type in (DiscountedReturn, RewardToGo)
    for baseline in ("leave_one_out", "group_mean", "greedy")
]


@pytest.fixture(scope="session")
def gridworld_group_estimates(gridworld):
    """The gridworld's batches of 16 episodes in groups of 4 (and a greedy episode
    for each group with ``"greedy"``), through each group baseline."""
    logits, _, _, batches = gridworld
    greedy = _greedy_gridworld_episode(logits)
    grouped = {
        False: [_with_groups(b.clone()) for b in batches],
        True: [_with_greedy(b.clone(), greedy) for b in batches],
    }
    out = {}
    for value_type, baseline in GROUP_VARIANTS:
        actor = _tabular_actor(SIDE * SIDE, len(MOVES), logits)
        loss = _make_loss(actor, None, value_type, baseline)
        out[value_type.__name__, baseline] = _estimates(
            loss, grouped[baseline == "greedy"], GRID_EPISODES
        )
    return out


GROUP_VARIANCE_FILE = Path(__file__).parents[1] / "results" / "gridworld-group-variance.json"
GROUP_VARIANCE_COMMAND = "tests/test_exact_gradients.py -n 0 -k lowers_the_variance"
GROUP_COLUMNS = {"none": "none", "leave_one_out": "leave-one-out", "group_mean": "group mean",
                 "greedy": "greedy episode"}  # fmt: skip


class TestGridworldGroupGradient:
    @pytest.mark.parametrize(("value_type", "baseline"), GROUP_VARIANTS)
    def test_unbiased_or_shrunk_by_one_over_k(
        self, gridworld, gridworld_group_estimates, value_type, baseline
    ):
        estimates = gridworld_group_estimates[value_type.__name__, baseline]
        shrink = 1 - 1 / GROUP if baseline == "group_mean" else 1.0
        assert _z_scores(estimates, shrink * gridworld[1]).abs().max() <= Z_MAX
        # Negative control: a target half as large or half as large again is refused.
        # (The greedy baseline resolves no less: this policy's greedy play walks in
        # circles until it is cut, so its return is a poor baseline, noisier than none.)
        for scale in (0.5, 1.5):
            assert _z_scores(estimates, scale * shrink * gridworld[1]).abs().max() > Z_MAX
        if baseline == "group_mean":  # the shrinkage is seen
            assert _z_scores(estimates, gridworld[1]).abs().max() > Z_MAX

    def test_leave_one_out_lowers_the_variance(
        self, gridworld_estimates, gridworld_group_estimates
    ):
        variance = {
            key: float(value.var(0).sum()) for key, value in gridworld_group_estimates.items()
        }
        for value_type in ROWS:
            variance[value_type, "none"] = float(
                gridworld_estimates[value_type, "none"].var(0).sum()
            )
        measured = {
            ROWS[value_type]: {name: round(variance[value_type, baseline], 4)
                               for baseline, name in GROUP_COLUMNS.items()}
            for value_type in ROWS
        }  # fmt: skip
        # The theory page's table is this file, written here when asked.
        _stored_variance(GROUP_VARIANCE_FILE, GROUP_VARIANCE_COMMAND, measured, group_size=GROUP)
        for value_type in ROWS:
            assert variance[value_type, "leave_one_out"] < variance[value_type, "none"]


# The stored table of the estimates' total variance: one row per weight, one column per
# baseline, as the pages show it.
VARIANCE_FILE = Path(__file__).parents[1] / "results" / "gridworld-gradient-variance.json"
VARIANCE_COMMAND = "tests/test_exact_gradients.py -n 0 -k lower_the_variance"
ROWS = {"DiscountedReturn": "whole-episode return R(τ)", "RewardToGo": "reward-to-go G_t"}
COLUMNS = {"none": "none", "running_mean": "running mean", "ema": "EMA", "critic": "critic"}

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


def _stored_variance(path: Path, command: str, measured: dict, **settings) -> None:
    """Checks that ``path`` holds the ``measured`` table of total variances (and the
    estimates' settings); with RL_PG_UPDATE_RESULTS=1 writes it first."""
    expected = {"estimates": GRID_ESTIMATES, "episodes_per_estimate": GRID_EPISODES, **settings}
    if os.environ.get("RL_PG_UPDATE_RESULTS"):
        stored = {"command": f"RL_PG_UPDATE_RESULTS=1 pytest {command}", **expected,
                  "total_variance": measured}  # fmt: skip
        path.write_text(json.dumps(stored, indent=1, ensure_ascii=False) + "\n")
    stored = json.loads(path.read_text())
    assert {key: stored[key] for key in expected} == expected
    assert stored["total_variance"].keys() == measured.keys()
    for row, columns in measured.items():
        assert stored["total_variance"][row] == pytest.approx(columns, rel=1e-3), (
            f"{path} no longer holds what the estimates measure: "
            f"RL_PG_UPDATE_RESULTS=1 pytest {command} writes it again."
        )


class TestGridworldGradient:
    @pytest.mark.parametrize(("value_type", "baseline"), GRIDWORLD_VARIANTS)
    def test_unbiased(self, gridworld, gridworld_estimates, value_type, baseline):
        estimates = gridworld_estimates[value_type.__name__, baseline]
        assert _z_scores(estimates, gridworld[1]).abs().max() <= Z_MAX

    @pytest.mark.parametrize(("value_type", "baseline"), GRIDWORLD_VARIANTS)
    def test_the_check_rejects_a_biased_gradient(
        self, gridworld, gridworld_estimates, value_type, baseline
    ):
        # Negative control, and the power of test_unbiased: the same check refuses a
        # target 25 % above or below the exact gradient for every reward-to-go variant,
        # but the whole-episode return's estimates (four times noisier) only resolve a
        # bias of a half: 375 estimates of 16 episodes each are too few to see less there.
        estimates = gridworld_estimates[value_type.__name__, baseline]
        bias = 0.5 if value_type is DiscountedReturn else 0.25
        for scale in (1 + bias, 1 - bias):
            assert _z_scores(estimates, scale * gridworld[1]).abs().max() > Z_MAX

    def test_any_state_only_critic_is_unbiased(self, gridworld):
        arbitrary = torch.linspace(-3, 3, SIDE * SIDE, dtype=torch.float64)
        estimates = _gridworld_estimates(gridworld, RewardToGo, "critic", arbitrary)
        assert _z_scores(estimates, gridworld[1]).abs().max() <= Z_MAX

    def test_reward_to_go_and_baselines_lower_the_variance(self, gridworld_estimates):
        variance = {key: value.var(0).sum() for key, value in gridworld_estimates.items()}
        # The table README.md and the theory page show is this file, written by this test
        # when asked (RL_PG_UPDATE_RESULTS=1); it must hold what the estimates measure.
        measured = {
            ROWS[value_type]: {COLUMNS[baseline]: round(float(variance[value_type, baseline]), 4)
                               for baseline in COLUMNS}
            for value_type in ROWS
        }  # fmt: skip
        _stored_variance(VARIANCE_FILE, VARIANCE_COMMAND, measured)
        for baseline in ("none", "running_mean", "critic"):
            assert variance["RewardToGo", baseline] < variance["DiscountedReturn", baseline]
        for value_type in ("DiscountedReturn", "RewardToGo"):
            assert variance[value_type, "critic"] < variance[value_type, "none"]
            assert variance[value_type, "running_mean"] < variance[value_type, "none"]


# ----------------------------------------------------- gradient statistics ---
# rl_pg.gradient_statistics measures, from one batch's unit gradients, the mean
# gradient and the trace of the per-episode covariance. Against exact answers: the
# bandit's covariance in closed form (a sum over arms), the gridworld's from a large
# Monte-Carlo sample computed here with plain tensor code (tabular scores, returns by
# reverse cumulative sums), independent of rl_pg. The tolerance of a trace is stated in
# standard errors of both estimates (5) and, as the target, 10 % of the reference.
REL_TRACE = 0.10


def _trace_check(measured_g: torch.Tensor, reference_trace: float, reference_se: float):
    """z of the measured trace of the covariance against the reference, and the
    relative error. The measured trace's SE is that of the mean of squared deviations."""
    from rl_pg.gradient_noise import noise_statistics

    stats = noise_statistics(measured_g)
    squared = (measured_g - stats["mean_gradient"]).pow(2).sum(-1)
    se = (squared.std() / squared.numel() ** 0.5).item()
    trace = stats["trace_covariance"].item()
    z = (trace - reference_trace) / (se**2 + reference_se**2) ** 0.5
    return z, abs(trace - reference_trace) / reference_trace


def _mean_z(measured_g: torch.Tensor, exact: torch.Tensor) -> torch.Tensor:
    se = measured_g.std(0) / measured_g.shape[0] ** 0.5
    return (measured_g.mean(0) - exact.flatten()) / se.clamp_min(1e-12)


BANDIT_CONSTANT = 0.6  # the scalar baseline of "reward_to_go_minus_mean"
BANDIT_VALUE = 0.3  # the critic's V(s) (any state-only value keeps the mean unbiased)


class TestBanditNoiseStatistics:
    def test_every_estimator_matches_the_exact_mean_and_covariance(self, bandit):
        from rl_pg.gradient_statistics import GradientStatistics

        logits, exact = bandit
        probs = logits.softmax(-1)[0]
        critic = _tabular_critic(torch.tensor([BANDIT_VALUE], dtype=torch.float64))
        loss = _make_loss(_tabular_actor(1, N_ARMS, logits), critic, RewardToGo, "critic")
        stats = GradientStatistics(loss, scalar_baseline=BANDIT_CONSTANT)
        batches = _bandit_batches(logits, 60, 100, seed=4)
        parts = [stats.unit_gradients(b, stats.weights(b)) for b in batches]
        gradients = {name: torch.cat([p[name] for p in parts]) for name in parts[0]}
        # One-step episodes: Psi = r(a) - b with b per estimator; g(a) = Psi (e_a - pi).
        baselines = {
            "loss": BANDIT_VALUE,
            "episode_return": 0.0,
            "reward_to_go": 0.0,
            "reward_to_go_minus_mean": BANDIT_CONSTANT,
            "reward_to_go_minus_value": BANDIT_VALUE,
            "gae": BANDIT_VALUE,
        }
        assert set(gradients) == set(baselines)
        eye = torch.eye(N_ARMS, dtype=torch.float64)
        for name, b in baselines.items():
            per_arm = (ARM_REWARDS - b).unsqueeze(-1) * (eye - probs)  # g for each arm
            second_moment = (probs * per_arm.pow(2).sum(-1)).sum()
            exact_trace = (second_moment - exact.pow(2).sum()).item()
            assert _mean_z(gradients[name], exact).abs().max() <= Z_MAX, name
            z, relative = _trace_check(gradients[name], exact_trace, 0.0)
            assert abs(z) <= Z_MAX and relative <= REL_TRACE, (name, z, relative)

    def test_the_check_rejects_a_wrong_covariance(self, bandit):
        # Negative control: the same check refuses a trace 25 % off the exact one.
        from rl_pg.gradient_statistics import GradientStatistics

        logits, exact = bandit
        probs = logits.softmax(-1)[0]
        loss = _make_loss(_tabular_actor(1, N_ARMS, logits), None, RewardToGo, "none")
        stats = GradientStatistics(loss, estimators=["reward_to_go"])
        (batch,) = _bandit_batches(logits, 1, 6000, seed=5)
        (gradients,) = stats.unit_gradients(batch, stats.weights(batch)).values()
        per_arm = ARM_REWARDS.unsqueeze(-1) * (torch.eye(N_ARMS, dtype=torch.float64) - probs)
        trace = ((probs * per_arm.pow(2).sum(-1)).sum() - exact.pow(2).sum()).item()
        z, _ = _trace_check(gradients, 1.25 * trace, 0.0)
        assert abs(z) > Z_MAX


GRID_CONSTANT = -1.0  # the scalar baseline of "reward_to_go_minus_mean"
GRID_LAMBDA = 0.8


def _reference_unit_gradients(logits, values, episodes) -> dict[str, torch.Tensor]:
    """Per-episode gradients of every estimator, by plain tensor code: tabular scores
    ``onehot(s) x (e_a - pi(s))`` weighted by returns from reverse cumulative sums."""
    state, action, reward, done, valid = episodes
    probs = logits.softmax(-1)
    reward = reward * valid
    to_go = reward.flip(-1).cumsum(-1).flip(-1)
    next_value = values[NEXT_STATE[state, action]] * ~done
    delta = (reward + next_value - values[state]) * valid
    gae = torch.zeros_like(delta)
    running = torch.zeros(delta.shape[0], dtype=delta.dtype)
    for t in reversed(range(delta.shape[1])):
        running = delta[:, t] + GRID_LAMBDA * running * ~done[:, t]
        gae[:, t] = running
    psi = {
        "loss": to_go - values[state],
        "episode_return": reward.sum(-1, keepdim=True).expand_as(reward),
        "reward_to_go": to_go,
        "reward_to_go_minus_mean": to_go - GRID_CONSTANT,
        "reward_to_go_minus_value": to_go - values[state],
        "gae": gae,
    }
    score = torch.nn.functional.one_hot(action, len(MOVES)).double() - probs[state]
    out = {}
    for name, weight in psi.items():
        coef = (weight * valid).unsqueeze(-1) * score  # [n, T, actions]
        g = torch.zeros(state.shape[0], SIDE * SIDE, len(MOVES), dtype=torch.float64)
        g.scatter_add_(1, state.unsqueeze(-1).expand_as(coef), coef)
        out[name] = g.transpose(1, 2).flatten(1)  # the actor's weight is [actions, states]
    return out


@pytest.fixture(scope="session")
def gridworld_reference(gridworld):
    """Each estimator's exact-mean per-episode covariance trace, from 30 000 episodes
    (in chunks), with its standard error (about 2 % of R(tau)'s trace, the most
    heavy-tailed)."""
    logits, exact, values, _ = gridworld
    squared = {}
    for chunk in range(3):
        episodes = _gridworld_episodes(logits, 10_000, seed=100 + chunk)
        for name, g in _reference_unit_gradients(logits, values, episodes).items():
            squared.setdefault(name, []).append((g - exact.flatten()).pow(2).sum(-1))
    return {
        name: (torch.cat(s).mean().item(), (torch.cat(s).std() / len(torch.cat(s)) ** 0.5).item())
        for name, s in squared.items()
    }


def _measured_unit_gradients(logits, values, batches) -> dict[str, torch.Tensor]:
    from rl_pg.gradient_statistics import GradientStatistics

    actor = _tabular_actor(SIDE * SIDE, len(MOVES), logits)
    loss = _make_loss(actor, _tabular_critic(values), RewardToGo, "critic")
    stats = GradientStatistics(loss, scalar_baseline=GRID_CONSTANT, gae_lambda=GRID_LAMBDA)
    parts = [stats.unit_gradients(b, stats.weights(b)) for b in batches]
    return {name: torch.cat([p[name] for p in parts]) for name in parts[0]}


class TestGridworldNoiseStatistics:
    @pytest.fixture(scope="class")
    @classmethod
    def measured(cls, gridworld):
        # 24 000 episodes: the trace of R(tau)'s covariance, the most heavy-tailed,
        # then has a standard error of about 2.5 %, a quarter of the 10 % target. Every
        # weight measured here is the episode's own (no batch statistics), so 24 batches
        # of 1 000 give the gradients 1 500 batches of 16 would, in one call each.
        logits, _, values, _ = gridworld
        return _measured_unit_gradients(logits, values, _gridworld_batches(logits, 24, 1000, 11))

    def test_reference_matches_the_exact_gradient(self, gridworld):
        # The independent reference itself is unbiased (a check of the checker).
        logits, exact, values, _ = gridworld
        episodes = _gridworld_episodes(logits, 6000, seed=7)
        for name, g in _reference_unit_gradients(logits, values, episodes).items():
            assert _mean_z(g, exact).abs().max() <= Z_MAX, name

    def test_mean_gradient_matches_the_exact_gradient(self, gridworld, measured):
        for name, g in measured.items():
            assert _mean_z(g, gridworld[1]).abs().max() <= Z_MAX, name

    def test_unit_gradients_equal_the_reference_on_the_same_episodes(self, gridworld):
        # Same episodes, two computations: rl_pg's batched backward and plain code.
        # TorchRL's GAE keeps gamma and lambda in float32, hence its looser tolerance.
        logits, _, values, batches = gridworld
        measured = _measured_unit_gradients(logits, values, batches[:20])
        episodes = _gridworld_episodes(logits, GRID_ESTIMATES * GRID_EPISODES, seed=1)
        episodes = tuple(x[: 20 * GRID_EPISODES] for x in episodes)
        for name, g in _reference_unit_gradients(logits, values, episodes).items():
            tol = 1e-6 if name == "gae" else 1e-9
            torch.testing.assert_close(measured[name], g, rtol=tol, atol=tol)

    def test_trace_of_the_covariance_matches_the_reference(self, measured, gridworld_reference):
        for name, g in measured.items():
            z, relative = _trace_check(g, *gridworld_reference[name])
            print(f"{name:26s} trace z {z:+.2f}, relative error {relative:.3f}")
            assert abs(z) <= Z_MAX and relative <= REL_TRACE, (name, z, relative)

    def test_the_trace_check_rejects_a_wrong_reference(self, measured, gridworld_reference):
        # Negative control: a reference 25 % off is refused for every estimator.
        for name, g in measured.items():
            trace, se = gridworld_reference[name]
            z, _ = _trace_check(g, 1.25 * trace, se)
            assert abs(z) > Z_MAX, name


# ------------------------------------------------- episodes from a collector ---
def _collected(logits, batches_of, n_batches, n_episodes, exact):
    """REINFORCE (whole-episode return, no baseline) on ``n_batches`` batches of
    ``n_episodes`` episodes that ``batches_of(env, actor)`` collects from as many
    gridworlds stepped as one batch: the z-scores of the mean estimate, and the batches'
    mean episode length."""
    from rl_pg.envs import GridWorldEnv

    cells = {"start": START, "goal": GOAL, "pit": PIT}
    env = GridWorldEnv(batch_size=n_episodes, max_steps=100_000,
                       **{name: divmod(cell, SIDE) for name, cell in cells.items()})  # fmt: skip
    assert torch.equal(env.next_cell, NEXT_STATE)  # the grid of the exact gradient
    actor = _tabular_actor(SIDE * SIDE, len(MOVES), logits).float()
    loss = _make_loss(actor, None, DiscountedReturn, "none")
    batches = batches_of(env, actor)
    weight = loss.actor_network_params["module", "0", "module", "weight"]
    estimates, steps = [], 0
    for _, batch in zip(range(n_batches), batches, strict=False):
        assert int(batch["next", "done"].sum()) == n_episodes  # complete episodes only
        (grad,) = torch.autograd.grad(loss(batch)["loss_actor"], weight)
        estimates.append(-grad.flatten().double() / n_episodes)
        steps += batch.numel()
    batches.shutdown()
    z, length = _z_scores(torch.stack(estimates), exact), steps / (n_batches * n_episodes)
    print(f"mean episode length {length:.1f}, max |z| {z.abs().max():.1f}")
    return z, length


class _FirstToEnd:
    """TorchRL's trajs_per_batch: the first episodes to end, the environments reset
    after every batch as a training loop would (else a batch also holds episodes that
    the previous policy began)."""

    def __init__(self, env, actor, episodes):
        from torchrl.collectors import Collector

        self.collector = Collector(env, actor, frames_per_batch=episodes * 4, total_frames=-1,
                                   trajs_per_batch=episodes, traj_format="cat",
                                   auto_register_policy_transforms=False)  # fmt: skip

    def __iter__(self):
        for batch in self.collector:
            yield batch
            self.collector.reset()

    def shutdown(self):
        self.collector.shutdown()


class TestCollectedEpisodes:
    """Whole-episode batches from a collector of 64 gridworlds, against the exact
    gradient and the policy's mean episode length."""

    EPISODES = 64  # one from each gridworld

    @pytest.fixture(scope="class")
    @classmethod
    def grid(cls, gridworld):
        logits = gridworld[0].float().double()  # what the float32 policy holds
        theta = logits.clone().requires_grad_(True)
        (exact,) = torch.autograd.grad(_state_values(theta)[START], theta)
        batches = gridworld[3]  # 6 000 independent episodes of the same policy
        mean_length = sum(batch.numel() for batch in batches) / (len(batches) * GRID_EPISODES)
        return logits, exact.T.contiguous(), mean_length

    def test_episode_collector_batches_give_the_exact_gradient(self, grid):
        from rl_pg.collectors import SegmentCollector
        from rl_pg.episode_collector import EpisodeCollector
        from rl_pg.lean import lean_policy

        def batches_of(env, actor):
            segments = SegmentCollector(env, lean_policy(actor), frames_per_batch=64 * 4)
            return EpisodeCollector(segments, episodes=self.EPISODES)

        logits, exact, mean_length = grid
        torch.manual_seed(1)
        z, length = _collected(logits, batches_of, 25, self.EPISODES, exact)
        assert z.abs().max() <= Z_MAX and length == pytest.approx(mean_length, rel=0.1)

    def test_the_first_episodes_to_end_are_short_and_give_another_gradient(self, grid):
        # Negative control, and why EpisodeCollector exists.
        logits, exact, mean_length = grid
        torch.manual_seed(1)
        first = lambda env, actor: _FirstToEnd(env, actor, self.EPISODES)  # noqa: E731
        z, length = _collected(logits, first, 8, self.EPISODES, exact)
        assert z.abs().max() > Z_MAX and length < 0.8 * mean_length


# ------------------------------------------------------------ natural gradient ---
# On both problems the Fisher of the policy is known exactly: the bandit's is that of
# one softmax, F = diag(p) - p p^T; the gridworld's is each state's, weighted by the
# state's expected visits per episode, the Hessian of the visit-weighted KL. The
# natural gradient is then F^+ grad J (F is singular: the logits of a state can all
# shift together), and NaturalGradient.direction, from one large batch, must point
# the same way. The plain gradient is the negative control: it does not. K-FAC's
# Kronecker-factored Fisher is exact on the bandit, an approximation on the gridworld.
COS_MIN = 0.99


def _cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(a @ b / (a.norm() * b.norm()))


def _gridworld_fisher(logits: torch.Tensor) -> torch.Tensor:
    """The Fisher of the episode's distribution over the actor's weight [actions, states]."""
    n = SIDE * SIDE
    probs = logits.softmax(-1)
    transition = torch.zeros(n, n, dtype=torch.float64)
    transition = transition.index_put((torch.arange(n).unsqueeze(-1), NEXT_STATE), probs, True)
    transition[:, TERMINAL] = 0.0
    transition[TERMINAL] = 0.0
    eye = torch.eye(n, dtype=torch.float64)
    visits = torch.linalg.solve((eye - transition).T, eye[START])  # expected, per episode

    def kl(weight):
        log_new = torch.log_softmax(weight.T, -1)
        return (visits.unsqueeze(-1) * probs * (probs.log() - log_new)).sum()

    size = n * len(MOVES)
    return torch.autograd.functional.hessian(kl, logits.T.contiguous()).reshape(size, size)


def _gridworld_natural(gridworld):
    """The gridworld's exact natural gradient F+ grad J, a loss with the oracle critic,
    and its 6 000 episodes as sampled (other tests of the session write returns into
    them, so a copy of the sampled entries only)."""
    logits, exact, values, batches = gridworld
    natural = torch.linalg.pinv(_gridworld_fisher(logits), hermitian=True) @ exact.flatten()
    actor = _tabular_actor(SIDE * SIDE, len(MOVES), logits)
    loss = _make_loss(actor, _tabular_critic(values), RewardToGo, "critic")
    loss.reduction = "mean"
    keys = ("observation", "action", ("next", "observation"), ("next", "reward"),
            ("next", "done"))  # fmt: skip
    return natural, loss, torch.cat([b.select(*keys).clone() for b in batches])


class TestNaturalGradientDirection:
    def test_bandit(self, bandit):
        from rl_pg.natural_gradient import NaturalGradient

        logits, exact = bandit
        probs = logits.softmax(-1)[0]
        fisher = torch.diag(probs) - torch.outer(probs, probs)
        natural = torch.linalg.pinv(fisher, hermitian=True) @ exact.flatten()
        loss = _make_loss(_tabular_actor(1, N_ARMS, logits), None, RewardToGo, "none")
        loss.reduction = "mean"
        (batch,) = _bandit_batches(logits, 1, 20_000, seed=9)
        direction, gradient = NaturalGradient(loss, damping=1e-6, cg_iters=50).direction(batch)
        assert _cosine(direction, natural) >= COS_MIN
        assert _cosine(gradient, natural) < 0.9  # the plain gradient points elsewhere

    def test_bandit_kfac(self, bandit):
        # One layer on one input (the bandit's single state): the Kronecker factors are
        # the Fisher itself, A = 1 and G = diag(p) - p p^T, estimated from actions
        # sampled from the policy.
        from rl_pg.natural_gradient import NaturalGradient

        logits, exact = bandit
        probs = logits.softmax(-1)[0]
        fisher = torch.diag(probs) - torch.outer(probs, probs)
        natural = torch.linalg.pinv(fisher, hermitian=True) @ exact.flatten()
        loss = _make_loss(_tabular_actor(1, N_ARMS, logits), None, RewardToGo, "none")
        loss.reduction = "mean"
        (batch,) = _bandit_batches(logits, 1, 20_000, seed=9)
        torch.manual_seed(3)
        update = NaturalGradient(loss, damping=1e-6, fisher="kfac")
        direction, gradient = update.direction(batch)
        assert _cosine(direction, natural) >= COS_MIN
        assert _cosine(gradient, natural) < 0.9

    def test_gridworld_kfac_is_an_approximation(self, gridworld):
        # One-hot states: the exact Fisher has a block per state, K-FAC one G shared by
        # all states (weighted by their visits). Its direction lies between the plain
        # gradient and the natural one, nearer the latter.
        from rl_pg.natural_gradient import NaturalGradient

        natural, loss, batch = _gridworld_natural(gridworld)
        torch.manual_seed(3)
        direction, gradient = NaturalGradient(loss, damping=1e-6, fisher="kfac").direction(batch)
        # Measured: 0.96 against the plain gradient's 0.86.
        assert _cosine(gradient, natural) + 0.05 < _cosine(direction, natural) < COS_MIN

    def test_gridworld(self, gridworld):
        from rl_pg.natural_gradient import NaturalGradient

        natural, loss, batch = _gridworld_natural(gridworld)
        update = NaturalGradient(loss, damping=1e-6, cg_iters=200)
        direction, gradient = update.direction(batch)
        assert _cosine(direction, natural) >= COS_MIN
        assert _cosine(gradient, natural) < 0.9
