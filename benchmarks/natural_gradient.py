"""What a natural-gradient update costs beside an Adam update, on LunarLander.

The LunarLander recipe's networks (two hidden layers of 128, actor and critic) and
batches (8 landers, 64-step segments), the same batches for every contender:

- ``adam``: the recipe's update (``rl_pg.training.optimisation.update``: the loss,
  one backward pass, the gradient clip, Adam's step on both networks);
- ``natural``: ``NaturalGradient.step`` (10 conjugate-gradient iterations, the line
  search) and the critic's own Adam step on ``loss.value_loss``, on the critic's
  values of the returns' pass (one critic call per batch, as in the Adam update);
- ``natural, Fisher on 1/4``: the same with ``fisher_fraction=0.25``;
- ``natural, K-FAC``: the Kronecker-factored Fisher inverted in closed form
  (``fisher="kfac"``) in place of the conjugate-gradient solve, with the line search;
- ``natural, K-FAC, no line search``: the same, taking the full step.

Each round times every contender over the batches, from the same starting weights,
in a rotating order; the medians of the rounds' per-update times are compared, with a
bootstrap interval of the ratio (rounds resampled whole). Target: a natural update at
most 2x an Adam update.

    python benchmarks/natural_gradient.py
"""

from __future__ import annotations

import copy
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro
from common import REPO, ratio_interval, table, write_json

from rl_pg.collectors import SegmentCollector
from rl_pg.envs import gym_env
from rl_pg.models import mlp_actor_critic
from rl_pg.natural_gradient import NaturalGradient
from rl_pg.recipes import load
from rl_pg.training.optimisation import make_loss, make_optimizer, update


@dataclass
class Config:
    """A natural-gradient update's time over an Adam update's, LunarLander."""

    batches: int = 20
    """Batches (of 8 x 64 steps) each contender updates on, per round."""
    repeats: int = 7
    """Rounds (medians of the per-update times are compared)."""
    threads: int = 1
    """torch threads (the recipes' default)."""
    json_path: Path = REPO / "benchmarks" / "results" / "natural_gradient.json"
    """Where the results go."""


CONTENDERS = {
    "adam": None,
    "natural": {},
    "natural, Fisher on 1/4": {"fisher_fraction": 0.25},
    "natural, K-FAC": {"fisher": "kfac"},
    "natural, K-FAC, no line search": {"fisher": "kfac", "line_search": False},
    "natural, K-FAC on 1/4": {"fisher": "kfac", "fisher_fraction": 0.25},
}


def _updater(cfg, actor, critic, natural: dict | None):
    """A fresh copy of the networks and the update of one contender on them."""
    actor, critic = copy.deepcopy(actor), copy.deepcopy(critic)
    loss = make_loss(cfg, actor, critic)
    if natural is None:
        optimizer = make_optimizer(cfg, loss)
        return lambda batch: update(cfg, loss, optimizer, batch, lr=cfg.lr)
    step = NaturalGradient(loss, **natural)
    critic_params = list(critic.parameters())
    optimizer = torch.optim.Adam(critic_params, lr=cfg.lr)

    def natural_update(batch):
        weights, valid, value = loss.policy_weights(batch, keep_value=True)
        step.step(batch, weights, valid)
        optimizer.zero_grad(set_to_none=True)
        loss.value_loss(batch, value=value).backward()
        torch.nn.utils.clip_grad_norm_(critic_params, cfg.max_grad_norm)
        optimizer.step()

    return natural_update


def main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    recipe = load("lunarlander").config(progress=False)
    torch.manual_seed(0)
    env = gym_env("LunarLander-v3", num_envs=recipe.num_envs)
    env.set_seed(0)
    actor, critic = mlp_actor_critic(env, hidden=(recipe.hidden, recipe.hidden))
    collector = SegmentCollector(env, actor, frames_per_batch=recipe.num_envs * 64)
    batches = [collector.next() for _ in range(cfg.batches)]
    collector.shutdown()
    times: dict[str, list[float]] = {name: [] for name in CONTENDERS}
    names = list(CONTENDERS)
    for round_ in range(cfg.repeats):
        for name in names[round_ % len(names) :] + names[: round_ % len(names)]:
            run = _updater(recipe, actor, critic, CONTENDERS[name])
            run(batches[0].clone())  # first-call set-up (numba's kernels, allocations)
            copies = [batch.clone() for batch in batches]
            start = time.perf_counter()
            for batch in copies:
                run(batch)
            times[name].append((time.perf_counter() - start) / len(copies))
    median = {name: statistics.median(t) for name, t in times.items()}
    over_adam = {name: median[name] / median["adam"] for name in names[1:]}
    intervals = {name: ratio_interval(times[name], times["adam"]) for name in names[1:]}
    rows = [
        [name, median[name] * 1e3, over_adam.get(name), *(intervals.get(name) or [None, None])]
        for name in names
    ]
    print(table(rows, ["update", "ms (median)", "/ adam", "90% low", "90% high"]))
    return write_json(
        cfg.json_path,
        cfg,
        ms_per_update={name: t * 1e3 for name, t in median.items()},
        over_adam=over_adam,
        over_adam_intervals=intervals,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
