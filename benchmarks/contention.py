"""How much does a busy machine slow rl_pg's training loop, next to the plain floor?

Users share machines (laptops, cluster nodes). On an idle machine and beside ``--busy``
processes that each spin one core, in one run, repetitions interleaved:

* rl_pg's training loop: the ``cartpole`` recipe with its defaults for ``--frames``
  frames (collection, returns, loss, optimiser step; evaluation excluded);
* the same loop with the return kernel on every numba thread whatever the batch (how
  rl_pg ran before the kernel chose its threads), for comparison;
* the floor: plain gymnasium ``SyncVectorEnv`` with as many CartPoles as the recipe,
  stepped by the same MLP policy (no learning, no TensorDict).

Each contender's slowdown is its median time when busy over its median time when
idle; the figure of merit is rl_pg's slowdown over the floor's (target <= 1.3: the loop
degrades about as gracefully as the environment does).

    python benchmarks/contention.py
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numba
import torch
import tyro
from common import REPO, table, write_json
from throughput import cartpole, cartpole_floor, recipe_training

from rl_pg import _scan

rl_pg_training = recipe_training(cartpole)


@dataclass
class Config:
    """CartPole training vs the plain vector-env floor, idle and beside busy processes."""

    frames: int = 60_000
    """Frames per repetition of each contender."""
    busy: int = 2
    """Processes spinning a core each during the busy repetitions."""
    repeats: int = 3
    """Interleaved repetitions per contender and condition (the median is reported)."""
    threads: int = 1
    """torch threads for every contender (the recipe's default)."""
    json_path: Path = REPO / "benchmarks/results/contention.json"
    """Where the results are written."""


@contextmanager
def busy_processes(n: int) -> Iterator[None]:
    """``n`` processes that each keep a core busy until the block ends."""
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        time.sleep(0.5)  # let the scheduler see them
        yield
    finally:
        for spinner in spinners:
            spinner.kill()
            spinner.wait()


def rl_pg_training_all_kernel_threads(frames: int) -> float:
    """The training loop with the return kernel spread over every numba thread."""
    chosen = _scan.kernel_threads
    _scan.kernel_threads = lambda n_rows, n_steps: numba.config.NUMBA_NUM_THREADS
    try:
        return rl_pg_training(frames)
    finally:
        _scan.kernel_threads = chosen


def seconds(rate_of: Callable[[int], float], frames: int) -> float:
    """Wall-clock seconds for ``frames`` frames, from a contender that reports frames/s."""
    return frames / rate_of(frames)


def main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    n_envs = cartpole.config().num_envs
    floor_name = f"floor: SyncVectorEnv({n_envs}) + MLP"
    contenders = {
        "rl_pg training loop (recipe)": rl_pg_training,
        "rl_pg, kernel on every numba thread (before)": rl_pg_training_all_kernel_threads,
        floor_name: cartpole_floor(n_envs, "gymnasium"),
    }
    for run in contenders.values():  # compile and warm everything up, untimed
        run(min(cfg.frames, 2_048))
    times: dict[str, dict[str, list[float]]] = {
        name: {"idle": [], "busy": []} for name in contenders
    }
    load = {"idle": [], "busy": []}
    for _ in range(cfg.repeats):
        for condition in ("idle", "busy"):
            with busy_processes(cfg.busy if condition == "busy" else 0):
                for name, run in contenders.items():
                    times[name][condition].append(seconds(run, cfg.frames))
                load[condition].append(os.getloadavg()[0])
    median = {
        name: {c: statistics.median(t) for c, t in by_condition.items()}
        for name, by_condition in times.items()
    }
    slowdown = {name: m["busy"] / m["idle"] for name, m in median.items()}
    over_floor = {name: value / slowdown[floor_name] for name, value in slowdown.items()}
    rows = [
        [name, m["idle"], m["busy"], slowdown[name], over_floor[name]] for name, m in median.items()
    ]
    header = ["contender", "idle s (median)", f"{cfg.busy} busy s", "slowdown", "/ floor's"]
    print(table(rows, header))
    ours = over_floor["rl_pg training loop (recipe)"]
    print(f"\nrl_pg slowdown / floor slowdown: {ours:.2f}x  (target <= 1.3)")
    print(
        f"load average (1 min) after the idle / busy blocks: "
        f"{statistics.median(load['idle']):.2f} / {statistics.median(load['busy']):.2f}"
    )
    return write_json(
        cfg.json_path,
        cfg,
        kernel_parallel_min_elements=_scan.PARALLEL_MIN_ELEMENTS,
        seconds=times,
        median_seconds=median,
        slowdown=slowdown,
        slowdown_over_floor=over_floor,
        rl_pg_slowdown_over_floor=ours,
        load_average=load,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
