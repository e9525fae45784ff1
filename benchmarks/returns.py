"""How fast are rl_pg's return kernels on a collector-sized batch?

One run, one [B x T] batch with about 1% of steps done, every contender timed on the
same data with repetitions interleaved (so machine noise hits all alike), medians
reported, ratios against ``torch.cumsum`` of the same tensor (the memory-bound floor
of any scan) and against TorchRL's fastest equivalent.

    python benchmarks/returns.py [--batch 256] [--steps 1000] [--repeats 200]
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro
from common import REPO, write_json
from tensordict import TensorDict
from torchrl.objectives.value import TD1Estimator
from torchrl.objectives.value.functional import reward2go, vec_td1_return_estimate

from rl_pg import RewardToGo
from rl_pg.functional import discounted_return, reward_to_go


@dataclass
class Config:
    """Benchmark of the return kernels."""

    batch: int = 256
    """Rows (environments) of the batch."""
    steps: int = 1000
    """Time steps per row."""
    done_rate: float = 0.01
    """Fraction of steps that end an episode."""
    gamma: float = 0.99
    """Discount."""
    repeats: int = 200
    """Timed calls per contender (interleaved)."""
    json_path: Path = REPO / "benchmarks/results/returns.json"
    """Where the results are written."""


def make_contenders(cfg: Config) -> dict:
    generator = torch.Generator().manual_seed(0)
    shape = (cfg.batch, cfg.steps, 1)
    reward = torch.randn(shape, generator=generator)
    done = torch.rand(shape, generator=generator) < cfg.done_rate
    zeros = torch.zeros_like(reward)
    data = TensorDict(
        {
            "state_value": zeros,
            "next": {"reward": reward, "done": done, "terminated": done, "state_value": zeros},
        },
        batch_size=shape[:2],
    )
    ours = RewardToGo(gamma=cfg.gamma)
    theirs = TD1Estimator(gamma=cfg.gamma, value_network=None)

    # Everything below computes the same reward-to-go (checked in main); cumsum is the floor.
    return {
        "torch.cumsum (floor)": lambda: torch.cumsum(reward, dim=-2),
        "rl_pg reward_to_go": lambda: reward_to_go(reward, done, cfg.gamma),
        "rl_pg discounted_return": lambda: discounted_return(reward, done, cfg.gamma),
        "rl_pg RewardToGo (module)": lambda: ours(data)["value_target"],
        "torchrl reward2go": lambda: reward2go(reward, done, cfg.gamma),
        "torchrl vec_td1_return_estimate": lambda: vec_td1_return_estimate(
            cfg.gamma, zeros, reward, done, done
        ),
        "torchrl TD1Estimator (module)": lambda: theirs(data)["value_target"],
    }


def main(cfg: Config) -> dict:
    torch.manual_seed(0)
    contenders = make_contenders(cfg)
    reference = contenders["rl_pg reward_to_go"]()
    for name in ("torchrl reward2go", "torchrl vec_td1_return_estimate"):
        torch.testing.assert_close(
            contenders[name]().reshape(reference.shape), reference, rtol=1e-4, atol=1e-3
        )

    times = {name: [] for name in contenders}
    every = {}
    for name, fn in contenders.items():  # warm-up (numba compilation, allocator)
        fn()
        start = time.perf_counter()
        fn()
        # Contenders slower than 20 ms join one round in 20: 10 samples still give a
        # stable median, and the run stays short.
        every[name] = 20 if time.perf_counter() - start > 0.02 else 1
    for round_ in range(cfg.repeats):
        for name, fn in contenders.items():
            if round_ % every[name]:
                continue
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    median_ms = {name: 1e3 * statistics.median(t) for name, t in times.items()}

    floor = median_ms["torch.cumsum (floor)"]
    torchrl_best = min(v for k, v in median_ms.items() if k.startswith("torchrl"))
    print(f"[{cfg.batch} x {cfg.steps}] float32, {cfg.done_rate:.0%} done, {cfg.repeats} repeats")
    print(f"{'contender':34s} {'median ms':>10s} {'x cumsum':>9s}")
    for name, ms in median_ms.items():
        print(f"{name:34s} {ms:10.3f} {ms / floor:9.2f}")
    ours = median_ms["rl_pg reward_to_go"]
    print(f"\nreward_to_go vs torch.cumsum:            {ours / floor:.2f}x   (target <= 3)")
    print(f"TorchRL's fastest equivalent / ours:     {torchrl_best / ours:.1f}x  (target >= 20)")

    return write_json(
        cfg.json_path,
        cfg,
        median_ms=median_ms,
        reward_to_go_over_cumsum=ours / floor,
        torchrl_fastest_over_reward_to_go=torchrl_best / ours,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
