"""How long does each tool take to solve CartPole-v1 (or LunarLander-v3), under one protocol?

rl_pg's recipe (its defaults) against Stable-Baselines3's A2C and PPO with the
rl-baselines3-zoo hyperparameters for the task. The same protocol for all: every
``eval_interval`` frames, training pauses for ``eval_episodes`` greedy episodes on a
separate environment; the first evaluation with a mean >= the threshold ends the run.
Reported: frames and training wall-clock (evaluation excluded) to solve, per seed and
median (a run that does not solve within its budget counts as never solving, so a tool
whose median seed fails has no median time). Seeds are interleaved (seed 0 of every
tool, then seed 1, ...) so that machine noise hits all tools alike. Every tool runs with
the same number of torch threads.

    pip install -c constraints.txt -e ".[bench]"
    python benchmarks/time_to_solve.py [--seeds 0 1 2 3 4]
    python benchmarks/time_to_solve.py --task lunarlander --seeds 0 1 2
"""

from __future__ import annotations

import math
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
import tyro
from common import REPO, table, write_json

from rl_pg.recipes import load


def _linear(start: float) -> Callable[[float], float]:
    """The zoo's ``lin_<start>``: decayed linearly to 0 over the tool's budget."""
    return lambda progress_remaining: start * progress_remaining


@dataclass(frozen=True)
class Task:
    """One environment of the comparison: its protocol and each tool's settings."""

    env_id: str
    recipe: str
    threshold: float
    eval_interval: int
    rl_pg_budget: int
    # The zoo's hyperparameters per SB3 tool: n_envs, n_timesteps (the budget, over
    # which its linear schedules decay) and the algorithm's keyword arguments.
    sb3: dict[str, dict[str, Any]]


TASKS = {
    "cartpole": Task(
        env_id="CartPole-v1",
        recipe="cartpole",
        threshold=475.0,
        eval_interval=5_000,
        rl_pg_budget=300_000,
        sb3={
            "sb3_a2c": {"n_envs": 8, "n_timesteps": 500_000, "kwargs": {"ent_coef": 0.0}},
            "sb3_ppo": {
                "n_envs": 8,
                "n_timesteps": 100_000,
                "kwargs": {
                    "n_steps": 32,
                    "batch_size": 256,
                    "gae_lambda": 0.8,
                    "gamma": 0.98,
                    "n_epochs": 20,
                    "ent_coef": 0.0,
                    "learning_rate": _linear(1e-3),
                    "clip_range": _linear(0.2),
                },
            },
        },
    ),
    "lunarlander": Task(
        env_id="LunarLander-v3",
        recipe="lunarlander",
        threshold=200.0,
        eval_interval=25_000,
        rl_pg_budget=1_000_000,
        sb3={  # the zoo's LunarLander-v2 entries (v3 fixed bugs, same task)
            "sb3_a2c": {
                "n_envs": 8,
                "n_timesteps": 200_000,
                "kwargs": {
                    "gamma": 0.995,
                    "n_steps": 5,
                    "learning_rate": _linear(0.00083),
                    "ent_coef": 0.00001,
                },
            },
            "sb3_ppo": {
                "n_envs": 16,
                "n_timesteps": 1_000_000,
                "kwargs": {
                    "n_steps": 1024,
                    "batch_size": 64,
                    "gae_lambda": 0.98,
                    "gamma": 0.999,
                    "n_epochs": 4,
                    "ent_coef": 0.01,
                },
            },
        },
    ),
}


@dataclass
class Config:
    """Time to solve a task (greedy mean >= threshold), rl_pg vs SB3."""

    task: Literal["cartpole", "lunarlander"] = "cartpole"
    """CartPole-v1 (solved at 475, evaluations every 5k frames) or LunarLander-v3 (200,
    every 25k frames)."""
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3, 4])
    """Seeds run by every tool."""
    tools: list[str] = field(default_factory=lambda: ["rl_pg", "sb3_a2c", "sb3_ppo"])
    """Contenders (any of rl_pg, sb3_a2c, sb3_ppo)."""
    eval_interval: int | None = None
    """Frames between evaluations (None: the task's)."""
    eval_episodes: int = 20
    """Greedy episodes per evaluation."""
    threshold: float | None = None
    """Mean evaluation return that counts as solved (None: the task's)."""
    budget_frames: int | None = None
    """Frames after which an unsolved run stops (None: the zoo's budgets; 300k for
    rl_pg on CartPole, 1M on LunarLander)."""
    threads: int = 1
    """torch threads for every tool (tiny MLPs run fastest on one)."""
    repeats: int = 3
    """Timed runs of every tool and seed, interleaved; a seed's time to solve is their
    median (its frames to solve are the same in every run: every tool is seeded). One
    seed's run decides a tool's median, and this VM's speed moves by a tenth from one
    second to the next; LunarLander's runs take minutes: ``--repeats 1`` there."""
    json_path: Path | None = None
    """Where the results are written (None: benchmarks/results/time_to_solve.json for
    CartPole, time_to_solve_lunarlander.json for LunarLander)."""

    def protocol(self) -> tuple[Task, int, float]:
        """The task, and its evaluation interval and threshold after the overrides."""
        task = TASKS[self.task]
        interval = self.eval_interval or task.eval_interval
        threshold = task.threshold if self.threshold is None else self.threshold
        return task, interval, threshold


