"""How many CartPole-v1 frames per second does each way of training (or just stepping) take?

One run, every contender timed in turn, repetitions interleaved (so machine noise hits
all alike), medians of frames/s reported with ratios:

* rl_pg's training loop: the ``cartpole`` recipe with its defaults (collection,
  returns, loss, optimiser step; evaluation excluded), frames / training wall-clock.
* TorchRL's stock ``Collector(GymEnv("CartPole-v1"))`` and
  ``Collector(GymEnv("CartPole-v1", num_envs=8))``, collection only, same MLP policy.
* Stable-Baselines3 A2C's training loop (8 environments, its defaults).
* The floor: plain gymnasium ``SyncVectorEnv`` stepped by the same MLP policy (sampled
  actions, no learning, no TensorDict), with 8 environments (the set-up users compare
  with) and with as many environments as the recipe uses.

    pip install -c constraints.txt -e ".[bench]"
    python benchmarks/throughput.py
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import torch
import tyro
from common import REPO, table, write_json
from torchrl.collectors import Collector
from torchrl.envs import GymEnv

from rl_pg.recipes import load

cartpole = load("cartpole")


@dataclass
class Config:
    """CartPole-v1 frames/s: rl_pg's loop vs TorchRL's stock collectors, SB3 A2C, raw gym."""

    seconds: float = 3.0
    """Target duration of one repetition of one contender."""
    repeats: int = 3
    """Interleaved repetitions per contender (the median is reported)."""
    probe_frames: int = 2_000
    """Frames of the first, untimed-for-the-result run that sizes each repetition."""
    threads: int = 1
    """torch threads for every contender."""
    json_path: Path = REPO / "benchmarks/results/throughput.json"
    """Where the results are written."""


def recipe_actor():
    """The recipe's MLP policy (same architecture for every contender that needs one)."""
    recipe = cartpole.config()
    return cartpole.make_models(cartpole.make_env(recipe), recipe)[0]


def rl_pg_training(frames: int) -> float:
    with tempfile.TemporaryDirectory() as run_dir:
        summary = cartpole.train(
            cartpole.config(
                run_dir=Path(run_dir),
                total_frames=frames,
                threshold=None,
                eval_interval=10**12,  # one evaluation, at the end, outside the timer
                eval_episodes=1,
                checkpoint_interval=10**12,
                progress=False,
            )
        )
    return summary["frames"] / summary["train_wall_s"]


def torchrl_collector(num_envs: int | None) -> Callable[[int], float]:
    def run(frames: int) -> float:
        kwargs = {} if num_envs is None else {"num_envs": num_envs}
        env = GymEnv("CartPole-v1", categorical_action_encoding=True, **kwargs)
        batch = 200 * (num_envs or 1)
        collector = Collector(
            env,
            recipe_actor(),
            frames_per_batch=batch,
            total_frames=-1,
            auto_register_policy_transforms=False,
        )
        iterator = iter(collector)
        next(iterator)  # start-up outside the timer
        start, done = time.perf_counter(), 0
        while done < frames:
            done += next(iterator).numel()
        rate = done / (time.perf_counter() - start)
        collector.shutdown()
        return rate

    return run


def sb3_a2c(frames: int) -> float:
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    model = A2C("MlpPolicy", make_vec_env("CartPole-v1", n_envs=8, seed=0), seed=0, device="cpu")
    start = time.perf_counter()
    model.learn(total_timesteps=frames)
    return model.num_timesteps / (time.perf_counter() - start)


def gym_floor(num_envs: int) -> Callable[[int], float]:
    def run(frames: int) -> float:
        envs = gym.make_vec("CartPole-v1", num_envs=num_envs, vectorization_mode="sync")
        net = recipe_actor().module[0].module  # the policy's plain nn.Module (logits)
        obs, _ = envs.reset(seed=0)
        steps = max(1, frames // num_envs)
        start = time.perf_counter()
        with torch.inference_mode():
            for _ in range(steps):
                logits = net(torch.as_tensor(obs))
                action = torch.distributions.Categorical(logits=logits).sample()
                obs, *_ = envs.step(action.numpy())
        return steps * num_envs / (time.perf_counter() - start)

    return run


def main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    n = cartpole.config().num_envs
    contenders: dict[str, Callable[[int], float]] = {
        "rl_pg training loop (recipe)": rl_pg_training,
        "TorchRL Collector(GymEnv), collection only": torchrl_collector(None),
        "TorchRL Collector(GymEnv(num_envs=8)), collection only": torchrl_collector(8),
        "SB3 A2C training loop (8 envs)": sb3_a2c,
        "floor: SyncVectorEnv(8) + MLP, no learning": gym_floor(8),
        f"floor: SyncVectorEnv({n}) + MLP, no learning": gym_floor(n),
    }
    # Size each contender's repetition to about cfg.seconds from a short probe.
    frames = {}
    for name, run in contenders.items():
        frames[name] = max(cfg.probe_frames, int(run(cfg.probe_frames) * cfg.seconds))
    rates: dict[str, list[float]] = {name: [] for name in contenders}
    for _ in range(cfg.repeats):
        for name, run in contenders.items():
            rates[name].append(run(frames[name]))
    median = {name: statistics.median(r) for name, r in rates.items()}

    ours = median["rl_pg training loop (recipe)"]
    floor8 = median["floor: SyncVectorEnv(8) + MLP, no learning"]
    stock = median["TorchRL Collector(GymEnv), collection only"]
    rows = [[name, rate, ours / rate] for name, rate in median.items()]
    print(table(rows, ["contender", "frames/s (median)", "rl_pg loop / this"]))
    print(f"\nrl_pg loop / SyncVectorEnv(8) floor: {ours / floor8:.2f}x  (target >= 0.9)")
    print(f"rl_pg loop / TorchRL stock Collector: {ours / stock:.1f}x  (target >= 10)")
    return write_json(
        cfg.json_path,
        cfg,
        frames_per_repeat=frames,
        frames_per_s=rates,
        median_frames_per_s=median,
        rl_pg_over_floor8=ours / floor8,
        rl_pg_over_stock_collector=ours / stock,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
