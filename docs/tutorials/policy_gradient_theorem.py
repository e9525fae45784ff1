# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 1. The policy-gradient theorem, checked
#
# The policy-gradient theorem says that the gradient of the expected return is an
# expectation we can sample:
#
# $$
# \nabla J(\theta) = \mathbb{E}_{a \sim \pi_\theta}\left[ r(a)\, \nabla \log \pi_\theta(a) \right]
# $$
#
# (the [theory page](../theory.md#the-log-derivative-trick) derives it). This notebook
# does not take it on trust: on a bandit, $J(\theta)$ has a closed form, so autograd gives
# the exact gradient, and we compare it with what `rl_pg.ReinforceLoss` estimates from
# sampled pulls. You will see the estimate converge to the exact gradient, its error
# shrink like $1/\sqrt{N}$ in the number of samples, and a baseline cut that error
# without moving the mean.

# %%
import matplotlib.pyplot as plt
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor

from rl_pg import ReinforceLoss
from rl_pg.envs import BanditEnv

torch.set_num_threads(1)  # these small networks run fastest on one thread
_ = torch.manual_seed(0)

# %% [markdown]
# ## A bandit whose J we can write down
#
# `BanditEnv(num_arms=10)` is a one-step game: arm 0 pays 1.0, arms 1–4 pay 0.9, arms 5–9
# pay 0. Its state is a constant, so a softmax policy is a vector of 10 logits $\theta$: a
# linear layer without bias on the constant input. With the rewards $r$ known,
#
# $$
# J(\theta) = \sum_a \mathrm{softmax}(\theta)_a \, r_a
# $$

# %%
N_ARMS = 10
arm_rewards = BanditEnv(num_arms=N_ARMS).arm_rewards
print("arm rewards:", [round(r, 2) for r in arm_rewards.tolist()])

linear = nn.Linear(1, N_ARMS, bias=False)
with torch.no_grad():
    linear.weight.copy_(torch.randn(N_ARMS, 1))  # some policy, not the optimum
actor = ProbabilisticActor(
    TensorDictModule(linear, ["observation"], ["logits"]),
    in_keys=["logits"],
    distribution_class=torch.distributions.Categorical,
    default_interaction_type=ExplorationType.RANDOM,  # rollouts sample (default: the mode)
)
theta = linear.weight


def exact_gradient() -> torch.Tensor:
    """dJ/dθ from the closed form, by autograd."""
    probs = theta.squeeze(-1).softmax(-1)
    (grad,) = torch.autograd.grad((probs * arm_rewards).sum(), theta)
    return grad.squeeze(-1)


exact = exact_gradient()
with torch.no_grad():
    print("J(θ) =", round(float((theta.squeeze(-1).softmax(-1) * arm_rewards).sum()), 4))
print("exact ∇J:", [round(g, 4) for g in exact.tolist()])

# %% [markdown]
# ## The same gradient from samples
#
# A batch of $N$ bandits stepped once is a batch of $N$ one-step episodes. `ReinforceLoss`
# builds the surrogate $-\frac{1}{N}\sum_i r_i \log \pi_\theta(a_i)$, whose gradient is the
# negative of the score-function estimate of $\nabla J$. No model of the bandit is used:
# only the actions taken, their rewards and the policy's log-probabilities.


# %%
def estimate(loss: ReinforceLoss, n: int) -> torch.Tensor:
    """One estimate of ∇J from n sampled pulls."""
    batch = BanditEnv(num_arms=N_ARMS, batch_size=n).rollout(1, actor)
    (grad,) = torch.autograd.grad(loss(batch)["loss_actor"], theta)
    return -grad.squeeze(-1)


plain = ReinforceLoss(actor, baseline="none")
plain.make_value_estimator("reward_to_go", gamma=1.0)

estimates = torch.stack([estimate(plain, 1024) for _ in range(200)])
mean, se = estimates.mean(0), estimates.std(0) / len(estimates) ** 0.5
print("mean of 200 estimates:", [round(g, 4) for g in mean.tolist()])
print("largest |z| = |mean - exact| / SE:", round(float(((mean - exact) / se).abs().max()), 2))

# %% [markdown]
# Every component of the averaged estimate lies within a few standard errors of the
# exact gradient: the estimator is unbiased. (`tests/test_exact_gradients.py` checks the
# same on this bandit and on a gridworld, for every return estimator and baseline.)
#
# ## Noise, and what a baseline does to it
#
# One estimate is noisy. Its error shrinks like $1/\sqrt{N}$, and subtracting a baseline
# $b$ from the reward, $(r_i - b)\nabla\log\pi_\theta(a_i)$, leaves the mean where it is
# (the expectation of $\nabla \log \pi$ is zero) while it removes most of the noise when
# $b$ is close to the typical reward. `baseline="running_mean"` subtracts the mean of the
# rewards of *earlier* batches, so it never uses the sample it is subtracted from.

# %%
with_baseline = ReinforceLoss(actor, baseline="running_mean")
with_baseline.make_value_estimator("reward_to_go", gamma=1.0)
for _ in range(10):  # let the running mean see a few batches first
    estimate(with_baseline, 256)

sizes = [16, 64, 256, 1024, 4096]
errors = {"no baseline": [], "running-mean baseline": []}
for n in sizes:
    for name, loss in (("no baseline", plain), ("running-mean baseline", with_baseline)):
        draws = torch.stack([estimate(loss, n) for _ in range(50)])
        errors[name].append(float((draws - exact).norm(dim=-1).pow(2).mean().sqrt()))

fig, ax = plt.subplots(figsize=(5.5, 3.5))
for name, values in errors.items():
    ax.loglog(sizes, values, "o-", label=name)
ref = errors["no baseline"][0] * (sizes[0] / torch.tensor(sizes, dtype=torch.float)) ** 0.5
ax.loglog(sizes, ref, "k:", label=r"$\propto 1/\sqrt{N}$")
ax.set_xlabel("pulls per estimate N")
ax.set_ylabel("RMS error of the estimate")
ax.legend()
fig.tight_layout()

# %%
for name, values in errors.items():
    print(f"{name:22s}", "  ".join(f"N={n}: {e:.4f}" for n, e in zip(sizes, values, strict=True)))
ratios = [a / b for a, b in zip(*errors.values(), strict=True)]
print("error without / with the baseline:", "  ".join(f"{r:.1f}" for r in ratios))

# %% [markdown]
# ## What to take away
#
# - `ReinforceLoss` estimates the exact $\nabla J$ without knowing the environment.
# - The estimate is noisy; the noise falls like $1/\sqrt{N}$ in the batch, and a baseline
#   cuts it at no cost in bias. The next notebooks measure that noise on tasks with
#   states: [baselines on the 100-armed bandit](bandit_baselines.py), then
#   [reward-to-go on a gridworld](reward_to_go.py).
