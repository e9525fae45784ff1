"""REINFORCE on a 100-armed bandit: why a baseline matters (docs/recipes/bandit.md).

Arm 0 pays 1.0, arms 1-49 pay 0.9, the rest 0. Without a baseline every sampled arm
is reinforced (all rewards are >= 0), so the policy often locks onto a 0.9 arm; with
the running-average baseline only better-than-average arms are. One sample per update
can still commit to a 0.9 arm before it has tried arm 0 enough: the default adds a
small entropy bonus, which keeps it trying. The comparisons run the tutorial's
setting, without it::

    rl-pg train bandit                       # one run (running-mean baseline, entropy 0.01)
    rl-pg train bandit --compare             # no baseline vs baseline, 5 seeds
    rl-pg train bandit --compare-samples     # 1, 4 and 16 samples per update
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
from torch import nn
from torchrl.envs import EnvBase

from rl_pg.envs import BanditEnv
from rl_pg.models import mlp_actor
from rl_pg.training import Count, Range, TrainConfig
from rl_pg.training.comparison import run_variants
from rl_pg.training.curves import plot_curves, read_curve
from rl_pg.training.recipe import Recipe

# The tutorial's experiments: REINFORCE without an entropy bonus.
TUTORIAL = {"entropy_coeff": 0.0, "confirm_episodes": None}
BASELINE_VARIANTS = {
    "no baseline": {"baseline": "none", **TUTORIAL},
    "running-average baseline": {"baseline": "running_mean", **TUTORIAL},
}
SAMPLE_VARIANTS = {f"{n} samples/update": {"samples_per_update": n, **TUTORIAL} for n in (1, 4, 16)}


@dataclass
class Config(
    TrainConfig,
    batch_mode="segments",  # each update pulls samples_per_update arms at once
    segment_length=1,
    total_frames=10_000_000,
    total_updates=20_000,  # the experiment: 20 000 updates of one sample
    baseline="running_mean",
    entropy_coeff=0.01,  # finds the 1.0 arm on 5/5 seeds; without it 3/5 (docs)
    # Greedily every checkpoint that found the 1.0 arm scores 1.0, the first of them
    # too; keep the one whose sampled pulls score best as well (docs: held both ways).
    confirm_episodes=200,
    lr=1e-3,
    eval_interval=1_000,
    eval_episodes=1,  # the bandit is deterministic for a greedy policy: one pull tells its arm
    threshold=0.99,  # the 1.0 arm
    # Trains on past the first checkpoint confirmed at 0.99 both ways: stopped there,
    # 8 of 10 seeds hold 0.99 on 1 000 fresh sampled pulls, trained on 10 of 10 (docs).
    stop_when_solved=False,
    checkpoint_interval=5_000,
    log_interval=10,
):
    """REINFORCE on a one-step bandit; policy Linear(1, 8)-tanh-Linear(8, A)."""

    arms: Annotated[int, Range(low=2)] = 100
    """Number of arms."""
    samples_per_update: Count = 1
    """Arms pulled (one-step episodes) per update."""
    compare: bool = False
    """Compare no baseline with a running-average one, and plot. Both without an entropy
    bonus, as the tutorial, on n_seeds seeds."""
    compare_samples: bool = False
    """Compare 1, 4 and 16 samples per update, and plot. With the baseline and no
    entropy bonus."""
    n_seeds: Count = 5
    """Seeds per variant for the comparisons."""


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    if render:  # one bandit, drawn
        return BanditEnv(num_arms=cfg.arms, render=True)
    return BanditEnv(num_arms=cfg.arms, batch_size=cfg.samples_per_update)


def make_eval_env(cfg: Config) -> EnvBase:
    return BanditEnv(num_arms=cfg.arms)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor(env, hidden=(8,), activation=nn.Tanh), None


def running_reward(run_dir, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """r <- 0.99 r + 0.01 reward, per update: the running reward the comparison plots
    (empty for a run shorter than ``log_interval`` updates, which logged none)."""
    try:
        frames, rewards = read_curve(run_dir, "train/episode_return")
    except FileNotFoundError:
        return np.zeros(0), np.zeros(0)
    running, out = 0.0, []
    for reward in rewards:
        # log_interval updates passed since the last point: apply them all at once.
        for _ in range(cfg.log_interval):
            running = 0.99 * running + 0.01 * reward
        out.append(running)
    return frames / cfg.samples_per_update, np.array(out)


def summarise(cfg: Config, run_dir) -> dict:
    _, running = running_reward(run_dir, cfg)
    return {"final_running_reward": float(running[-1]) if len(running) else None}


def _compare(cfg: Config, variants: dict, name: str) -> dict:
    root = Path(cfg.run_dir or f"runs/bandit-{name}")
    seeds = range(cfg.seed, cfg.seed + cfg.n_seeds)
    results = run_variants(RECIPE.train, cfg, variants, seeds=seeds, root=root)
    curves = {}
    for variant, runs in results.items():
        run_cfg = dataclasses.replace(cfg, **variants[variant])
        curves[variant] = [running_reward(run["run_dir"], run_cfg) for run in runs]
    plot_curves(
        curves,
        root / "comparison.png",
        xlabel="updates",
        ylabel="running reward",
        title=f"{cfg.arms}-armed bandit",
        hlines=[0.9, 1.0],
    )
    return results


def compare(cfg: Config) -> dict:
    """No baseline vs the running-average baseline, ``n_seeds`` seeds each."""
    return _compare(cfg, BASELINE_VARIANTS, "baselines")


def compare_samples(cfg: Config) -> dict:
    """1, 4 and 16 samples per update, ``n_seeds`` seeds each."""
    return _compare(cfg, SAMPLE_VARIANTS, "samples")


RECIPE = Recipe(
    name="bandit",
    config=Config,
    make_env=make_env,
    make_models=make_models,
    make_eval_env=make_eval_env,
    summarise=summarise,
    commands={"compare": compare, "compare_samples": compare_samples},
)
