"""Does the deployed policy hold its target both greedily and by sampling? rl_pg's
LunarLander recipe beside Stable-Baselines3's A2C and sb3-contrib's TRPO, at the same
frame budget, under one protocol.

Every tool trains ``budget_frames`` frames (the recipe's 1M); every ``eval_interval``
frames it pauses for ``eval_episodes`` greedy episodes on a separate environment, and
the best of those evaluations is the policy kept (rl_pg's ``best.pt`` rule). The kept
policy then plays ``final_episodes`` fresh episodes greedily and as many by sampling
its actions; a seed *holds* when both means reach the threshold. SB3's settings are
rl-baselines3-zoo's for LunarLander (their linear schedules decay over the budget
given here, not the zoo's shorter one). rl_pg's row is read from the recipe's stored
runs (``--rl-pg-stored``: ``rl-pg train lunarlander --seed S``, then ``rl-pg evaluate
RUN --episodes 100`` and ``--sample``; the recipe's defaults confirm a candidate
``best.pt`` on 100 more episodes both ways, its former defaults kept the best greedy
evaluation as the other tools do), or trained here with ``--tools rl_pg ...``.

Each finished (tool, seed) is written to the JSON at once: a killed run starts again
where it stopped (``--fresh`` discards what is there).

    pip install -c constraints.txt -e ".[bench]"
    python benchmarks/held_both_ways.py [--seeds 0 1 2 3 4]
"""

from __future__ import annotations

import copy
import json
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import tyro
from common import REPO, table, write_json

from rl_pg.app.stores import read_stored
from rl_pg.recipes import load


def _linear(start: float) -> Callable[[float], float]:
    """The zoo's ``lin_<start>``: decayed linearly to 0 over the run."""
    return lambda progress_remaining: start * progress_remaining


ZOO = {  # rl-baselines3-zoo 2.9.2, hyperparams/{a2c,trpo}.yml, LunarLander-v3
    "sb3_a2c": {
        "n_envs": 8,
        "kwargs": {
            "gamma": 0.995,
            "n_steps": 5,
            "learning_rate": _linear(0.00083),
            "ent_coef": 0.00001,
        },
    },
    "sb3_trpo": {
        "n_envs": 2,
        "kwargs": {
            "n_steps": 512,
            "cg_damping": 0.01,
            "gae_lambda": 0.98,
            "gamma": 0.99,
            "learning_rate": 1e-3,
            "n_critic_updates": 15,
        },
    },
}


@dataclass
class Config:
    """LunarLander's deployed policy, greedy and sampled: rl_pg against SB3's A2C and TRPO."""

    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3, 4])
    """Seeds run by every tool."""
    tools: list[str] = field(default_factory=lambda: ["sb3_a2c", "sb3_trpo"])
    """Tools trained here (any of rl_pg, sb3_a2c, sb3_trpo)."""
    rl_pg_stored: list[Path] = field(
        default_factory=lambda: [
            REPO / "results" / "lunarlander-kl-rate-0.001-confirm-entropy-0.json",
            REPO / "results" / "lunarlander-seeds.json",
        ]
    )
    """rl_pg's runs, stored by rl-pg report --store, one row per file, named by it (the
    recipe's defaults, whose best.pt is confirmed both ways on 100 more episodes, and
    its former defaults, kept by the best greedy evaluation as the other tools' are).
    None read with rl_pg among --tools."""
    budget_frames: int = 1_000_000
    """Frames every tool trains."""
    eval_interval: int = 25_000
    """Frames between the evaluations that pick the policy kept."""
    eval_episodes: int = 20
    """Greedy episodes per evaluation."""
    final_episodes: int = 100
    """Fresh episodes the kept policy plays, greedily and by sampling (a multiple of 10:
    ten environments play them)."""
    threshold: float = 200.0
    """Both means must reach it for a seed to hold."""
    threads: int = 1
    """torch threads for every tool."""
    fresh: bool = False
    """Discard the results already in the JSON instead of continuing them."""
    json_path: Path = REPO / "benchmarks" / "results" / "held_both_ways_lunarlander.json"
    """Where the results go (written after every finished run)."""


def sb3_model(tool: str, seed: int):
    """``tool``'s SB3 model on LunarLander with rl-zoo3's settings, untrained."""
    from sb3_contrib import TRPO
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    zoo = ZOO[tool]
    env = make_vec_env("LunarLander-v3", n_envs=zoo["n_envs"], seed=seed)
    algorithm = {"sb3_a2c": A2C, "sb3_trpo": TRPO}[tool]
    return algorithm("MlpPolicy", env, seed=seed, device="cpu", **zoo["kwargs"])


def run_sb3(tool: str, seed: int, cfg: Config) -> dict[str, Any]:
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    class KeepBest(BaseCallback):
        """Evaluates greedily every ``eval_interval`` frames and keeps the best weights."""

        def __init__(self) -> None:
            super().__init__()
            # One environment per episode: the policy acts on all of them at once.
            self.env = make_vec_env("LunarLander-v3", n_envs=cfg.eval_episodes, seed=10_000 + seed)
            self.next_eval, self.best, self.best_at, self.weights = cfg.eval_interval, None, 0, None

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next_eval:
                self.next_eval += cfg.eval_interval
                mean, _ = evaluate_policy(
                    self.model, self.env, n_eval_episodes=cfg.eval_episodes, deterministic=True
                )
                if self.best is None or mean > self.best:
                    self.best, self.best_at = float(mean), self.num_timesteps
                    self.weights = copy.deepcopy(self.model.policy.state_dict())
            return True

    model = sb3_model(tool, seed)
    keep = KeepBest()
    start = time.perf_counter()
    model.learn(total_timesteps=cfg.budget_frames, callback=keep)
    wall = time.perf_counter() - start
    model.policy.load_state_dict(keep.weights)
    out = {"best_eval": keep.best, "best_at_frames": keep.best_at, "wall_s": wall}
    for mode, deterministic in (("greedy", True), ("sampled", False)):
        final = make_vec_env("LunarLander-v3", n_envs=10, seed=2_000_000 + seed)
        mean, std = evaluate_policy(
            model, final, n_eval_episodes=cfg.final_episodes, deterministic=deterministic
        )
        out[mode] = {"mean_return": float(mean), "std_return": float(std)}
    return out


