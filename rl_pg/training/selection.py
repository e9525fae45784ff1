"""What a run plays at each evaluation: the evaluation episodes, and the replays that
confirm a candidate for ``best.pt`` on more of them (the
[`Confirmation`][rl_pg.training.callbacks.Confirmation] callback's)."""

from __future__ import annotations

import contextlib
import time

import torch

from rl_pg.evaluation import evaluate
from rl_pg.training.checkpoints import RunState
from rl_pg.training.config import TrainConfig

__all__ = ["confirm", "evaluate_run"]


def confirm(cfg, actor, eval_env, state: RunState, logger, *, episodes: int) -> float:
    """Replays ``actor`` on ``episodes`` episodes greedily, then by sampling,
    both from the confirmation seed; logs both means and returns the lower one. Training's
    random stream is left as it was: confirming changes which checkpoint is kept, not
    the run."""
    start = time.perf_counter()
    means = {}
    for mode, greedy in (("greedy", True), ("sampled", False)):
        with _random_stream(cfg, state.streams["confirmation"]):
            eval_env.set_seed(state.streams["confirmation"])
            result = evaluate(actor, eval_env, episodes=episodes, deterministic=greedy)
        means[f"confirm/{mode}_mean_return"] = result["mean_return"]
    score = min(means.values())
    logged = {**means, "confirm/score": score, "time/confirm_s": time.perf_counter() - start}
    for name, value in logged.items():
        logger.log_scalar(name, value, step=state.frames)
    return score


def evaluate_run(cfg, actor, eval_env, eval_entries, state: RunState, logger) -> None:
    """Plays the run's evaluation (``cfg.eval_episodes`` from the evaluation seed, the
    same start states every time and, sampled, the same random numbers), logs it under
    ``eval/`` and keeps it as ``state.last_eval``. Training's random stream is left as
    it was: how often a run evaluates does not change what it learns."""
    start = time.perf_counter()
    with _random_stream(cfg, state.streams["evaluation"]):
        eval_env.set_seed(state.streams["evaluation"])
        result = evaluate(
            actor, eval_env, episodes=cfg.eval_episodes, deterministic=cfg.eval_greedy,
            **eval_entries,
        )  # fmt: skip
    result = {f"eval/{key}": value for key, value in result.items()}
    result["time/eval_s"] = time.perf_counter() - start
    result["time/train_s"] = state.train_time
    state.last_eval = result
    for name, value in result.items():
        logger.log_scalar(name, value, step=state.frames)


@contextlib.contextmanager
def _random_stream(cfg: TrainConfig, seed: int):
    """torch's generators seeded with ``seed`` inside, restored to training's after."""
    device = cfg.torch_device()
    cuda = (
        [torch.cuda.current_device() if device.index is None else device.index]
        if device.type == "cuda"
        else []
    )
    with torch.random.fork_rng(devices=cuda):
        torch.manual_seed(seed)
        yield
