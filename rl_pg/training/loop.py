"""The on-policy, replay-free training loop every recipe runs.

collect (a TorchRL collector) -> returns (the loss's value estimator) ->
``ReinforceLoss`` -> one optimiser step -> log, evaluate, checkpoint.

Two ways to batch experience:

* ``batch_mode="episodes"``: ``episodes_per_batch`` complete episodes per update,
  REINFORCE as the textbook states it. With one worker the loop is strictly on-policy:
  after each update the collector drops the episode in flight (whose first steps the
  previous policy chose); those frames still count as spent.
* ``batch_mode="segments"``: ``segment_length`` steps from every environment per
  update; unfinished episodes bootstrap from the critic (the Pong recipe's set-up).

``resume=True`` continues from the run directory's checkpoint; with one worker, a run
killed at any time and resumed ends exactly as the uninterrupted run with the same
seed would.
"""

from __future__ import annotations

import math
import random
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase

from rl_pg._checks import check_names
from rl_pg.evaluation import evaluate
from rl_pg.loss import ReinforceLoss
from rl_pg.training.checkpoints import RunState, restore
from rl_pg.training.collection import Collection
from rl_pg.training.config import TrainConfig
from rl_pg.training.console import Console
from rl_pg.training.interrupt import InterruptRequest
from rl_pg.training.metrics import EpisodeReturns, Loggers
from rl_pg.training.run_dir import RunDirectory, new_run_dir

__all__ = ["TrainingDiverged", "train"]


class TrainingDiverged(RuntimeError):
    """The loss or its gradient became non-finite; the last good checkpoint is kept."""


