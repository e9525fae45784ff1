"""How many steps per second do the torch-native environments take, by batch size?

rl_pg's ``GridWorldEnv`` and ``BanditEnv`` step a whole batch with a few tensor
operations. Against them: the same gridworld written the way gymnasium environments
usually are (a Python ``gymnasium.Env`` stepping one copy), alone and batched by
gymnasium's ``SyncVectorEnv``. Every contender takes uniformly random actions and is
reset when an episode ends; our envs are driven through TorchRL's
``env.step_and_maybe_reset`` (what a collector calls at every step, without storing the
trajectory), so TorchRL's per-step overhead is included. Batch sizes
and contenders are interleaved within each repetition; medians are reported.

    python benchmarks/envs.py [--batch-sizes 1 16 256 4096 65536]
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import tyro
from common import REPO, table, write_json
from torchrl.envs import EnvBase

from rl_pg.envs import BanditEnv, GridWorldEnv


@dataclass
class Config:
    """Steps/s of the torch-native bandit and gridworld vs a Python gymnasium gridworld."""

    batch_sizes: list[int] = field(default_factory=lambda: [1, 16, 256, 4096, 65536])
    """Batch sizes of the batched environments."""
    python_max_batch: int = 4096
    """Largest batch given to the Python gridworld (it scales linearly; larger is slow)."""
    seconds: float = 1.0
    """Target duration of one measurement."""
    repeats: int = 3
    """Interleaved repetitions (the median is reported)."""
    threads: int = 1
    """torch threads."""
    json_path: Path = REPO / "benchmarks/results/envs.json"
    """Where the results are written."""


class PythonGridWorld(gym.Env):
    """The 4x4 gridworld, one copy, the way gymnasium environments are written."""

    MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1))

    def __init__(self, max_steps: int = 100) -> None:
        self.observation_space = gym.spaces.Box(0.0, 1.0, (16,), np.float32)
        self.action_space = gym.spaces.Discrete(4)
        self.max_steps = max_steps
        self.start, self.goal, self.pit = (3, 0), (0, 3), (1, 2)

    def _obs(self) -> np.ndarray:
        obs = np.zeros(16, np.float32)
        obs[self.cell[0] * 4 + self.cell[1]] = 1.0
        return obs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.cell, self.steps = self.start, 0
        return self._obs(), {}

    def step(self, action):
        dr, dc = self.MOVES[int(action)]
        self.cell = (min(max(self.cell[0] + dr, 0), 3), min(max(self.cell[1] + dc, 0), 3))
        self.steps += 1
        terminated = self.cell in (self.goal, self.pit)
        reward = 1.0 if self.cell == self.goal else -1.0 if self.cell == self.pit else -0.1
        return self._obs(), reward, terminated, self.steps >= self.max_steps, {}


def torch_native(make: Callable[[int], EnvBase]) -> Callable[[int, float], float]:
    def run(batch: int, seconds: float) -> float:
        env = make(batch)
        env.set_seed(0)
        actions = env.full_action_spec
        tensordict = env.reset()
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            for _ in range(10):
                tensordict.update(actions.rand())
                _, tensordict = env.step_and_maybe_reset(tensordict)
            steps += 10
        return steps * batch / (time.perf_counter() - start)

    return run


def python_gridworld(batch: int, seconds: float) -> float:
    rng = np.random.default_rng(0)
    if batch == 1:
        env = PythonGridWorld()
        env.reset(seed=0)
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            for _ in range(1000):
                _, _, terminated, truncated, _ = env.step(rng.integers(4))
                if terminated or truncated:
                    env.reset()
            steps += 1000
        return steps / (time.perf_counter() - start)
    envs = gym.vector.SyncVectorEnv([PythonGridWorld] * batch)  # auto-resets finished copies
    envs.reset(seed=0)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        envs.step(rng.integers(4, size=batch))
        steps += 1
    return steps * batch / (time.perf_counter() - start)


def main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    contenders = {
        "rl_pg GridWorldEnv": torch_native(lambda b: GridWorldEnv(batch_size=b)),
        "rl_pg BanditEnv": torch_native(lambda b: BanditEnv(batch_size=b)),
        "Python gridworld (gymnasium.Env, SyncVectorEnv)": python_gridworld,
    }
    rates: dict[str, dict[int, list[float]]] = {
        n: {b: [] for b in cfg.batch_sizes} for n in contenders
    }
    for _ in range(cfg.repeats):
        for batch in cfg.batch_sizes:
            for name, run in contenders.items():
                if name.startswith("Python") and batch > cfg.python_max_batch:
                    continue
                rates[name][batch].append(run(batch, cfg.seconds))
    median = {
        name: {b: statistics.median(r) if r else None for b, r in by_batch.items()}
        for name, by_batch in rates.items()
    }
    python_best = max(
        v for v in median["Python gridworld (gymnasium.Env, SyncVectorEnv)"].values() if v
    )
    rows = [[name, *(median[name][b] for b in cfg.batch_sizes)] for name in contenders]
    print("steps per second (median), by batch size")
    print(table(rows, ["contender", *map(str, cfg.batch_sizes)]))
    largest = max(cfg.batch_sizes)
    grid = median["rl_pg GridWorldEnv"][largest]
    print(
        f"\nGridWorldEnv at batch {largest}: {grid / 1e6:.1f}M steps/s (target >= 5M); "
        f"{grid / python_best:.0f}x the Python gridworld's best"
    )
    return write_json(
        cfg.json_path,
        cfg,
        steps_per_s=rates,
        median_steps_per_s=median,
        gridworld_largest_batch_steps_per_s=grid,
        gridworld_over_python_best=grid / python_best,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
