"""Where the time of one update goes: rl_pg's loop piece by piece, beside the same
algorithm written in plain PyTorch, in one process.

For each task (a recipe at its number of environments), both contenders collect a
segment of the recipe's length from their own environments and make one update on it,
round after round, alternating; each piece is timed per update:

* collection: the policy (building its input and sampling), the environments (the
  vector environment's step, the resets of finished environments, the step's tensors),
  and building the batch from the steps;
* update: the loss's forward pass (returns, critic values, log-probabilities, checks,
  diagnostics), timed by hooks around its call inside
  ``rl_pg.training.optimisation.update``, and the rest of that call (backward, gradient
  clip, optimiser step, metrics, observation statistics);
* the loop's bookkeeping: the training episodes' returns and the CSV logger's rows.

After each update the loss's forward pass is run and timed once more, at once, on the
same batch: the same work with its code and data still in the caches, beside what it
costs inside the loop.

The environments' piece is also split (not in the total): the vector environment's own
step (gymnasium's ``SyncVectorEnv.step``; the plain loop's resets its finished
environments inside it), rl_pg's resets of finished environments made apart from the
step, and the rest (numpy to tensors, done flags), each call timed by a wrapper that
adds well under a microsecond to it. With the episodes ended per update:
how often the environments reset depends on each loop's policy, and a reset can cost
more than a step (a LunarLander builds its terrain and bodies).

rl_pg's collection is ``rl_pg.collectors.SegmentCollector``'s own steps (its lean path,
the one the recipes take), timed between its calls. The plain contender is
``throughput.py``'s plain-PyTorch loop cut into the same pieces: gymnasium's vector env
resetting finished environments inside its step, ``Categorical(logits=...).sample()``,
the same networks, reward-to-go bootstrapped from the critic and fused Adam. Medians
over rounds; the ratio of the totals is the one ``throughput.py`` measures end to end,
without its start-up and logging.

    python benchmarks/breakdown.py
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tyro
from common import REPO, table, write_json
from tensordict import TensorDictBase
from throughput import PlainLoop
from torchrl.envs.utils import set_exploration_type

from rl_pg.collectors import SegmentCollector
from rl_pg.envs import VectorGymEnv
from rl_pg.lean import LeanCategoricalPolicy, lean_policy
from rl_pg.recipes import load
from rl_pg.segments import cleared_flags, observations_of, segment_of
from rl_pg.training.loggers import BufferedCSVLogger
from rl_pg.training.metrics import EpisodeReturns
from rl_pg.training.optimisation import make_loss, make_optimizer, update, warm_up


@dataclass
class Config:
    """Per-update cost of each piece of rl_pg's loop and of a plain-PyTorch loop."""

    tasks: list[str] = field(default_factory=lambda: ["cartpole:32", "lunarlander:8"])
    """Recipes and their numbers of environments, RECIPE:N."""
    rounds: int = 7
    """Rounds, each timing both contenders in turn (medians over rounds)."""
    updates: int = 60
    """Updates per contender per round."""
    json_path: Path = REPO / "benchmarks" / "results" / "breakdown.json"
    """Where the results are written."""


PIECES = (
    "collection: policy",
    "collection: environments",
    "collection: building the batch",
    "update: loss forward",
    "update: backward, clip, optimiser step, metrics",
    "loop: episode returns and logging",
)
# Not a piece of the loop: the loss's forward pass run again right after the update.
REPEATED = "loss forward, repeated at once"
# The environments' piece split (its parts are in it already, so not in the total).
ENV_PARTS = (
    "the vector env's step",
    "resets apart from the step",
    "around them (tensors, flags)",
)
EPISODES = "episodes ended"


class _Timer:
    """Sums nanoseconds per piece; ``per_update`` gives microseconds per update."""

    def __init__(self) -> None:
        self.ns: dict[str, int] = defaultdict(int)

    def add(self, piece: str, start: int) -> int:
        now = time.perf_counter_ns()
        self.ns[piece] += now - start
        return now

    def per_update(self, updates: int) -> dict[str, float]:
        return {
            piece: self.ns[piece] / updates / 1000
            for piece in (*PIECES, REPEATED, *ENV_PARTS)
            if piece in self.ns
        }


def _timed_calls(owner, name: str, timers: list, piece: str) -> None:
    """Times every call of ``owner.name`` into ``timers[0]`` (the current round's
    timer) under ``piece``, by an attribute of ``owner`` that shadows the method."""
    method = getattr(owner, name)

    def timed(*args):
        start = time.perf_counter_ns()
        try:
            return method(*args)
        finally:
            timers[0].ns[piece] += time.perf_counter_ns() - start

    setattr(owner, name, timed)


