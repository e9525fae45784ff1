"""How long does each tool take to solve CartPole-v1, under one protocol?

rl_pg's CartPole recipe (its defaults) against Stable-Baselines3's A2C and PPO with the
rl-baselines3-zoo hyperparameters for CartPole-v1. The same protocol for all: every
``eval_interval`` frames, training pauses for ``eval_episodes`` greedy episodes on a
separate environment; the first evaluation with a mean >= 475 ends the run. Reported:
frames and training wall-clock (evaluation excluded) to solve, per seed and median.
Seeds are interleaved (seed 0 of every tool, then seed 1, ...) so that machine noise
hits all tools alike. Every tool runs with the same number of torch threads.

    pip install -c constraints.txt -e ".[bench]"
    python benchmarks/time_to_solve.py [--seeds 0 1 2 3 4]
"""

from __future__ import annotations

import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tyro
from common import REPO, table, write_json

from rl_pg.recipes import load


@dataclass
class Config:
    """Time to solve CartPole-v1 (greedy mean >= threshold), rl_pg vs SB3."""

    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3, 4])
    """Seeds run by every tool."""
    tools: list[str] = field(default_factory=lambda: ["rl_pg", "sb3_a2c", "sb3_ppo"])
    """Contenders (any of rl_pg, sb3_a2c, sb3_ppo)."""
    eval_interval: int = 5_000
    """Frames between evaluations."""
    eval_episodes: int = 20
    """Greedy episodes per evaluation."""
    threshold: float = 475.0
    """Mean evaluation return that counts as solved."""
    budget_frames: int | None = None
    """Frames after which an unsolved run stops (None: the zoo's budgets, 300k for rl_pg)."""
    threads: int = 1
    """torch threads for every tool (tiny MLPs run fastest on one)."""
    json_path: Path = REPO / "benchmarks/results/time_to_solve.json"
    """Where the results are written."""


# The zoo's budgets (n_timesteps); PPO's linear schedules decay over its budget.
SB3_BUDGET = {"sb3_a2c": 500_000, "sb3_ppo": 100_000}
RL_PG_BUDGET = 300_000


def run_rl_pg(seed: int, cfg: Config) -> dict:
    cartpole = load("cartpole")
    with tempfile.TemporaryDirectory() as run_dir:
        summary = cartpole.train(
            cartpole.config(
                seed=seed,
                run_dir=Path(run_dir),
                total_frames=cfg.budget_frames or RL_PG_BUDGET,
                eval_interval=cfg.eval_interval,
                eval_episodes=cfg.eval_episodes,
                threshold=cfg.threshold,
                stop_when_solved=True,
                progress=False,
            )
        )
    return {
        "solved_at_frames": summary["solved_at_frames"],
        "train_wall_s": summary["train_wall_s"],
    }


def run_sb3(tool: str, seed: int, cfg: Config) -> dict:
    from stable_baselines3 import A2C, PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    class EvaluateAndStop(BaseCallback):
        """The shared protocol: pause, evaluate greedily, stop once solved."""

        def __init__(self) -> None:
            super().__init__()
            self.eval_env = make_vec_env("CartPole-v1", n_envs=cfg.eval_episodes, seed=seed + 1)
            self.next_eval = cfg.eval_interval
            self.eval_s = 0.0
            self.solved_at = None

        def _on_step(self) -> bool:
            if self.num_timesteps < self.next_eval:
                return True
            start = time.perf_counter()
            mean, _ = evaluate_policy(
                self.model, self.eval_env, n_eval_episodes=cfg.eval_episodes, deterministic=True
            )
            self.eval_s += time.perf_counter() - start
            self.next_eval = (self.num_timesteps // cfg.eval_interval + 1) * cfg.eval_interval
            if mean >= cfg.threshold:
                self.solved_at = self.num_timesteps
                return False
            return True

    env = make_vec_env("CartPole-v1", n_envs=8, seed=seed)
    if tool == "sb3_a2c":  # zoo: n_envs 8, ent_coef 0, SB3 defaults otherwise
        model = A2C("MlpPolicy", env, ent_coef=0.0, seed=seed, device="cpu")
    else:  # zoo: PPO with linearly decayed learning rate and clip range
        model = PPO(
            "MlpPolicy",
            env,
            n_steps=32,
            batch_size=256,
            gae_lambda=0.8,
            gamma=0.98,
            n_epochs=20,
            ent_coef=0.0,
            learning_rate=lambda progress_remaining: 1e-3 * progress_remaining,
            clip_range=lambda progress_remaining: 0.2 * progress_remaining,
            seed=seed,
            device="cpu",
        )
    callback = EvaluateAndStop()
    start = time.perf_counter()
    model.learn(total_timesteps=cfg.budget_frames or SB3_BUDGET[tool], callback=callback)
    wall = time.perf_counter() - start - callback.eval_s
    return {"solved_at_frames": callback.solved_at, "train_wall_s": wall}


def main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    runs: dict[str, dict[int, dict]] = {tool: {} for tool in cfg.tools}
    for seed in cfg.seeds:
        for tool in cfg.tools:
            run = run_rl_pg(seed, cfg) if tool == "rl_pg" else run_sb3(tool, seed, cfg)
            runs[tool][seed] = run
            print(
                f"seed {seed} {tool:8s} solved at {run['solved_at_frames']} frames, "
                f"{run['train_wall_s']:.2f} s",
                flush=True,
            )

    medians = {}
    rows = []
    for tool, by_seed in runs.items():
        solved = [r for r in by_seed.values() if r["solved_at_frames"] is not None]
        # Unsolved runs count as their whole budget (an optimistic lower bound).
        walls = [r["train_wall_s"] for r in by_seed.values()]
        frames = [r["solved_at_frames"] or float("inf") for r in by_seed.values()]
        medians[tool] = {
            "solved": f"{len(solved)}/{len(by_seed)}",
            "median_frames": statistics.median(frames),
            "median_train_wall_s": statistics.median(walls),
        }
        rows.append(
            [
                tool,
                medians[tool]["solved"],
                medians[tool]["median_frames"],
                medians[tool]["median_train_wall_s"],
            ]
            + [
                f"{r['solved_at_frames'] or '—'} / {r['train_wall_s']:.2f} s"
                for r in by_seed.values()
            ]
        )
    header = ["tool", "solved", "median frames", "median wall (s)"] + [
        f"seed {s}: frames / wall" for s in cfg.seeds
    ]
    print()
    print(table(rows, header))
    result: dict = {"runs": runs, "medians": medians}
    sb3 = [medians[t]["median_train_wall_s"] for t in cfg.tools if t.startswith("sb3")]
    if "rl_pg" in medians and sb3:
        ratio = medians["rl_pg"]["median_train_wall_s"] / min(sb3)
        result["rl_pg_over_best_sb3_wall"] = ratio
        print(f"\nrl_pg median wall / best SB3 median wall: {ratio:.2f}x  (target <= 0.5)")
    return write_json(cfg.json_path, cfg, **result)


if __name__ == "__main__":
    main(tyro.cli(Config))
