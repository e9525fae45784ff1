"""How fast does rl_pg evaluate on MetaDrive: episodes played inside worker processes
against the same episodes stepped from the main process through TorchRL's ParallelEnv?

The MetaDrive recipe's evaluations play each worker's part of a scenario set in order.
In one run, repetitions interleaved, the same policy (the recipe's network, untrained
unless ``--run`` names a run directory; greedy) plays the same held-out scenarios:

* ``EpisodeWorkers``: each process receives the policy once and plays its episodes on
  its own engine (what the recipe does);
* ``ParallelEnv``: the same environments in as many processes, stepped one batched step
  at a time from the main process, which runs the policy.

Both print their scores (the same, up to MetaDrive's float-level non-repeatability
from one reset to the next, which a greedy policy can amplify over long episodes) and
the time of one evaluation once the engines are up; the figure of merit is
ParallelEnv's time over EpisodeWorkers'.

    python benchmarks/evaluation.py --run runs/md0
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch
import tyro
from common import REPO, table, write_json
from torchrl.envs import ParallelEnv

from rl_pg.envs import metadrive as md
from rl_pg.episode_workers import EpisodeWorkers
from rl_pg.evaluation import evaluate
from rl_pg.recipes import load
from rl_pg.training import read_run
from rl_pg.training.checkpoints import load_models

COLUMNS = ["seconds", "steps/s", "mean return", "route completion"]


@dataclass
class Config:
    """MetaDrive evaluation: episodes in worker processes vs a step-by-step ParallelEnv."""

    episodes: int = 40
    """Episodes per evaluation (each a different held-out scenario)."""
    workers: int = 2
    """Processes (MetaDrive engines) for each contender."""
    horizon: int = md.DEFAULT_HORIZON
    """Time limit of an episode, in steps."""
    repeats: int = 2
    """Interleaved repetitions per contender (the median is reported)."""
    run: Path | None = None
    """A MetaDrive run directory whose last checkpoint drives; untrained if omitted."""
    json_path: Path = REPO / "benchmarks/results/evaluation.json"
    """Where the results are written."""


def main(cfg: Config) -> dict:
    recipe = load("metadrive")
    saved = None if cfg.run is None else read_run(cfg.run, which="last")
    config = recipe.config() if saved is None else recipe.config.from_stored(saved["config"])
    # The first `episodes` held-out scenarios, cut into one consecutive part per worker.
    makers = [
        partial(md.metadrive_env, md.HELD_OUT, actions=config.actions, order="sequential",
                horizon=cfg.horizon, scenarios=part)
        for part in md.split_scenarios(md.HELD_OUT, cfg.workers, count=cfg.episodes)
    ]  # fmt: skip
    contenders = {
        "EpisodeWorkers": EpisodeWorkers(makers),
        "ParallelEnv": ParallelEnv(cfg.workers, makers, use_buffers=False),
    }
    torch.manual_seed(0)
    actor = None
    seconds: dict[str, list[float]] = {name: [] for name in contenders}
    scores: dict[str, dict] = {}
    try:
        for env in contenders.values():  # start the engines, outside the timings
            if actor is None:
                actor, critic = recipe.make_models(env, config)
                if saved is not None:
                    load_models(saved, actor, critic)
            evaluate(actor, env, episodes=cfg.workers, max_steps=cfg.horizon)
        for _ in range(cfg.repeats):
            for name, env in contenders.items():
                env.set_seed(0)
                begin = time.perf_counter()
                scores[name] = evaluate(
                    actor, env, episodes=cfg.episodes, max_steps=cfg.horizon,
                    values=recipe.eval_values,
                )  # fmt: skip
                seconds[name].append(time.perf_counter() - begin)
    finally:
        for env in contenders.values():
            env.close()
    median = {name: statistics.median(times) for name, times in seconds.items()}
    rows = [
        [name, median[name], cfg.episodes * scores[name]["mean_length"] / median[name],
         scores[name]["mean_return"], scores[name]["mean_route_completion"]]
        for name in contenders
    ]  # fmt: skip
    print(table(rows, ["contender", *COLUMNS]))
    ratio = median["ParallelEnv"] / median["EpisodeWorkers"]
    print(f"ParallelEnv / EpisodeWorkers: {ratio:.2f}x the time")
    return write_json(
        cfg.json_path,
        cfg,
        median_seconds=median,
        scores=scores,
        rows={row[0]: dict(zip(COLUMNS, row[1:], strict=True)) for row in rows},
        parallel_env_over_workers=ratio,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