def _split_environments(times: dict[str, float], episodes: int, updates: int) -> None:
    """Adds to ``times`` the environments' piece less the two parts timed inside it,
    and the episodes ended per update."""
    inside = times.get(ENV_PARTS[0], 0.0) + times.get(ENV_PARTS[1], 0.0)
    times[ENV_PARTS[2]] = times["collection: environments"] - inside
    times[EPISODES] = episodes / updates


def timed_segment(collector: SegmentCollector, timer: _Timer) -> TensorDictBase:
    """``collector.next()`` on its lean path, step for step (the same batch, and the
    collector carries on from it), with the policy's and the environments' time and
    the batch's building timed apart."""
    env = collector.env
    if collector._observations is None:
        collector._observations = observations_of(env, env.reset())
    observations, roots, nexts = collector._observations, [], []
    clear = cleared_flags(env.batch_size, env.device)
    with torch.no_grad(), set_exploration_type(collector.exploration_type):
        for _ in range(collector.frames_per_batch // env.batch_size.numel()):
            t = time.perf_counter_ns()
            root = collector._policy_at(observations, clear, env.batch_size)
            action = collector._action(root)
            t = timer.add("collection: policy", t)
            next_step, observations = env.step_tensors(action)
            timer.add("collection: environments", t)
            roots.append(root)
            nexts.append(next_step)
        t = time.perf_counter_ns()
        batch = segment_of(roots, nexts, env.batch_size, env.device)
        timer.add("collection: building the batch", t)
    collector._observations = observations
    collector._frames += collector.frames_per_batch
    return batch


def rl_pg_contender(recipe, n: int, log_dir: Path) -> Callable[[int], dict[str, float]]:
    """rl_pg's loop on the recipe: its environments, lean policy, loss, optimiser."""
    cfg = recipe.config(num_envs=n, progress=False)
    env = recipe.make_env(cfg)
    actor, critic = recipe.make_models(env, cfg)
    loss = make_loss(cfg, actor, critic)
    warm_up(loss, env, torch.device("cpu"))
    optimizer = make_optimizer(cfg, loss)
    collector = SegmentCollector(env, lean_policy(actor), frames_per_batch=n * cfg.segment_length)
    if not collector._lean:
        raise ValueError(f"{recipe.name}: its environment has no lean step to time.")
    # The loss's forward pass, timed inside the update by hooks around its call.
    clock = {"start": 0, "forward": 0}
    loss.register_forward_pre_hook(lambda *_: clock.update(start=time.perf_counter_ns()))
    loss.register_forward_hook(
        lambda *_: clock.update(forward=time.perf_counter_ns() - clock["start"])
    )
    episodes = EpisodeReturns(carry=True)
    logger = BufferedCSVLogger(exp_name="csv", log_dir=str(log_dir))  # as the loop logs
    keys = loss.tensor_keys
    estimated = [keys.advantage, keys.value_target, keys.value, ("next", keys.value)]
    timers = [_Timer()]
    _timed_calls(env, "_env_step", timers, ENV_PARTS[0])
    _timed_calls(env, "_env_reset_some", timers, ENV_PARTS[1])

    def run(updates: int) -> dict[str, float]:
        timer = timers[0] = _Timer()
        ended = 0
        for step in range(updates):
            batch = timed_segment(collector, timer)
            ended += int(batch.get(("next", "done")).sum())
            t = time.perf_counter_ns()
            metrics = update(cfg, loss, optimizer, batch, lr=cfg.lr)
            whole, forward = time.perf_counter_ns() - t, clock["forward"]
            timer.ns["update: loss forward"] += forward
            timer.ns["update: backward, clip, optimiser step, metrics"] += whole - forward
            t = time.perf_counter_ns()
            episodes.add(batch)
            metrics["train/episode_return"] = episodes.pop_mean()
            for name, value in metrics.items():
                logger.log_scalar(name, value, step=step)
            t = timer.add("loop: episode returns and logging", t)
            # The same forward pass again at once (what the estimator wrote removed, so
            # that it estimates again): the piece with its code and data already cached.
            loss(batch.exclude(*estimated))
            timer.add(REPEATED, t)
        times = timer.per_update(updates)
        _split_environments(times, ended, updates)
        return times

    return run


def plain_contender(recipe, n: int) -> Callable[[int], dict[str, float]]:
    """``throughput.py``'s plain-PyTorch loop, its pieces timed apart."""
    plain = PlainLoop(recipe, n)
    timers = [_Timer()]
    _timed_calls(plain.envs, "step", timers, ENV_PARTS[0])  # resets inside it

    def run(updates: int) -> dict[str, float]:
        timer = timers[0] = _Timer()
        ended = 0
        for _ in range(updates):
            segment = []
            for _ in range(plain.cfg.segment_length):
                t = time.perf_counter_ns()
                acted = plain.act()
                t = timer.add("collection: policy", t)
                segment.append(plain.step(*acted))
                timer.add("collection: environments", t)
                ended += int(segment[-1][-1].sum())
            t = time.perf_counter_ns()
            batch = plain.batch(segment)
            t = timer.add("collection: building the batch", t)
            loss = plain.loss(*batch)
            t = timer.add("update: loss forward", t)
            plain.optimise(loss)
            t = timer.add("update: backward, clip, optimiser step, metrics", t)
            plain.loss(*batch)
            timer.add(REPEATED, t)
        times = timer.per_update(updates)
        _split_environments(times, ended, updates)
        return times

    return run


def _task(task: str):
    """The recipe and number of environments of ``RECIPE:N``, or a clear error."""
    name, _, n = task.partition(":")
    if not n.isdigit() or int(n) < 1:
        raise ValueError(f"--tasks takes RECIPE:N (N environments, N >= 1), got {task!r}.")
    recipe = load(name)
    cfg = recipe.config(num_envs=int(n), progress=False)
    env = recipe.make_env(cfg)
    actor, _ = recipe.make_models(env, cfg)
    env.close()
    if type(env) is not VectorGymEnv or not LeanCategoricalPolicy.supports(actor):
        raise ValueError(
            f"{name}: the breakdown times recipes with a categorical policy over gymnasium's "
            f"vector environments, as the plain loop it compares with (cartpole, "
            f"lunarlander); this one's policy or environments are of another kind."
        )
    return recipe, int(n)


def main(cfg: Config) -> dict:
    torch.set_num_threads(1)
    results = {}
    with tempfile.TemporaryDirectory() as log_dir:
        for task in cfg.tasks:
            recipe, n = _task(task)
            label = f"{recipe.name}-x{n}"  # a JSON pointer without spaces
            contenders = {
                "rl_pg": rl_pg_contender(recipe, n, Path(log_dir) / label),
                "plain PyTorch": plain_contender(recipe, n),
            }
            for run in contenders.values():  # warm-up: first calls, caches
                run(max(1, cfg.updates // 4))
            rounds = defaultdict(list)
            for _ in range(cfg.rounds):
                for who, run in contenders.items():
                    rounds[who].append(run(cfg.updates))
            parts = {
                piece: {
                    who: (
                        statistics.median(r[piece] for r in rounds[who])
                        if piece in rounds[who][0]
                        else 0.0
                    )
                    for who in contenders
                }
                for piece in PIECES
            }
            totals = {who: sum(p[who] for p in parts.values()) for who in contenders}
            parts["total"] = totals
            repeated = {
                who: statistics.median(r[REPEATED] for r in rounds[who]) for who in contenders
            }
            environments = {
                part: {
                    who: statistics.median(r.get(part, 0.0) for r in rounds[who])
                    for who in contenders
                }
                for part in (*ENV_PARTS, EPISODES)
            }
            results[label] = {
                "parts": parts,
                "plain_over_rl_pg": totals["plain PyTorch"] / totals["rl_pg"],
                "frames_per_update": n * recipe.config().segment_length,
                "loss_forward_repeated_at_once": repeated,
                "loss_forward_in_loop_over_repeated": {
                    who: parts["update: loss forward"][who] / repeated[who] for who in contenders
                },
                "environments": environments,
            }
            rows = [[piece, *values.values()] for piece, values in parts.items()]
            rows.append([REPEATED + " (not in the total)", *repeated.values()])
            print(f"\n{label}: microseconds per update")
            print(table(rows, ["piece", *contenders]))
            print(f"plain / rl_pg: {results[label]['plain_over_rl_pg']:.2f}")
            rows = [[part, *values.values()] for part, values in environments.items()]
            print(f"\n{label}: the environments' piece, microseconds (episodes) per update")
            print(table(rows, ["part", *contenders]))
    return write_json(cfg.json_path, cfg, tasks=results)


if __name__ == "__main__":
    main(tyro.cli(Config))
