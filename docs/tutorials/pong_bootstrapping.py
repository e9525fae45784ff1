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
# # 6. Pong: a learned baseline, and returns bootstrapped every 50 steps
#
# In Pong a reward comes only when a point ends, and a game lasts thousands of steps.
# Waiting for the end of each game before an update would mean few updates, each
# weighting an action by a return that sums every later point. The Pong tutorial this
# project grew from does what actor-critic methods do: 16 games play side by side, and
# every $n = 50$ steps an update weights each action by
#
# $$
# \hat G_t - V(s_t) = \sum_{k=t}^{T-1} \gamma^{k-t} r_k + \gamma^{T-t}\, V(s_T) - V(s_t)
# $$
#
# the rewards up to the end of the segment ($T$), then the learned value of where the
# segment stopped (none if the game ended inside it), minus the value of where the
# action was taken. Here we look at what
# the network sees, then at the three weights — the return to the end of the game, the
# same minus $V(s_t)$, and the bootstrapped one — on the same steps of a trained agent.

# %%
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import torch
from IPython.display import Image, Markdown
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rl_pg import ReinforceLoss
from rl_pg.app.figures import plot_stored
from rl_pg.app.sources import shipped_agent
from rl_pg.app.tables import format_evaluations
from rl_pg.functional import reward_to_go
from rl_pg.recipes import load
from rl_pg.training import load_models, read_run

torch.set_num_threads(1)
_ = torch.manual_seed(0)

# %% [markdown]
# ## What the network sees
#
# `load("pong")` is the recipe (`rl-pg train pong`). Its games go through
# `FrameDifference`: each 210×160 colour frame is cropped to the court, every second row
# and column of one channel is kept (80×80), the background becomes 0 and everything
# else 1; the network gets the difference between this frame and the previous one, so a
# single input shows which way the ball and the paddles move. A paddle that waits shows
# in no difference, so the agent shipped with rl_pg, trained with `--frame`, also gets
# the processed frame itself. We load it (`rl-pg play pong --pretrained` plays it: 2M
# agent steps of the recipe with `--frame`) and let it play a few seconds of a game,
# keeping the raw frames.

# %%
pong = load("pong")
saved = read_run(shipped_agent("pong"))
cfg = pong.config.from_stored(saved["config"], num_envs=1)

env = pong.make_play_env(cfg, render=True)  # one game, raw frames kept
actor, critic = pong.make_models(env, cfg)
load_models(saved, actor, critic)
env.set_seed(0)
with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
    opening = env.rollout(80, actor)
env.close()

step = 70
fig, axes = plt.subplots(1, 3, figsize=(10, 3.6))
axes[0].imshow(opening["pixels"][step])
axes[0].set_title("the game's frame (210×160×3)")
axes[1].imshow(opening["next", "previous_frame"][step - 1], cmap="gray")
axes[1].set_title("processed (80×80, 0 or 1): with --frame, an input")
axes[2].imshow(opening["observation"][step].reshape(80, 80), cmap="bwr", vmin=-1, vmax=1)
axes[2].set_title("the input: this minus the last")
for ax in axes:
    ax.set_axis_off()
fig.tight_layout()

# %% [markdown]
# ## The critic follows the return
#
# One model with two heads: a shared Linear–ReLU trunk of 200 units (over the 6 400
# inputs of the difference, and the frame's 6 400 with `--frame`), 6 action logits and
# one value. Now 6 000 steps of play by sampling (as in training), without the raw
# frames. The environment resets itself when a game ends: the done flags mark where,
# and `reward_to_go` keeps each game's rewards to itself. The last game is cut by the
# end of the batch, so its return is bootstrapped from $V$ of the state after the last
# step (`next_value`), as at any batch edge.

# %%
env = pong.make_play_env(cfg)
env.set_seed(1)
with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
    steps = env.rollout(6_000, actor, break_when_any_done=False)
    value = critic(steps.select(*critic.in_keys).clone())["state_value"]
    next_value = critic(steps["next"].select(*critic.in_keys).clone())["state_value"]
env.close()

reward, done = steps["next", "reward"], steps["next", "done"]
terminated = steps["next", "terminated"]
gamma = cfg.gamma
to_end = reward_to_go(reward, done, gamma, terminated=terminated, next_value=next_value)
print(
    f"{int(done.sum())} games ended in {len(steps)} steps; points won "
    f"{int((reward > 0).sum())}, lost {int((reward < 0).sum())}"
)

shown = slice(0, 1500)
fig, ax = plt.subplots(figsize=(10, 3.4))
ax.plot(to_end[shown], label="return to the end of the game $G_t$", lw=1)
ax.plot(value[shown], label="the critic's $V(s_t)$", lw=1)
points = reward[shown].squeeze(-1).nonzero().squeeze(-1)
ax.scatter(points, reward[shown][points], c="k", s=12, label="a point ($r = \\pm 1$)")
ax.set(xlabel="step", ylabel="return", title=f"γ = {gamma}: a point counts for about 100 steps")
ax.legend(loc="lower left", fontsize=8)
fig.tight_layout()

