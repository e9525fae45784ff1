"""What does MetaDrive's map store cost and save: memory per road network kept, and the
time of a reset that builds a new road network against one that finds it built?

MetaDrive keeps every road network it has built (its ``store_map`` setting, on by
default), so that playing a scenario again skips building its map. A training worker
plays the recipe's 1 000 training scenarios at random, so its memory grows with each
new one. In one run, the two settings interleaved, each in a process of its own (one
MetaDrive engine per process): reset through ``scenarios`` consecutive training
scenarios (first visits), then through the same ones again (second visits), timing
each reset and reading the process's resident memory after it.

    python benchmarks/metadrive_maps.py
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import psutil
import tyro
from common import REPO, table, write_json

from rl_pg.envs import metadrive as md

MB = 2**20
TRAINING = "MetaDrive-validation-v0"  # the recipe's training scenarios


@dataclass
class Config:
    """MetaDrive's map store: memory per road network, and resets with and without it."""

    scenarios: int = 40
    """Consecutive training scenarios each setting resets through, twice."""
    repeats: int = 2
    """Interleaved repetitions per setting (medians over them are reported)."""
    json_path: Path = REPO / "benchmarks/results/metadrive_maps.json"
    """Where the results are written."""


def resets(store_map: bool, scenarios: int) -> dict[str, list[float]]:
    """In this process: the seconds of each reset and the resident memory (MB) after
    it, through ``scenarios`` training scenarios and then through them again."""
    (first,) = md.split_scenarios(TRAINING, 1, count=scenarios)
    env = md.metadrive_env(
        TRAINING, order="sequential", scenarios=first, config={"store_map": store_map}
    )
    process = psutil.Process()
    seconds, memory = [], []
    try:
        for _ in range(2 * scenarios):
            begin = time.perf_counter()
            env.reset()
            seconds.append(time.perf_counter() - begin)
            memory.append(process.memory_info().rss / MB)
    finally:
        env.close()
    return {"seconds": seconds, "memory_mb": memory}


def summary(run: dict[str, list[float]], scenarios: int) -> dict[str, float]:
    """Median reset times of first and second visits (the very first reset, which
    starts the engine, left out) and memory grown per first visit."""
    seconds, memory = run["seconds"], run["memory_mb"]
    return {
        "first_visit_reset_ms": 1000 * statistics.median(seconds[1:scenarios]),
        "second_visit_reset_ms": 1000 * statistics.median(seconds[scenarios:]),
        "mb_per_new_scenario": (memory[scenarios - 1] - memory[0]) / (scenarios - 1),
        "mb_during_second_visits": memory[-1] - memory[scenarios - 1],
    }


def main(cfg: Config) -> dict:
    training = md.SCENARIO_SETS[TRAINING][1]
    if not 3 <= cfg.scenarios <= training:
        raise SystemExit(
            f"--scenarios {cfg.scenarios}: at least 3 are needed to measure, and the "
            f"training set has {training}."
        )
    if cfg.repeats < 1:
        raise SystemExit(f"--repeats {cfg.repeats}: at least one repetition is needed.")
    # A process of its own, and a fresh engine, per measurement (memory is compared
    # within it), forked from a server that imported MetaDrive and rl_pg once.
    context = mp.get_context("forkserver")
    context.set_forkserver_preload(["rl_pg.envs.metadrive"])
    runs: dict[str, list[dict[str, float]]] = {"store_map": [], "no store_map": []}
    with context.Pool(1, maxtasksperchild=1) as pool:
        for _ in range(cfg.repeats):
            for name, store in (("store_map", True), ("no store_map", False)):
                run = pool.apply(resets, (store, cfg.scenarios))
                runs[name].append(summary(run, cfg.scenarios))
    results = {
        name: {key: statistics.median(r[key] for r in measured) for key in measured[0]}
        for name, measured in runs.items()
    }
    kept = results["store_map"]
    gigabytes = kept["mb_per_new_scenario"] * training / 1024
    columns = list(kept)
    print(table([[name, *[r[c] for c in columns]] for name, r in results.items()], ["", *columns]))
    speedup = results["no store_map"]["second_visit_reset_ms"] / kept["second_visit_reset_ms"]
    print(f"a second visit resets {speedup:.1f}x faster with the map stored")
    print(f"the {training} training scenarios' maps: {gigabytes:.1f} GB")
    return write_json(
        cfg.json_path,
        cfg,
        results=results,
        runs=runs,
        training_scenarios=training,
        gb_for_the_training_scenarios=gigabytes,
        second_visit_speedup=speedup,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
