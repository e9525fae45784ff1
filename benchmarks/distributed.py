"""Collecting on several workers: Ray against the multi-process collector, and a model of
how training speed scales with the workers, from costs measured here.

One run, contenders interleaved, training frames/s (training wall-clock, evaluation
excluded) of a recipe's defaults with:

* one worker in the training process (the local collector),
* ``--workers N`` worker processes (TorchRL's multi-process collector),
* ``--ray --workers N`` Ray actors (TorchRL's Ray collector, on one local Ray instance
  that every Ray run shares; with ``RAY_ADDRESS`` set, on that cluster),

for N in ``workers``. Then the costs that the scaling model is made of, each measured
alone: the seconds one worker takes to collect one segment (its environment and the
policy, no learning), and the learner's seconds per frame of an update (the recipe's
loss, backward pass and optimiser step, on batches of 1 to N segments). The model of one
synchronous update with n workers, each collecting a segment of S frames on its own core:

    T(n) = S / c  +  n · S · l  +  o

(collection in parallel, then the learner on all n segments, then a fixed overhead o of
gathering the batch and sending the weights, fitted on the one-Ray-worker run). It
predicts Ray's frames/s n · S / T(n) at every n; the runs at 2 workers check it, and its
predictions at 8, 32 and 128 workers assume a core per worker and an overhead that does
not grow with them (gathering more segments does, a little: an upper bound).

    pip install -c constraints.txt -e ".[metadrive,ray]"
    python benchmarks/distributed.py                       # MetaDrive
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tyro
from common import REPO, table, write_json
from throughput import recipe_training
from torchrl.collectors import Collector

from rl_pg.lean import lean_policy
from rl_pg.recipes import load
from rl_pg.training.cluster import start_ray
from rl_pg.training.optimisation import make_loss, make_optimizer, update


@dataclass
class Config:
    """Training frames/s with worker processes and Ray actors, and a scaling model."""

    recipe: str = "metadrive"
    """The recipe trained (its defaults; segments)."""
    frames: int = 30_000
    """Training frames per repetition of one contender."""
    repeats: int = 2
    """Interleaved repetitions per contender (the median is reported)."""
    workers: list[int] = field(default_factory=lambda: [2])
    """Worker counts compared beside the single in-process worker."""
    predict: list[int] = field(default_factory=lambda: [8, 32, 128])
    """Worker counts the model predicts for."""
    cost_segments: int = 20
    """Segments timed for the collection and learner costs."""
    threads: int = 1
    """torch threads of the training process."""
    json_path: Path = REPO / "benchmarks/results/distributed.json"
    """Where the results are written."""


def costs(recipe, segments: int, largest: int) -> dict[str, float]:
    """Seconds per segment of one worker collecting alone, and the learner's seconds per
    frame (median over batches of 1 to ``largest`` segments)."""
    cfg = recipe.config()
    env = recipe.make_env(cfg)
    actor, critic = recipe.make_models(env, cfg)
    per_segment = cfg.segment_length * max(1, env.batch_size.numel())
    collector = Collector(
        env,
        lean_policy(actor),
        frames_per_batch=per_segment,
        total_frames=-1,
        track_traj_ids=False,
        auto_register_policy_transforms=False,
    )
    batches = iter(collector)
    kept = [next(batches)]  # start-up outside the timer
    start = time.perf_counter()
    for _ in range(segments):
        kept.append(next(batches))
    collect = (time.perf_counter() - start) / segments
    collector.shutdown()
    loss = make_loss(cfg, actor, critic)
    optimizer = make_optimizer(cfg, loss)
    per_frame = []
    for n in range(1, largest + 1):
        batch = torch.stack(kept[:n])  # n workers' segments, one batch dimension each
        update(cfg, loss, optimizer, batch.clone(), lr=cfg.lr)  # warm
        start = time.perf_counter()
        for _ in range(3):
            update(cfg, loss, optimizer, batch.clone(), lr=cfg.lr)
        per_frame.append((time.perf_counter() - start) / 3 / batch.numel())
    return {
        "segment_frames": per_segment,
        "collect_s_per_segment": collect,
        "learn_s_per_frame": statistics.median(per_frame),
    }


def model(cost: dict[str, float], overhead: float, n: int) -> float:
    """Predicted training frames/s with ``n`` workers."""
    s = cost["segment_frames"]
    seconds = cost["collect_s_per_segment"] + n * s * cost["learn_s_per_frame"] + overhead
    return n * s / seconds


def fitted_overhead(cost: dict[str, float], rate: float, n: int) -> float:
    """The overhead per update that makes the model give ``rate`` at ``n`` workers."""
    s = cost["segment_frames"]
    return n * s / rate - cost["collect_s_per_segment"] - n * s * cost["learn_s_per_frame"]


def main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    recipe = load(cfg.recipe)
    runs = {"1 worker, in the training process": {}}
    for n in cfg.workers:
        runs[f"{n} worker processes"] = {"workers": n}
        runs[f"{n} Ray workers"] = {"workers": n, "ray": True}
    # (One worker process is the in-process collector: the process backend starts at 2.)
    runs["1 Ray worker"] = {"workers": 1, "ray": True}
    rates: dict[str, list[float]] = {name: [] for name in runs}
    # One Ray instance for every Ray run (each would start and stop its own otherwise:
    # seconds each, outside the training clock all the same).
    started = start_ray(max(cfg.workers))
    try:
        for _ in range(cfg.repeats):
            for name, overrides in runs.items():
                rates[name].append(recipe_training(recipe, **overrides)(cfg.frames))
    finally:
        if started:
            import ray

            ray.shutdown()
    median = {name: statistics.median(r) for name, r in rates.items()}
    cost = costs(recipe, cfg.cost_segments, max(cfg.workers))

    # The model is Ray's (the backend that spreads over machines): its overhead is fitted
    # on one Ray worker and checked at the other counts.
    overhead = fitted_overhead(cost, median["1 Ray worker"], 1)
    checks = {}
    for n in cfg.workers:
        predicted, measured = model(cost, overhead, n), median[f"{n} Ray workers"]
        checks[f"{n} Ray workers"] = {"measured": measured, "predicted": predicted,
                                      "predicted_over_measured": predicted / measured}  # fmt: skip
    predictions = {str(n): model(cost, overhead, n) for n in [1, *cfg.predict]}
    speedups = {n: rate / predictions["1"] for n, rate in predictions.items()}
    ratios = {
        f"{n} Ray workers / {n} worker processes": median[f"{n} Ray workers"]
        / median[f"{n} worker processes"]
        for n in cfg.workers
    }
    print(table([[k, v] for k, v in median.items()], ["contender", "frames/s (median)"]))
    print()
    print(table([[k, v] for k, v in ratios.items()], ["ratio", "x"]))
    print()
    print(table([[k, v] for k, v in cost.items()], ["measured cost", "value"]))
    print()
    print(table([[k, v["measured"], v["predicted"]] for k, v in checks.items()],
                ["model check", "measured frames/s", "predicted"]))  # fmt: skip
    print()
    print(table([[f"{n} Ray workers", x] for n, x in speedups.items()],
                ["predicted speed-up over 1 Ray worker", "x"]))  # fmt: skip
    return write_json(
        cfg.json_path,
        cfg,
        frames_per_s=rates,
        median_frames_per_s=median,
        ratios=ratios,
        costs=cost,
        overhead_s_per_update=overhead,
        model_checks=checks,
        predicted_frames_per_s=predictions,
        predicted_speedup=speedups,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
