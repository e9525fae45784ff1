"""REINFORCE on a 100-armed bandit: why a baseline matters (docs/recipes/bandit.md).

Arm 0 pays 1.0, arms 1-49 pay 0.9, the rest 0. Without a baseline every sampled arm
is reinforced (all rewards are >= 0), so the policy often locks onto a 0.9 arm; with
the running-average baseline only better-than-average arms are.

    python recipes/bandit.py                       # one run (running-mean baseline)
    python recipes/bandit.py --compare             # no baseline vs baseline, 5 seeds
    python recipes/bandit.py --compare-samples     # 1, 4 and 16 samples per update
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from torch import nn
from torchrl.envs import EnvBase

from rl_pg.checkpoint import write_atomically
from rl_pg.envs import BanditEnv
from rl_pg.models import mlp_actor
from rl_pg.training import Count, Range, TrainConfig, train
from rl_pg.training.cli import parse_config
from rl_pg.training.comparison import plot_curves, read_curve, run_variants
from rl_pg.training.console import format_summary
from rl_pg.training.interrupt import exit_quietly_on_interrupt


@dataclass
class Config(TrainConfig):
    """REINFORCE on a one-step bandit; policy Linear(1, 8)-tanh-Linear(8, A)."""

    arms: Annotated[int, Range(low=2)] = 100
    """Number of arms."""
    samples_per_update: Count = 1
    """Arms pulled (one-step episodes) per update."""
    compare: bool = False
    """Run no baseline vs running-average baseline on n_seeds seeds and plot them."""
    compare_samples: bool = False
    """Run 1, 4 and 16 samples per update (with the baseline) and plot them."""
    n_seeds: Count = 5
    """Seeds per variant for the comparisons."""
    batch_mode: Literal["episodes", "segments"] = "segments"
    """Each update pulls samples_per_update arms at once (one-step segments)."""
    segment_length: int = 1
    """One step per environment per update."""
    total_frames: int = 10_000_000
    """Environment steps to train for (at most)."""
    total_updates: int | None = 20_000
    """Updates (the experiment: 20 000 updates of one sample)."""
    baseline: Literal["none", "batch_mean", "running_mean", "ema", "critic"] = "running_mean"
    """What is subtracted from the reward: 'none' or 'running_mean' in the comparison."""
    lr: float = 1e-3
    """Learning rate."""
    eval_interval: int = 1_000
    """Frames between greedy evaluations."""
    eval_episodes: int = 1
    """The bandit is deterministic for a greedy policy: one pull tells its arm."""
    threshold: float | None = 0.99
    """Greedy return that counts as solved (the 1.0 arm)."""
    stop_when_solved: bool = False
    """Keep training to show where the running reward settles."""
    checkpoint_interval: int = 5_000
    """Updates between checkpoints."""
    log_interval: int = 10
    """Updates between training-metric log lines."""


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    return BanditEnv(num_arms=cfg.arms, batch_size=cfg.samples_per_update)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor(env, hidden=(8,), activation=nn.Tanh), None


def main(cfg: Config) -> dict:
    summary = train(
        cfg,
        recipe="bandit",
        make_env=partial(make_env, cfg),
        make_models=partial(make_models, cfg=cfg),
        make_eval_env=partial(BanditEnv, num_arms=cfg.arms),
    )
    _, running_reward = _running_reward(summary["run_dir"], cfg)
    summary["final_running_reward"] = float(running_reward[-1])
    write_atomically(Path(summary["run_dir"]) / "summary.json", json.dumps(summary, indent=2))
    return summary


def _running_reward(run_dir, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """r <- 0.99 r + 0.01 reward, per update: the running reward the comparison plots."""
    frames, rewards = read_curve(run_dir, "train/episode_return")
    running, out = 0.0, []
    for reward in rewards:
        # log_interval updates passed since the last point: apply them all at once.
        for _ in range(cfg.log_interval):
            running = 0.99 * running + 0.01 * reward
        out.append(running)
    return frames / cfg.samples_per_update, np.array(out)


def compare(cfg: Config, variants: dict, name: str) -> dict:
    root = Path(cfg.run_dir or f"runs/bandit-{name}")
    seeds = range(cfg.seed, cfg.seed + cfg.n_seeds)
    results = run_variants(main, cfg, variants, seeds=seeds, root=root)
    curves = {}
    for variant, runs in results.items():
        run_cfg = dataclasses.replace(cfg, **variants[variant])
        curves[variant] = [_running_reward(run["run_dir"], run_cfg) for run in runs]
    plot_curves(
        curves,
        root / "comparison.png",
        xlabel="updates",
        ylabel="running reward",
        title=f"{cfg.arms}-armed bandit",
        hlines=[0.9, 1.0],
    )
    return results


BASELINE_VARIANTS = {
    "no baseline": {"baseline": "none"},
    "running-average baseline": {"baseline": "running_mean"},
}
SAMPLE_VARIANTS = {f"{n} samples/update": {"samples_per_update": n} for n in (1, 4, 16)}


if __name__ == "__main__":
    with exit_quietly_on_interrupt():
        config = parse_config(Config)
        if config.compare:
            print(compare(config, BASELINE_VARIANTS, "baselines"))
        elif config.compare_samples:
            print(compare(config, SAMPLE_VARIANTS, "samples"))
        else:
            print(format_summary(main(config)))
