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
# # 7. Four episodes from one start: a baseline for free
#
# A baseline answers one question for each step: *how well does this policy usually do
# from here?* A critic learns the answer, slowly, and is wrong while it learns. There
# is a cheaper way when the environment can be replayed from a seed: play K episodes
# from the same start. Given the start, the other K − 1 episodes know nothing of this
# one's actions, so their mean return is an unbiased answer to the question, with no
# network to fit (the [theory page](../theory.md#group-baselines) has the argument;
# Kool et al. 2019 called it a baseline "for free").
#
# This notebook trains CartPole that way, measures the group's baseline beside a
# single number on the very same batches, and then asks what the shared start itself
# is worth, on CartPole and on LunarLander.

# %%
import matplotlib.pyplot as plt
import torch
from torchrl.collectors import Collector

from rl_pg import ReinforceLoss
from rl_pg.envs import gym_env
from rl_pg.episode_collector import EpisodeCollector
from rl_pg.gradient_statistics import GradientStatistics
from rl_pg.groups import batch_group_advantage
from rl_pg.models import mlp_actor

torch.set_num_threads(1)  # these small networks run fastest on one thread
_ = torch.manual_seed(0)

K, GROUPS = 4, 8  # 8 groups of 4 episodes: 32 CartPoles, one episode each per batch
envs = gym_env("CartPole-v1", num_envs=K * GROUPS)
actor = mlp_actor(envs, hidden=(32,))
segments = Collector(
    envs, actor, frames_per_batch=32 * K * GROUPS, total_frames=-1,
    auto_register_policy_transforms=False,
)  # fmt: skip
# One episode per environment and batch; the environments of a group reset with one seed.
batches = EpisodeCollector(segments, episodes=K * GROUPS, group_size=K, seed=0)

# %% [markdown]
# ## Training with the leave-one-out baseline
#
# `ReinforceLoss(baseline="leave_one_out")` reads each step's group (written by the
# collector under `"group"`) and weighs the reward-to-go of step t against the mean
# reward-to-go of the group's other episodes at their own step t (0 for an episode
# already over). No critic, 25 updates:

# %%
loss = ReinforceLoss(actor, baseline="leave_one_out")
loss.make_value_estimator("reward_to_go", gamma=0.99)
optimizer = torch.optim.Adam(actor.parameters(), lr=0.01)


def episode_returns(batch):
    """Each episode's undiscounted return and group (the batch holds whole episodes
    laid end to end)."""
    ends = batch["next", "done"].squeeze(-1)
    starts = torch.cat([torch.ones(1, dtype=torch.bool), ends[:-1]])
    episode = starts.long().cumsum(0) - 1
    reward = batch["next", "reward"].squeeze(-1)
    returns = torch.zeros(int(episode[-1]) + 1).index_add_(0, episode, reward)
    return returns, batch["group"].squeeze(-1)[starts]


mean_return = []
for _ in range(25):
    batch = batches.next()
    mean_return.append(episode_returns(batch)[0].mean().item())
    optimizer.zero_grad()
    loss(batch)["loss_actor"].backward()
    optimizer.step()

fig, ax = plt.subplots(figsize=(5, 3))
ax.plot(mean_return)
ax.set(xlabel="update (32 episodes each)", ylabel="mean episode return",
       title="CartPole, leave-one-out baseline")  # fmt: skip
fig.tight_layout()

# %% [markdown]
# ## The noise of each baseline, on the same batches
#
# Now the policy stays where it is, and `GradientStatistics` takes every episode's
# policy gradient under several weights at once, on 15 fresh batches. The independent
# unit is the *group* (`unit="group"`): episodes from one start are not independent of
# each other, and a group baseline ties them further, so only whole groups give an
# honest spread. `tr Σ` is the spread of one group's gradient; the noise scale B is
# the number of groups a batch needs before its mean gradient's noise falls to the size
# of its signal.

# %%
names = ["reward_to_go", "reward_to_go_minus_mean", "leave_one_out", "group_mean",
         "group_mean_scaled"]  # fmt: skip
stats = GradientStatistics(loss, unit="group", estimators=names)
trace = {name: 0.0 for name in names}
signal = {name: 0.0 for name in names}
measured = [batches.next() for _ in range(15)]
for batch in measured:
    out = stats(batch)
    for name in names:
        trace[name] += out[name, "trace_covariance"].item() / len(measured)
        signal[name] += out[name, "grad_norm_sq"].item() / len(measured)