# %% [markdown]
# The critic has learnt what the coming point is worth from where the ball is: its
# value rises before the points the agent wins and falls before those it loses. It is
# noisy, and often hopeful where a point is about to be lost (orange above blue): the
# bias we meet next.
#
# ## Three weights on the same steps
#
# Cut the steps into segments of 50, as the training loop collects them, and bootstrap
# each segment's end from $V$: the same `reward_to_go`, with the segment ends marked as
# cuts (done, but not terminated).

# %%
segment = cfg.segment_length
cut = done.clone()
cut[segment - 1 :: segment] = True
bootstrapped = reward_to_go(reward, cut, gamma, terminated=terminated, next_value=next_value)

weights = {  # name: (label of the figure, the weight of each step)
    "G_t": ("$G_t$", to_end),
    "G_t - V(s_t)": ("$G_t - V(s_t)$", to_end - value),
    f"bootstrapped ({segment} steps) - V(s_t)": (
        f"$\\hat G_t - V(s_t)$, {segment} steps, bootstrapped",
        bootstrapped - value,
    ),
}
for name, (_, psi) in weights.items():
    print(f"{name:35s} spread (std) {psi.std():.3f}   mean {psi.mean():+.3f}")
print(f"bootstrapped minus to-the-end returns: mean {(bootstrapped - to_end).mean():+.3f}")

fig, ax = plt.subplots(figsize=(7, 3.4))
for label, psi in weights.values():
    ax.hist(psi.squeeze(-1), bins=80, range=(-2, 2), histtype="step", label=label)
ax.set(xlabel="the weight $\\Psi_t$ of $\\nabla \\log \\pi(a_t \\mid s_t)$", ylabel="steps")
ax.legend(fontsize=8)
fig.tight_layout()

# %% [markdown]
# Subtracting $V(s_t)$ narrows the weights without moving their expectation in the
# gradient (the baseline lesson of notebooks 2 and 3). Bootstrapping narrows them
# further: the rewards after the segment's end, and their noise, are replaced by one
# number, $V(s_T)$. The price is bias: where $V(s_T)$ is wrong, every weight of the
# segment is wrong by $\gamma^{T-t}$ times as much (the mean difference printed above),
# and unlike a baseline, that does move the gradient. A critic that is still learning
# makes it worse, which is why the value head gets twice the weight of the policy in
# the loss (`critic_coeff=2`).
#
# ## The same target in the training loop
#
# The loop does not cut anything by hand: a collector hands it a batch of 16 games × 50
# steps, and `ReinforceLoss`'s reward-to-go estimator bootstraps every row whose episode
# the batch cut. On our steps laid out as rows of 50, it computes exactly the targets
# above:

# %%
loss = ReinforceLoss(actor, critic, critic_coeff=cfg.critic_coeff)
loss.make_value_estimator("reward_to_go", gamma=gamma)
rows = steps[: len(steps) // segment * segment].reshape(-1, segment)
with torch.no_grad():
    rows = loss.value_estimator(rows.clone())
torch.testing.assert_close(rows["value_target"].reshape(-1, 1), bootstrapped[: rows.numel()])
torch.testing.assert_close(rows["advantage"].reshape(-1, 1), (bootstrapped - value)[: rows.numel()])
print("batch", tuple(rows.shape), "→ value_target and advantage match the hand-made ones")

# %% [markdown]
# ## Trained for real
#
# `rl-pg train pong` trains this for 2M agent steps, evaluating greedily every 100k
# steps. The two seeds below, their kept and final checkpoints played on 20 fresh games
# greedily and by sampling, come from stored results. Evaluations use sticky actions
# (each step the game repeats the previous action with probability 0.25), so that
# greedy games differ:

# %%
here = Path.cwd().resolve()  # docs/tutorials in a checkout of rl_pg
seeds = next(
    found
    for folder in (here, *here.parents)
    if (found := folder / "results" / "pong-seeds.json").is_file()
)
Markdown(format_evaluations(seeds))

# %%
figure = Path(tempfile.mkdtemp()) / "pong_seeds.png"
Image(filename=plot_stored(seeds, figure))

# %% [markdown]
# The agents return the ball for thousands of steps but still lose most points: the
# milestone of a greedy mean ≥ 0 within 2M steps is not met with sticky actions. Without
# them, the same training wins every greedy game — a single line of play, learnt by
# heart. The [Pong](../recipes/pong.md) page has the set-up, the flags and the
# evaluations along training.
