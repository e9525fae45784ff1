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
# # 3. Reward-to-go and a learned baseline on a gridworld
#
# A 4×4 grid (`rl_pg.envs.GridWorldEnv`): the agent starts bottom-left, the goal
# top-right pays +1, a pit pays −1, every other step costs 0.1, and episodes end at the
# goal, the pit or after 100 steps. With states, an action can only change the rewards
# that follow it, so each $\log \pi(a_t \mid s_t)$ can be weighted by the reward-to-go
# $G_t = \sum_{k \ge t} r_k$ instead of the whole return $R(\tau)$, and the expected return
# from the state, $V(s_t)$, can be subtracted. Neither changes the expected gradient;
# both remove noise. We measure how much on one batch, then train with each.

# %%
import matplotlib.pyplot as plt
import torch
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rl_pg import ReinforceLoss
from rl_pg.envs import GridWorldEnv
from rl_pg.episode_collector import EpisodeCollector
from rl_pg.gradient_statistics import GradientStatistics
from rl_pg.models import mlp_actor_critic

torch.set_num_threads(1)  # these small networks run fastest on one thread

EPISODES = 30  # episodes per update, played side by side
env = GridWorldEnv(batch_size=EPISODES)
print("best return:", round(env.optimal_return, 3), "(6 moves: 5 steps at -0.1, then the goal)")


def episodes(actor, grids: GridWorldEnv = env):
    """One complete episode from each grid of the batch, actions sampled."""
    with set_exploration_type(ExplorationType.RANDOM):
        return grids.rollout(100, actor, break_when_all_done=True)


# %% [markdown]
# ## Four weights on the same episodes
#
# `GradientStatistics` computes one gradient per episode for each weight $\Psi_t$ at the
# same parameters, and the trace of their covariance $\mathrm{tr}\,\Sigma$ (the noise one
# episode adds to the batch's mean gradient). The critic is fitted first on other
# episodes of the same policy, so that $V(s)$ is a fair baseline.

# %%
torch.manual_seed(0)
actor, critic = mlp_actor_critic(env, hidden=(32,))
loss = ReinforceLoss(actor, critic)
loss.make_value_estimator("reward_to_go", gamma=1.0)
optimizer = torch.optim.Adam(critic.parameters(), lr=0.02)
fit = episodes(actor, GridWorldEnv(batch_size=500))  # V is fitted on other episodes
loss(fit)  # writes the value targets into the batch
for _ in range(200):  # only the critic moves
    optimizer.zero_grad()
    loss.value_loss(fit).backward()
    optimizer.step()

batch = episodes(actor, GridWorldEnv(batch_size=500))
stats = GradientStatistics(loss)(batch)
reference = stats["episode_return", "trace_covariance"].item()
print(f"{'weight Ψ_t':28s} {'tr Σ':>8s} {'vs R(τ)':>8s}")
for name, label in [
    ("episode_return", "R(τ)"),
    ("reward_to_go", "G_t"),
    ("reward_to_go_minus_mean", "G_t - mean return"),
    ("reward_to_go_minus_value", "G_t - V(s_t)"),
]:
    trace = stats[name, "trace_covariance"].item()
    print(f"{label:28s} {trace:8.3f} {trace / reference:8.2f}")

# %% [markdown]
# Each step down the table keeps the same expected gradient with less noise per
# episode: reward-to-go drops the rewards an action could not have changed, and the
# baselines centre the weight on "better or worse than usual".
#
# ## Training with each
#
# The noisiest weight against the quietest: 30 updates of 30 episodes, Adam at 0.02,
# three seeds each (the settings of `rl-pg train gridworld --compare`, which runs all
# four on five seeds). A TorchRL `Collector` steps the 30 grids in segments;
# `rl_pg.episode_collector.EpisodeCollector` makes batches of exactly 30 complete episodes out
# of them, one per grid, and restarts the grids after each batch, so that every episode
# is played by the policy being updated. (Taking the first 30 episodes to end, as
# `Collector(trajs_per_batch=30)` does, would favour short episodes: a grid whose
# episode ends fast plays a second one before a slow grid ends its first, and the
# gradient is no longer the policy's.) We follow the mean return of each batch's 30
# sampled episodes, what the policy earns while it learns.

# %%
VARIANTS = {  # (returns, baseline)
    "R(τ), no baseline": ("discounted_return", "none"),
    "G_t - learned V": ("reward_to_go", "critic"),
}
UPDATES, SEEDS = 30, range(3)
returns, greedy = {}, {}
for name, (estimator, baseline) in VARIANTS.items():
    for seed in SEEDS:
        torch.manual_seed(seed)
        actor, critic = mlp_actor_critic(env, hidden=(32,))
        if baseline == "critic":
            loss = ReinforceLoss(actor, critic)
        else:
            loss = ReinforceLoss(actor, baseline=baseline)
        loss.make_value_estimator(estimator, gamma=1.0)
        optimizer = torch.optim.Adam(loss.parameters(), lr=0.02)
        segments = Collector(
            env,
            actor,
            frames_per_batch=10 * EPISODES,  # how often it checks for finished episodes
            total_frames=-1,
            auto_register_policy_transforms=False,  # the policy needs no env transform
        )
        collector = EpisodeCollector(segments, episodes=EPISODES)
        curve = []
        for _, batch in zip(range(UPDATES), collector, strict=False):  # the collector is endless
            out = loss(batch)
            optimizer.zero_grad()
            (out["loss_actor"] + out.get("loss_value", 0.0)).backward()
            optimizer.step()
            curve.append(batch["next", "reward"].sum().item() / EPISODES)
        collector.shutdown()
        returns[name, seed] = curve
        with torch.no_grad():  # a rollout outside set_exploration_type plays the mode
            walk = GridWorldEnv().rollout(100, actor)  # deterministic: one episode tells
        greedy[name, seed] = walk["next", "reward"].sum().item()

fig, axes = plt.subplots(1, len(VARIANTS), figsize=(8, 3), sharey=True)
for ax, name in zip(axes, VARIANTS, strict=True):
    for seed in SEEDS:
        ax.plot(range(1, UPDATES + 1), returns[name, seed], lw=1)
    ax.axhline(env.optimal_return, color="k", ls=":", lw=1)
    ax.set_title(name, fontsize=10)
    ax.set_xlabel("update")
axes[0].set_ylabel("mean return of the batch")
fig.tight_layout()

# %%
for name in VARIANTS:
    early = sum(sum(returns[name, seed][5:15]) / 10 for seed in SEEDS) / len(SEEDS)
    best = sum(abs(greedy[name, seed] - env.optimal_return) < 1e-6 for seed in SEEDS)
    print(
        f"{name:22s} mean batch return, updates 6-15: {early:+.2f}; "
        f"greedy shortest path after {UPDATES} updates: {best} of {len(SEEDS)} seeds"
    )

# %% [markdown]
# Both weights have the same expected gradient, and with batches of independent
# episodes both end on the shortest path here. The one with a fifth of the noise per
# episode climbs sooner: its batches earn more from the first updates on. The
# [Gridworld](../recipes/gridworld.md) page compares all four
# weights on five seeds each; `tests/test_exact_gradients.py` checks every one of these
# estimators against the exact gradient of this grid.