print(f"{'weight Ψ':25s} {'tr Σ / tr Σ of G_t':>19s} {'B (groups)':>11s}")
for name in names:
    relative = trace[name] / trace["reward_to_go"]
    shown = "(other scale)" if name == "group_mean_scaled" else f"{relative:.2f}"
    print(f"{name:25s} {shown:>19s} {trace[name] / signal[name]:11.2f}")

# %% [markdown]
# Three things to read in the table:
#
# - both baselines cut the noise of the plain reward-to-go several times over; here,
#   the group's does about as well as the batch's mean return, without needing the
#   whole batch (a group is its own baseline) and without a critic to train;
# - `group_mean` (GRPO's baseline: the episode itself included) has the *same* B as
#   leave-one-out. It is leave-one-out times (K − 1)/K exactly, a shorter gradient with
#   the same direction and the same signal-to-noise ratio; a larger step size undoes
#   the difference;
# - `group_mean_scaled` divides by the group's spread of returns (GRPO's normalised
#   advantage). Its B can look good, but its expected gradient is no longer a multiple
#   of ∇J: the tests measure that bias against the exact gradient of a bandit.
#
# ## What the shared start adds
#
# Does the shared start matter, or would any four episodes do? The same batches answer
# it. Regroup their episodes so that each "group" holds one episode of four
# *different* starts (episode k of groups 0–3, of groups 4–7), weigh each step by the
# same leave-one-out rule, and compare the size of the advantages: the smaller they
# are, the less noise each step's gradient carries.


# %%
def regrouped(batch):
    """The same episodes, grouped across starts: episode k of K different starts."""
    ends = batch["next", "done"].squeeze(-1)
    starts = torch.cat([torch.ones(1, dtype=torch.bool), ends[:-1]])
    episode = starts.long().cumsum(0) - 1  # group g holds episodes g*K ... g*K + K - 1
    group, member = episode // K, episode % K
    out = batch.clone()
    out["group"] = ((group // K) * K + member).unsqueeze(-1)
    return out


def advantage_rms(loss, batch):
    """The root mean square of the leave-one-out advantage over the batch's steps."""
    with torch.no_grad():
        loss.value_estimator(batch)
    return batch_group_advantage(batch, batch["value_target"]).square().mean().sqrt().item()


def shared_start(loss, batches, n=10):
    same = [advantage_rms(loss, batch) for batch in batches[:n]]
    mixed = [advantage_rms(loss, regrouped(batch)) for batch in batches[:n]]
    return sum(same) / len(same), sum(mixed) / len(mixed)


# A fresh LunarLander policy: landers that crash in about a hundred steps, 4 groups of 4.
landers = gym_env("LunarLander-v3", num_envs=16)
lander = mlp_actor(landers, hidden=(32,))
lander_loss = ReinforceLoss(lander, baseline="leave_one_out")
lander_loss.make_value_estimator("reward_to_go", gamma=0.99)
lander_batches = EpisodeCollector(
    Collector(landers, lander, frames_per_batch=16 * 32, total_frames=-1,
              auto_register_policy_transforms=False),
    episodes=16, group_size=K, seed=0,
)  # fmt: skip
landings = [lander_batches.next() for _ in range(10)]

for task, task_loss, task_batches in (("CartPole", loss, measured),
                                      ("LunarLander", lander_loss, landings)):  # fmt: skip
    same, mixed = shared_start(task_loss, task_batches)
    print(f"{task:12s} RMS advantage: same start {same:6.2f}, four starts {mixed:6.2f} "
          f"(variance x{(same / mixed) ** 2:.2f})")  # fmt: skip

# %% [markdown]
# On CartPole the shared start is worth nothing: its starts differ by a few hundredths
# in each coordinate, and what decides an episode is the policy's own draws, so four
# episodes from anywhere are as good a baseline as four from one start. A lander's
# start decides much more (its terrain and first push): there, the episodes of one
# start are a clearly better baseline for each other than episodes of four.
#
# So a group baseline is always unbiased and free of a critic, and it pays most where
# episodes that share their randomness share their fate. The
# [theory page](../theory.md#measuring-the-variance-on-your-task) measures the group
# baselines through whole trainings with the variance lab (`rl-pg lab variance RECIPE
# --baseline greedy --batch-mode episodes ...`), where the greedy-rollout baseline, one
# greedy episode per group, turns out on LunarLander no better than none: it is only as
# good as the greedy policy it replays.

# %%
batches.shutdown()
lander_batches.shutdown()