def run_rl_pg(seed: int, cfg: Config) -> dict[str, Any]:
    from rl_pg.app.evaluate import Args
    from rl_pg.app.evaluate import main as evaluate

    recipe = load("lunarlander")
    with tempfile.TemporaryDirectory() as run_dir:
        start = time.perf_counter()
        summary = recipe.train(
            recipe.config(
                seed=seed,
                run_dir=Path(run_dir),
                total_frames=cfg.budget_frames,
                eval_interval=cfg.eval_interval,
                eval_episodes=cfg.eval_episodes,
                progress=False,
            )
        )
        wall = time.perf_counter() - start
        out = {
            "best_eval": summary["best_eval_mean_return"],
            "best_at_frames": summary["best_at_frames"],
            "wall_s": wall,
        }
        for mode in ("greedy", "sampled"):
            record = evaluate(
                Args(run=Path(run_dir), episodes=cfg.final_episodes, sample=mode == "sampled")
            )
            out[mode] = {"mean_return": record["mean_return"], "std_return": record["std_return"]}
    return out


def stored_rl_pg(path: Path, seeds: list[int]) -> dict[int, dict[str, Any]]:
    """rl_pg's runs of ``seeds`` from a store of ``rl-pg report --store``."""
    runs = {}
    for report in read_stored(path)[0]:
        if report["seed"] in seeds and report.get("greedy") and report.get("sampled"):
            runs[report["seed"]] = {
                "best_eval": report["best_eval_mean_return"],
                "best_at_frames": report["best_at_frames"],
                "wall_s": report["train_wall_s"],
                **{
                    m: {k: report[m][k] for k in ("mean_return", "std_return")}
                    for m in ("greedy", "sampled")
                },
            }
    missing = sorted(set(seeds) - set(runs))
    if missing:
        raise SystemExit(f"{path} has no run evaluated both ways for seeds {missing}.")
    return runs


def summarise(runs: dict[str, dict[int, dict]], threshold: float) -> dict[str, Any]:
    """The table (printed) and each tool's held count over the seeds it has run so far
    (a stopped benchmark's tools may have run different seeds: "—" where one has not)."""
    seeds = sorted({seed for by_seed in runs.values() for seed in by_seed})
    rows, held = [], {}
    for tool, by_seed in runs.items():
        holds = [min(r["greedy"]["mean_return"], r["sampled"]["mean_return"]) >= threshold
                 for r in by_seed.values()]  # fmt: skip
        held[tool] = f"{sum(holds)}/{len(holds)}"
        means = {s: (r["greedy"]["mean_return"], r["sampled"]["mean_return"])
                 for s, r in by_seed.items()}  # fmt: skip
        cells = [f"{means[s][0]:.0f} / {means[s][1]:.0f}" if s in means else "—" for s in seeds]
        rows.append([tool, held[tool], *cells])
    print(table(rows, ["tool", "held both ways"] + [f"seed {s}: greedy / sampled" for s in seeds]))
    return {"held": held}


def main(cfg: Config) -> dict[str, Any]:
    torch.set_num_threads(cfg.threads)
    if cfg.final_episodes % 10:
        raise SystemExit(f"--final-episodes must be a multiple of 10, got {cfg.final_episodes}.")
    unknown = set(cfg.tools) - {"rl_pg", *ZOO}
    if unknown:
        raise SystemExit(f"--tools takes rl_pg, sb3_a2c and sb3_trpo, got {sorted(unknown)}.")
    done: dict[str, dict[int, dict]] = {}
    if cfg.json_path.exists() and not cfg.fresh:
        kept = json.loads(cfg.json_path.read_text())
        if kept["config"]["budget_frames"] != cfg.budget_frames:
            raise SystemExit(
                f"{cfg.json_path} holds runs of {kept['config']['budget_frames']} frames: "
                f"continue them with that budget, or pass --fresh."
            )
        done = {t: {int(s): r for s, r in by.items()} for t, by in kept["runs"].items()}
    runs: dict[str, dict[int, dict]] = {}
    if "rl_pg" not in cfg.tools:
        for path in cfg.rl_pg_stored:
            runs[f"rl_pg: {path.stem}"] = stored_rl_pg(path, cfg.seeds)
    for tool in cfg.tools:
        runs[tool] = {s: r for s, r in done.get(tool, {}).items() if s in cfg.seeds}
    for seed in cfg.seeds:  # seeds interleaved: machine noise hits every tool alike
        for tool in cfg.tools:
            if seed in runs[tool]:
                continue
            run = run_rl_pg(seed, cfg) if tool == "rl_pg" else run_sb3(tool, seed, cfg)
            runs[tool][seed] = run
            print(
                f"seed {seed} {tool}: best evaluation {run['best_eval']:.1f} at "
                f"{run['best_at_frames']} frames; greedy {run['greedy']['mean_return']:.1f}, "
                f"sampled {run['sampled']['mean_return']:.1f} ({run['wall_s']:.0f} s)",
                flush=True,
            )
            write_json(cfg.json_path, cfg, runs=runs, **summarise(runs, cfg.threshold))
    return write_json(cfg.json_path, cfg, runs=runs, **summarise(runs, cfg.threshold))


if __name__ == "__main__":
    main(tyro.cli(Config))