def run_rl_pg(seed: int, cfg: Config) -> dict:
    task, interval, threshold = cfg.protocol()
    recipe = load(task.recipe)
    with tempfile.TemporaryDirectory() as run_dir:
        summary = recipe.train(
            recipe.config(
                seed=seed,
                run_dir=Path(run_dir),
                total_frames=cfg.budget_frames or task.rl_pg_budget,
                eval_interval=interval,
                eval_episodes=cfg.eval_episodes,
                threshold=threshold,
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

    task, interval, threshold = cfg.protocol()
    zoo = task.sb3[tool]

    class EvaluateAndStop(BaseCallback):
        """The shared protocol: pause, evaluate greedily, stop once solved."""

        def __init__(self) -> None:
            super().__init__()
            self.eval_env = make_vec_env(task.env_id, n_envs=cfg.eval_episodes, seed=seed + 1)
            self.next_eval = interval
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
            self.next_eval = (self.num_timesteps // interval + 1) * interval
            if mean >= threshold:
                self.solved_at = self.num_timesteps
                return False
            return True

    env = make_vec_env(task.env_id, n_envs=zoo["n_envs"], seed=seed)
    algorithm = A2C if tool == "sb3_a2c" else PPO
    model = algorithm("MlpPolicy", env, seed=seed, device="cpu", **zoo["kwargs"])
    callback = EvaluateAndStop()
    start = time.perf_counter()
    model.learn(total_timesteps=cfg.budget_frames or zoo["n_timesteps"], callback=callback)
    wall = time.perf_counter() - start - callback.eval_s
    return {"solved_at_frames": callback.solved_at, "train_wall_s": wall}


def main(cfg: Config) -> dict:
    if cfg.repeats < 1:
        raise SystemExit(f"--repeats must be at least 1, got {cfg.repeats}.")
    torch.set_num_threads(cfg.threads)
    walls: dict[str, dict[int, list[float]]] = {tool: {} for tool in cfg.tools}
    runs: dict[str, dict[int, dict]] = {tool: {} for tool in cfg.tools}
    for _ in range(cfg.repeats):
        for seed in cfg.seeds:
            for tool in cfg.tools:
                run = run_rl_pg(seed, cfg) if tool == "rl_pg" else run_sb3(tool, seed, cfg)
                first = runs[tool].setdefault(seed, run)
                if run["solved_at_frames"] != first["solved_at_frames"]:
                    raise RuntimeError(
                        f"{tool}, seed {seed}: solved at {first['solved_at_frames']} frames "
                        f"in one run and {run['solved_at_frames']} in another. Its runs are "
                        f"not reproducible, so their times cannot be pooled: run with "
                        f"--repeats 1."
                    )
                walls[tool].setdefault(seed, []).append(run["train_wall_s"])
                print(
                    f"seed {seed} {tool:8s} solved at {run['solved_at_frames']} frames, "
                    f"{run['train_wall_s']:.2f} s",
                    flush=True,
                )
    for tool, by_seed in runs.items():
        for seed, run in by_seed.items():
            run["train_wall_s"] = statistics.median(walls[tool][seed])
            run["train_wall_s_runs"] = walls[tool][seed]
    result = summarise(runs, cfg.seeds)
    name = "time_to_solve" if cfg.task == "cartpole" else f"time_to_solve_{cfg.task}"
    json_path = cfg.json_path or REPO / f"benchmarks/results/{name}.json"
    return write_json(json_path, cfg, **result)


def summarise(runs: dict[str, dict[int, dict]], seeds: list[int]) -> dict:
    """Print the per-tool table and rl_pg's wall-clock ratios; return them with the runs."""
    medians = {}
    rows = []
    for tool, by_seed in runs.items():
        solved = [r for r in by_seed.values() if r["solved_at_frames"] is not None]
        # An unsolved run has no time to solve: it counts as infinitely slow, so a tool
        # whose median seed does not solve has no finite median (a short budget spent
        # without solving cannot look fast).
        frames = [r["solved_at_frames"] or math.inf for r in by_seed.values()]
        walls = [
            r["train_wall_s"] if r["solved_at_frames"] is not None else math.inf
            for r in by_seed.values()
        ]
        median_frames, median_wall = statistics.median(frames), statistics.median(walls)
        medians[tool] = {  # None (JSON null): the median seed did not solve
            "solved": f"{len(solved)}/{len(by_seed)}",
            "median_frames": median_frames if math.isfinite(median_frames) else None,
            "median_train_wall_s": median_wall if math.isfinite(median_wall) else None,
        }
        rows.append(
            [
                tool,
                medians[tool]["solved"],
                medians[tool]["median_frames"] or "unsolved",
                medians[tool]["median_train_wall_s"] or "unsolved",
            ]
            + [
                f"{r['solved_at_frames'] or 'unsolved'} / {r['train_wall_s']:.2f} s"
                for r in by_seed.values()
            ]
        )
    header = ["tool", "solved", "median frames", "median wall to solve (s)"] + [
        f"seed {s}: frames / wall" for s in seeds
    ]
    print()
    print(table(rows, header))
    result: dict = {"runs": runs, "medians": medians}
    ours = medians.get("rl_pg", {}).get("median_train_wall_s")
    if ours is not None:
        ratios = {
            tool: ours / m["median_train_wall_s"]
            for tool, m in medians.items()
            if tool.startswith("sb3") and m["median_train_wall_s"] is not None
        }
        for tool, ratio in ratios.items():
            print(f"\nrl_pg median wall to solve / {tool}'s: {ratio:.2f}x  (target <= 0.5)")
        if ratios:
            result["rl_pg_over_sb3_wall"] = ratios
            result["rl_pg_over_best_sb3_wall"] = max(ratios.values())
    return result


if __name__ == "__main__":
    main(tyro.cli(Config))