def train(
    cfg: TrainConfig,
    *,
    recipe: str,
    make_env: Callable[[], EnvBase],
    make_models: Callable[[EnvBase], tuple[TensorDictModuleBase, TensorDictModuleBase | None]],
    make_eval_env: Callable[[], EnvBase] | None = None,
    eval_flags: Sequence[str] = (),
) -> dict[str, Any]:
    """Trains ``make_models``' actor (and critic) on ``make_env`` with REINFORCE.

    Args:
        cfg (TrainConfig): the loop's settings.

    Keyword Args:
        recipe (str): the recipe's name, written to the summary and the checkpoint.
        make_env (callable): builds one training environment (must be picklable for
            ``workers > 1`` or ``ray``).
        make_models (callable): ``env -> (actor, critic or None)``; sizes come from the
            environment's specs.
        make_eval_env (callable, optional): builds the evaluation environment.
            Defaults to ``make_env``.
        eval_flags (sequence of str): boolean entries reported as rates by evaluations,
            e.g. ``("crashed",)``. Defaults to ``()``.

    Returns:
        The summary written to ``run_dir/summary.json``.

    Raises:
        CheckpointError: a fresh run in a directory that already holds a run, a resume
            from a missing, corrupted or incompatible checkpoint, or one whose budget
            (``total_frames`` / ``total_updates``) is already spent (nothing is
            overwritten).
        RunDirBusy: another process is running in ``run_dir``.
        TrainingDiverged: the loss or gradient became non-finite.
        ValueError: an invalid configuration (the message names the field).

    Examples:
        >>> import tempfile
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor_critic
        >>> from rl_pg.training import TrainConfig, train
        >>> cfg = TrainConfig(
        ...     run_dir=tempfile.mkdtemp(), total_updates=2, eval_episodes=1, progress=False
        ... )
        >>> summary = train(
        ...     cfg,
        ...     recipe="demo",
        ...     make_env=lambda: GridWorldEnv(batch_size=4),
        ...     make_models=mlp_actor_critic,
        ... )
        >>> summary["updates"], summary["frames"] > 0, "eval_mean_return" in summary
        (2, True, True)
    """
    if not isinstance(cfg, TrainConfig):
        raise TypeError(f"train needs a TrainConfig, got {type(cfg).__name__}.")
    cfg.validate()  # again: fields may have been changed since the config was made
    eval_flags = check_names("eval_flags", eval_flags)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    run_dir = Path(cfg.run_dir) if cfg.run_dir is not None else new_run_dir(recipe, cfg.seed)
    # Held until the run ends, however it ends: one run per directory at a time.
    with RunDirectory(run_dir) as directory:
        saved = directory.open(cfg, recipe)
        _seed_everything(cfg.seed)
        env = make_env()
        if not isinstance(env, EnvBase):
            raise TypeError(
                f"make_env must return a TorchRL environment (EnvBase), got "
                f"{type(env).__name__}. Wrap gymnasium environments with rl_pg.envs.gym_env."
            )
        actor, critic = _models(make_models, env)
        loss = _make_loss(cfg, actor, critic)
        _warm_up(loss, env)
        optimizer = _make_optimizer(cfg, loss)
        state = RunState()
        if saved is not None:
            state = restore(saved, loss, optimizer, directory.checkpoint_path)
        eval_env = (make_eval_env or make_env)()
        collection = Collection(cfg, env, make_env, actor, updates=state.updates)
        logger = Loggers(
            run_dir / "logs",
            tensorboard=cfg.tensorboard,
            resume_at=state.frames if saved is not None else None,
        )
        console = Console(
            total_frames=cfg.total_frames, initial_frames=state.frames, enabled=cfg.progress
        )
        next_eval = (state.frames // cfg.eval_interval + 1) * cfg.eval_interval
        episode_returns = EpisodeReturns(carry=cfg.batch_mode == "segments")
        # Ctrl-C ends the update in progress, then the run saves and stops.
        with InterruptRequest() as interrupt:
            try:
                start = time.perf_counter()
                for batch in collection:
                    metrics = _update(
                        cfg, loss, optimizer, batch, lr=_learning_rate(cfg, state.frames)
                    )
                    episode_returns.add(batch)
                    state.updates += 1
                    spent = collection.frames_spent(batch)
                    state.frames += spent
                    collection.after_update(state.updates)
                    logged = state.updates % cfg.log_interval == 0
                    if logged:
                        metrics["train/episode_return"] = episode_returns.pop_mean()
                        for name, value in metrics.items():
                            if math.isfinite(value):
                                logger.log_scalar(name, value, step=state.frames)
                                state.record(name, state.frames, value)
                    done = state.frames >= cfg.total_frames or (
                        cfg.total_updates is not None and state.updates >= cfg.total_updates
                    )
                    evaluated = state.frames >= next_eval or done
                    if evaluated:
                        state.train_time += time.perf_counter() - start
                        next_eval = (state.frames // cfg.eval_interval + 1) * cfg.eval_interval
                        _evaluate(cfg, actor, eval_env, eval_flags, state, logger)
                        if state.is_best():
                            directory.save(cfg, recipe, loss, optimizer, state, best=True)
                        solved = cfg.threshold is not None and (
                            state.last_eval["eval/mean_return"] >= cfg.threshold
                        )
                        if solved and state.solved_at_frames is None:
                            state.solved_at_frames = state.frames
                        done = done or (solved and cfg.stop_when_solved)
                        start = time.perf_counter()
                    console.update(
                        state.frames,
                        spent,
                        metrics if logged else None,
                        state.last_eval,
                        evaluated=evaluated,
                    )
                    if done or interrupt.requested or state.updates % cfg.checkpoint_interval == 0:
                        state.train_time += time.perf_counter() - start
                        directory.save(cfg, recipe, loss, optimizer, state)
                        start = time.perf_counter()
                        # A resumed run restarts its environments here; so does this one.
                        if collection.after_checkpoint(state.updates):
                            episode_returns.reset()
                    if done or interrupt.requested:
                        break
            finally:
                console.close()
                collection.shutdown()
                eval_env.close()
        summary = directory.finish(cfg, recipe, state, interrupted=interrupt.requested)
        if interrupt.requested:
            print(
                f"Interrupted at {state.frames} frames; checkpoint and summary saved in "
                f"{run_dir}. Continue with --resume --run-dir {run_dir}",
                file=sys.stderr,
            )
            raise KeyboardInterrupt
        return summary


def _models(make_models, env: EnvBase):
    models = make_models(env)
    if not (isinstance(models, tuple) and len(models) == 2):
        raise TypeError(
            f"make_models must return (actor, critic or None), got {type(models).__name__}. "
            f"Return (actor, None) to train without a critic."
        )
    return models


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _make_loss(cfg: TrainConfig, actor, critic) -> ReinforceLoss:
    loss = ReinforceLoss(
        actor,
        critic,
        baseline=cfg.baseline,
        baseline_rate=cfg.baseline_rate,
        entropy_coeff=cfg.entropy_coeff or None,
        critic_coeff=cfg.critic_coeff,
        normalize_advantage=cfg.normalize_advantage,
        loss_critic_type="l2",
        # The collector runs the actor itself: keep one set of parameters.
        functional=False,
    )
    loss.make_value_estimator(cfg.returns, gamma=cfg.gamma)
    return loss


def _warm_up(loss: ReinforceLoss, env: EnvBase) -> None:
    """Compiles (or loads from numba's cache) the return kernel before the clock starts.

    The first calls cost up to a second; timing them would charge the training loop
    with set-up, as if timing ``import torch``.
    """
    fake = env.fake_tensordict()
    batch = torch.stack([fake, fake], dim=-1)
    with torch.no_grad():
        for _ in range(2):  # the second call still pays for thread-pool start-up
            loss.value_estimator(batch)


def _make_optimizer(cfg: TrainConfig, loss: ReinforceLoss) -> torch.optim.Optimizer:
    params = [p for p in loss.parameters() if p.requires_grad]
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay)


def _learning_rate(cfg: TrainConfig, frames: int) -> float:
    """The learning rate of the update that follows ``frames`` environment steps."""
    if cfg.lr_schedule == "linear":
        return cfg.lr * max(0.0, 1.0 - frames / cfg.total_frames)
    return cfg.lr


def _update(
    cfg: TrainConfig, loss: ReinforceLoss, optimizer, batch: TensorDictBase, *, lr: float
) -> dict:
    losses = loss(batch)
    total = sum(value for key, value in losses.items() if key.startswith("loss_"))
    if not torch.isfinite(total):
        raise TrainingDiverged(
            f"The loss became {total.item()} ({_describe(losses)}); training stopped and "
            f"the last good checkpoint was kept. Lower the learning rate or clip gradients."
        )
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    params = [p for group in optimizer.param_groups for p in group["params"]]
    max_norm = cfg.max_grad_norm if cfg.max_grad_norm is not None else float("inf")
    grad_norm = nn.utils.clip_grad_norm_(params, max_norm)
    if not torch.isfinite(grad_norm):
        raise TrainingDiverged(
            f"The gradient norm became {grad_norm.item()}; training stopped and the last "
            f"good checkpoint was kept. Lower the learning rate or set max_grad_norm."
        )
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.step()
    metrics = {
        f"loss/{key[5:]}": value.item() for key, value in losses.items() if key.startswith("loss_")
    }
    for key in ("entropy", "advantage_mean", "advantage_std", "explained_variance", "baseline"):
        value = losses.get(key, None)
        if value is not None:
            metrics[f"train/{key}"] = value.item()
    metrics["train/grad_norm"] = grad_norm.item()
    metrics["train/lr"] = lr
    return metrics


def _describe(losses: TensorDictBase) -> str:
    return ", ".join(f"{k}={v.item():.4g}" for k, v in losses.items() if k.startswith("loss_"))


def _evaluate(cfg, actor, eval_env, eval_flags, state: RunState, logger) -> None:
    eval_env.set_seed(cfg.seed + 1_000_003)  # the same start states at every evaluation
    start = time.perf_counter()
    result = evaluate(
        actor, eval_env, episodes=cfg.eval_episodes, deterministic=cfg.eval_greedy, flags=eval_flags
    )
    result = {f"eval/{key}": value for key, value in result.items()}
    result["time/eval_s"] = time.perf_counter() - start
    result["time/train_s"] = state.train_time
    state.last_eval = result
    for name, value in result.items():
        logger.log_scalar(name, value, step=state.frames)
        state.record(name, state.frames, value)
