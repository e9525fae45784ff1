"""REINFORCE on CartPole-v1 with rl_pg's components, until greedy play is solved.

Reads top to bottom: config, seeding, environments, models, loss, optimiser, loop
(collect K whole episodes with the current policy -> reward-to-go -> ReinforceLoss
-> one Adam step), with a
greedy evaluation every ``eval_interval`` frames. Stops when the evaluation mean
reaches ``threshold`` (475, CartPole-v1's solve line) or after ``total_frames``.

    python recipes/cartpole.py --help
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass

import numpy as np
import torch
import tyro
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import EnvBase, GymEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator
from tqdm import tqdm

from rl_pg import ReinforceLoss


@dataclass
class Config:
    """REINFORCE with reward-to-go and a learned value baseline on CartPole-v1."""

    seed: int = 0
    """Seed of torch, numpy, random and the environments."""
    env_id: str = "CartPole-v1"
    """Gymnasium environment id."""
    total_frames: int = 300_000
    """Give up after this many environment steps."""
    episodes_per_batch: int = 8
    """Complete episodes collected for each update."""
    gamma: float = 0.99
    """Discount of the reward-to-go."""
    lr: float = 3e-3
    """Adam learning rate (actor and critic)."""
    hidden: int = 64
    """Width of the two hidden layers of the actor and of the critic."""
    max_grad_norm: float = 1.0
    """Gradient-norm clipping."""
    eval_interval: int = 10_000
    """Frames between greedy evaluations."""
    eval_episodes: int = 20
    """Episodes per greedy evaluation."""
    threshold: float = 475.0
    """Stop once the greedy evaluation mean return reaches this."""


def make_env(cfg: Config, seed: int) -> EnvBase:
    env = GymEnv(cfg.env_id, categorical_action_encoding=True)
    env.set_seed(seed)
    return env


def make_models(env: EnvBase, cfg: Config) -> tuple[ProbabilisticActor, ValueOperator]:
    n_obs = env.observation_spec["observation"].shape[-1]
    n_act = env.action_spec.space.n
    actor = ProbabilisticActor(
        TensorDictModule(
            MLP(n_obs, n_act, num_cells=[cfg.hidden, cfg.hidden], activation_class=nn.Tanh),
            in_keys=["observation"],
            out_keys=["logits"],
        ),
        in_keys=["logits"],
        spec=env.action_spec,
        distribution_class=torch.distributions.Categorical,
    )
    critic = ValueOperator(
        MLP(n_obs, 1, num_cells=[cfg.hidden, cfg.hidden], activation_class=nn.Tanh),
        in_keys=["observation"],
    )
    return actor, critic


def evaluate(actor: ProbabilisticActor, env: EnvBase, episodes: int) -> tuple[float, float]:
    """Mean and std of the return of ``episodes`` greedy (argmax) episodes."""
    returns = []
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in range(episodes):
            rollout = env.rollout(max_steps=100_000, policy=actor)
            returns.append(rollout["next", "reward"].sum().item())
    returns = torch.tensor(returns)
    return returns.mean().item(), returns.std().item()


def main(cfg: Config) -> dict:
    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    torch.manual_seed(cfg.seed)

    env, eval_env = make_env(cfg, cfg.seed), make_env(cfg, cfg.seed + 10_000)
    actor, critic = make_models(env, cfg)
    loss = ReinforceLoss(actor, critic, normalize_advantage=True, loss_critic_type="l2")
    loss.make_value_estimator("reward_to_go", gamma=cfg.gamma)
    optimizer = torch.optim.Adam(loss.parameters(), lr=cfg.lr)
    collector = Collector(
        env,
        actor,
        frames_per_batch=64,  # only the polling granularity with trajs_per_batch
        trajs_per_batch=cfg.episodes_per_batch,
        traj_format="cat",
        total_frames=cfg.total_frames,
        # The policy needs no extra transform (no recurrent state to initialise).
        auto_register_policy_transforms=False,
    )

    frames, next_eval, train_time = 0, cfg.eval_interval, 0.0
    result = {"solved_at_frames": None, "eval_mean_return": None, "eval_std_return": None}
    progress = tqdm(total=cfg.total_frames, unit="frames", disable=None)
    start = time.perf_counter()
    for batch in collector:
        losses = loss(batch)
        total = losses["loss_actor"] + losses["loss_value"]
        optimizer.zero_grad()
        total.backward()
        nn.utils.clip_grad_norm_(loss.parameters(), cfg.max_grad_norm)
        optimizer.step()
        # Strictly on-policy: drop the episode in flight, whose first steps came from
        # the policy before this update. Its frames still count as spent.
        collector.reset()

        frames = collector.state_dict()["frames"]
        train_return = batch["next", "reward"].sum().item() / cfg.episodes_per_batch
        progress.update(frames - progress.n)
        progress.set_postfix(train_return=f"{train_return:.1f}", refresh=False)
        if frames < next_eval:
            continue
        train_time += time.perf_counter() - start
        next_eval += cfg.eval_interval
        mean, std = evaluate(actor, eval_env, cfg.eval_episodes)
        result.update(eval_mean_return=mean, eval_std_return=std)
        progress.write(
            f"frames {frames:>7d}  train {train_return:6.1f}  eval {mean:6.1f} ± {std:.1f}"
        )
        start = time.perf_counter()
        if mean >= cfg.threshold:
            result["solved_at_frames"] = frames
            break
    collector.shutdown()
    progress.close()
    result.update(frames=frames, train_wall_s=train_time, threshold=cfg.threshold, seed=cfg.seed)
    return result


if __name__ == "__main__":
    print(main(tyro.cli(Config)))
