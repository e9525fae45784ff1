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
# # 5. Driving with a table of nine actions, and with continuous ones
#
# MetaDrive drives a car with a continuous action, $[\text{steering}, \text{throttle}]$ in
# $[-1, 1]^2$. The driving tutorial this project grew from gave its policy a table
# instead: nine fixed actions (three throttles × three steerings), and a softmax over
# them. The policy gradient is the same either way,
# $\Psi_t \nabla \log \pi_\theta(a_t \mid s_t)$; only the distribution $\pi$ changes: a
# categorical over table rows, or a density over the square. rl_pg gives both on the
# same environment: `DiscretizeAction`, a TorchRL transform, turns the continuous action
# into a choice of row, and `mlp_actor(..., bounded="beta")` puts a Beta policy on the
# bounds. MetaDrive runs headless here, on state observations, without its 3-D assets.

# %%
import matplotlib.pyplot as plt
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rl_pg import ReinforceLoss
from rl_pg.envs.metadrive import driving_actions, metadrive_env
from rl_pg.gradient_statistics import GradientStatistics
from rl_pg.models import mlp_actor

torch.set_num_threads(1)  # these small networks run fastest on one thread
_ = torch.manual_seed(0)

# %% [markdown]
# ## The table
#
# The tutorial wrote its table as (throttle, steering) pairs and handed each pair to
# MetaDrive as it was, but MetaDrive reads $[\text{steering}, \text{throttle}]$: its agent
# steered with ±1 and throttled with ±0.6. `driving_actions("tutorial")` keeps that
# table (the recipe's default, which the driving results were measured with);
# `"swapped"` applies the table as written.

# %%
fig, axes = plt.subplots(1, 2, figsize=(7, 3.2), sharey=True)
for ax, order in zip(axes, ("tutorial", "swapped"), strict=True):
    table = torch.tensor(driving_actions(order))
    ax.scatter(table[:, 0], table[:, 1])
    for index, (steering, throttle) in enumerate(table.tolist()):
        ax.annotate(str(index), (steering, throttle), xytext=(4, 4), textcoords="offset points")
    ax.set(title=f'driving_actions("{order}")', xlabel="steering", xlim=(-1.3, 1.3))
axes[0].set(ylabel="throttle (< 0 brakes)", ylim=(-1.3, 1.3))
fig.tight_layout()

# %% [markdown]
# ## A categorical policy over the table
#
# `metadrive_env(actions="tutorial")` is MetaDrive's validation scenarios as a TorchRL
# environment, with `DiscretizeAction` appended: the policy outputs a row index, the
# transform hands MetaDrive the row. `mlp_actor` sizes a softmax policy from the specs.
# We play four episodes with a fresh policy, sampling its actions, and read what
# MetaDrive reports about each (route completion, how it ended).

# %%
env = metadrive_env("MetaDrive-validation-v0", actions="tutorial")
print(
    "observation:", env.observation_spec["observation"].shape, " actions:", env.action_spec.space.n
)
policy = mlp_actor(env, hidden=(128,))
with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
    episodes = [env.rollout(1000, policy) for _ in range(4)]
for episode in episodes:
    last = episode[-1]["next"]
    ended = [flag for flag in ("arrive_dest", "crash", "out_of_road", "max_step") if last[flag]]
    completion = last["route_completion"].item()
    print(f"{len(episode):4d} steps, route completion {completion:.2f}, ended by {ended}")

# %% [markdown]
# A random driver goes nowhere: it covers a few percent of its route before it leaves
# the road or runs out of steps. How noisy is the gradient it would learn from? One
# episode is one unit of `GradientStatistics`; with $\gamma = 0.99$, reward-to-go
# against whole-episode returns:

# %%
loss = ReinforceLoss(policy, baseline="none")
loss.make_value_estimator("reward_to_go", gamma=0.99)
batch = torch.cat(episodes)  # one time axis; the done flags separate the episodes
stats = GradientStatistics(loss, estimators=["episode_return", "reward_to_go"])(batch)
for name in ("episode_return", "reward_to_go"):
    print(f"{name:15s} tr Σ per episode {stats[name, 'trace_covariance'].item():10.1f}")
env.close()

# %% [markdown]
# ## A Beta policy on the continuous action
#
# `actions=None` keeps MetaDrive's own action. A Gaussian's samples fall outside
# $[-1, 1]$ and the environment clips them; a policy whose mean drifts past a bound then
# sees only the bound (the MetaDrive page shows this happening to the throttle). A Beta
# distribution, scaled to the bounds, puts all its mass inside them:

# %%
env = metadrive_env("MetaDrive-validation-v0", actions=None)
beta_policy = mlp_actor(env, hidden=(128,), bounded="beta")
with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
    episode = env.rollout(200, beta_policy)
actions = episode["action"]
print("action shape:", tuple(actions.shape), " inside [-1, 1]:", bool(actions.abs().le(1).all()))
env.close()

fig, ax = plt.subplots(figsize=(4, 3.2))
ax.scatter(actions[:, 0], actions[:, 1], s=6)
ax.set(
    xlabel="steering",
    ylabel="throttle",
    xlim=(-1.05, 1.05),
    ylim=(-1.05, 1.05),
    title="a fresh Beta policy's actions",
)
fig.tight_layout()

# %% [markdown]
# ## Trained for real
#
# `rl-pg train metadrive` trains the nine-action table with reward-to-go minus a learned
# $V(s)$ for 2M steps and scores the deployed agent on 100 scenarios it never saw;
# `--actions continuous --bounded beta` trains the Beta policy instead. Both, with what
# they reach and why the table is the default, are on the
# [MetaDrive](../recipes/metadrive.md) page.
