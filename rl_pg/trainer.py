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

A run directory holds ``checkpoint.pt`` (written atomically), ``summary.json``,
``logs/`` (TorchRL's CSV logger, TensorBoard optional) and ``learning_curve.png``.
``resume=True`` continues from the checkpoint; with one worker, a run killed at any
time and resumed ends exactly as the uninterrupted run with the same seed would.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import random
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.collectors.weight_update import RayWeightUpdater
from torchrl.envs import EnvBase
from torchrl.record.loggers import CSVLogger, Logger, TensorboardLogger
from tqdm import tqdm

from rl_pg._checks import Range, check_fields, check_names
from rl_pg.checkpoint import (
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
    write_atomically,
)
from rl_pg.evaluation import evaluate
from rl_pg.functional import discounted_return
from rl_pg.loss import ReinforceLoss
from rl_pg.plots import png_figure
from rl_pg.run_dir import RunDirectory

__all__ = [
    "Count",
    "NonNegative",
    "Positive",
    "Range",
    "TrainConfig",
    "TrainingDiverged",
    "check_fields",
    "load_models",
    "read_run",
    "scalar_log_rows",
    "train",
]

CHECKPOINT = "checkpoint.pt"
SUMMARY = "summary.json"
CURVE = "learning_curve.png"
# Config fields that may change when a run is resumed; any other change is refused.
_RESUMABLE_FIELDS = frozenset(
    {
        "total_frames",
        "total_updates",
        "resume",
        "run_dir",
        "workers",
        "ray",
        "tensorboard",
        "progress",
        "threads",
    }
)


Count = Annotated[int, Range(low=1)]
"""An integer >= 1 (a config field type: the bound is checked when a config is made)."""
Positive = Annotated[float, Range(low=0, low_open=True)]
"""A finite number > 0."""
NonNegative = Annotated[float, Range(low=0)]
"""A finite number >= 0."""


class TrainingDiverged(RuntimeError):
    """The loss or its gradient became non-finite; the last good checkpoint is kept."""


@dataclass
class TrainConfig:
    """Settings of the training loop shared by every recipe."""

    seed: Annotated[int, Range(low=0, high=2**32 - 1)] = 0
    """Seed of torch, numpy, random and the environments."""
    total_frames: Count = 100_000
    """Environment steps to train for (at most)."""
    total_updates: Count | None = None
    """Updates to train for (at most; None: no limit)."""
    run_dir: Path | None = None
    """Where checkpoints, logs and the summary go (default: runs/<recipe>-seed<seed>-<time>)."""
    resume: bool = False
    """Continue the run in run_dir from its checkpoint."""
    workers: Count = 1
    """Collector processes; more than 1 uses TorchRL's multi-process collector."""
    ray: bool = False
    """Collect with TorchRL's Ray collector (rl_pg[ray]; `workers` actors; segments only)."""
    threads: Count | None = 1
    """torch threads of this process: small models update fastest on one, and a second
    thread only contends with the environment on a busy machine (None: torch's default)."""
    batch_mode: Literal["episodes", "segments"] = "episodes"
    """'episodes': whole episodes per update; 'segments': fixed-length segments + bootstrap."""
    episodes_per_batch: Count = 8
    """Complete episodes per update (batch_mode='episodes')."""
    segment_length: Count = 50
    """Steps per environment per update (batch_mode='segments')."""
    returns: Literal["reward_to_go", "discounted_return"] = "reward_to_go"
    """Return that weights log pi: reward-to-go (causality) or the whole-episode return."""
    gamma: Annotated[float, Range(0, 1)] = 0.99
    """Discount factor."""
    baseline: Literal["none", "batch_mean", "running_mean", "ema", "critic"] = "critic"
    """What is subtracted from the return."""
    baseline_rate: Annotated[float, Range(0, 1, low_open=True)] = 0.01
    """Rate of the 'ema' baseline."""
    entropy_coeff: NonNegative = 0.0
    """Entropy bonus weight."""
    critic_coeff: NonNegative = 1.0
    """Value-loss weight."""
    normalize_advantage: bool = False
    """Standardise the policy weights over each batch."""
    optimizer: Literal["adam", "sgd"] = "adam"
    """Optimiser of actor and critic."""
    lr: Positive = 1e-3
    """Learning rate."""
    lr_schedule: Literal["constant", "linear"] = "constant"
    """'linear': decay the learning rate from lr at frame 0 to 0 at total_frames
    (set before each update from the frames seen so far, so a resumed run continues the
    same schedule; raising total_frames on resume stretches what is left of it)."""
    weight_decay: NonNegative = 0.0
    """L2 weight decay."""
    max_grad_norm: Positive | None = None
    """Gradient-norm clipping (None: no clipping)."""
    eval_interval: Count = 10_000
    """Frames between evaluations."""
    eval_episodes: Count = 20
    """Episodes per evaluation."""
    eval_greedy: bool = True
    """Evaluate greedily (argmax / mean action) rather than by sampling."""
    threshold: float | None = None
    """Evaluation mean return that counts as solved."""
    stop_when_solved: bool = True
    """Stop at the first evaluation that reaches the threshold."""
    checkpoint_interval: Count = 50
    """Updates between checkpoints (one is always written at the end)."""
    log_interval: Count = 1
    """Updates between training-metric log lines."""
    tensorboard: bool = False
    """Also log to TensorBoard (pip install tensorboard)."""
    progress: bool = True
    """Show a progress bar."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Checks every field (also those a recipe adds) against its type and bounds.

        Runs when the config is made, so that the command line refuses a bad flag
        before anything starts, and again in [`train`][rl_pg.trainer.train].

        Raises:
            ValueError: a value out of its range or choices; the message names the
                field and its flag.
            TypeError: a value of the wrong kind (from Python code).
        """
        check_fields(self)
        if self.resume and self.run_dir is None:
            raise ValueError("--resume needs --run-dir: the directory of the run to continue.")
        if self.ray and self.batch_mode != "segments":
            raise ValueError(
                "The Ray collector yields fixed-length batches: use --batch-mode segments with "
                "--ray (whole-episode batches need the local or multi-process collectors)."
            )


@dataclass
class _State:
    """Everything about the run's progress that a checkpoint must restore."""

    frames: int = 0
    updates: int = 0
    train_time: float = 0.0
    solved_at_frames: int | None = None
    last_eval: dict[str, float] = field(default_factory=dict)
    history: dict[str, list[tuple[int, float]]] = field(default_factory=dict)

    def record(self, name: str, frames: int, value: float) -> None:
        self.history.setdefault(name, []).append((frames, value))


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
        >>> from rl_pg.trainer import TrainConfig, train
        >>> cfg = TrainConfig(
        ...     run_dir=tempfile.mkdtemp(), total_updates=2, eval_episodes=1, progress=False
        ... )
        >>> summary = train(
        ...     cfg,
        ...     recipe="demo",
        ...     make_env=lambda: GridWorldEnv(batch_size=4),
        ...     make_models=mlp_actor_critic,
        ... )
        >>> summary["updates"], sorted(summary)[:4]
        (2, ['eval_mean_return', 'eval_std_return', 'frames', 'recipe'])
    """
    if not isinstance(cfg, TrainConfig):
        raise TypeError(f"train needs a TrainConfig, got {type(cfg).__name__}.")
    cfg.validate()  # again: fields may have been changed since the config was made
    eval_flags = check_names("eval_flags", eval_flags)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    run_dir = Path(cfg.run_dir) if cfg.run_dir is not None else _new_run_dir(recipe, cfg.seed)
    checkpoint_path = run_dir / CHECKPOINT
    # Held until the run ends, however it ends: one run per directory at a time.
    with RunDirectory(run_dir) as directory:
        saved = _open_run_dir(cfg, recipe, directory, checkpoint_path)
        if saved is not None:
            directory.keep()
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
        state = _State()
        if saved is not None:
            state = _restore(saved, loss, optimizer, checkpoint_path)
        eval_env = (make_eval_env or make_env)()
        collector, sync_weights = _make_collector(cfg, env, make_env, actor, state)
        logger = _make_logger(cfg, run_dir, state)

        progress = tqdm(
            total=cfg.total_frames,
            initial=state.frames,
            unit="frames",
            disable=None if cfg.progress else True,  # None: shown on terminals only
        )
        next_eval = (state.frames // cfg.eval_interval + 1) * cfg.eval_interval
        collector_frames = 0
        episode_returns = _EpisodeReturns(carry=cfg.batch_mode == "segments")
        try:
            start = time.perf_counter()
            for batch in collector:
                metrics = _update(cfg, loss, optimizer, batch, lr=_learning_rate(cfg, state.frames))
                episode_returns.add(batch)
                state.updates += 1
                collector_frames, spent = _frames_spent(cfg, collector, batch, collector_frames)
                state.frames += spent
                if sync_weights is not None:
                    sync_weights()
                elif cfg.batch_mode == "episodes":
                    _restart_episodes(collector, cfg.seed, state.updates)
                if state.updates % cfg.log_interval == 0:
                    metrics["train/episode_return"] = episode_returns.pop_mean()
                    for name, value in metrics.items():
                        if math.isfinite(value):
                            logger.log_scalar(name, value, step=state.frames)
                            state.record(name, state.frames, value)
                    progress.set_postfix(
                        train=f"{metrics['train/episode_return']:.2f}",
                        eval=f"{state.last_eval.get('eval/mean_return', float('nan')):.2f}",
                        refresh=False,
                    )
                progress.update(spent)
                done = state.frames >= cfg.total_frames or (
                    cfg.total_updates is not None and state.updates >= cfg.total_updates
                )
                if state.frames >= next_eval or done:
                    state.train_time += time.perf_counter() - start
                    next_eval = (state.frames // cfg.eval_interval + 1) * cfg.eval_interval
                    _evaluate(cfg, actor, eval_env, eval_flags, state, logger)
                    solved = cfg.threshold is not None and (
                        state.last_eval["eval/mean_return"] >= cfg.threshold
                    )
                    if solved and state.solved_at_frames is None:
                        state.solved_at_frames = state.frames
                    done = done or (solved and cfg.stop_when_solved)
                    start = time.perf_counter()
                if done or state.updates % cfg.checkpoint_interval == 0:
                    state.train_time += time.perf_counter() - start
                    _save(cfg, recipe, loss, optimizer, state, checkpoint_path)
                    directory.keep()
                    start = time.perf_counter()
                    if cfg.batch_mode == "segments" and cfg.workers == 1 and not cfg.ray:
                        # A resumed run restarts its environments here; so does this one.
                        _restart_episodes(collector, cfg.seed, state.updates)
                        episode_returns.reset()
                if done:
                    break
        finally:
            progress.close()
            collector.shutdown()
            eval_env.close()
        summary = _summary(cfg, recipe, state, run_dir)
        write_atomically(run_dir / SUMMARY, json.dumps(summary, indent=2))
        _plot(state, cfg.threshold, run_dir / CURVE, recipe)
        return summary


# ----------------------------------------------------------------- building ---
def _open_run_dir(cfg, recipe, directory: RunDirectory, checkpoint_path: Path) -> dict | None:
    run_dir = directory.path
    if cfg.resume:
        saved = load_checkpoint(checkpoint_path)
        if saved.get("recipe") != recipe:
            raise CheckpointError(
                f"{checkpoint_path} was written by recipe {saved.get('recipe')!r}, not "
                f"{recipe!r}; resume it with that recipe."
            )
        current = _config_dict(cfg)
        changed = {
            key: (saved["config"].get(key), value)
            for key, value in current.items()
            if key not in _RESUMABLE_FIELDS and saved["config"].get(key) != value
        }
        if changed:
            details = ", ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in changed.items())
            raise CheckpointError(
                f"Cannot resume {checkpoint_path} with a different configuration ({details}). "
                f"Only {sorted(_RESUMABLE_FIELDS)} may change on resume."
            )
        _check_budget_left(cfg, saved["state"], run_dir)
        return saved
    if checkpoint_path.exists():
        raise CheckpointError(
            f"{run_dir} already holds a checkpoint; pass --resume to continue it, or choose "
            f"another --run-dir. Nothing was overwritten."
        )
    if directory.contents():
        # A run that died before its first checkpoint: its logs would interleave with ours.
        raise CheckpointError(
            f"{run_dir} holds {directory.contents()} but no checkpoint (a run that stopped "
            f"before its first checkpoint?). Delete it or choose another --run-dir; nothing "
            f"was overwritten."
        )
    return None


def _models(make_models, env: EnvBase):
    models = make_models(env)
    if not (isinstance(models, tuple) and len(models) == 2):
        raise TypeError(
            f"make_models must return (actor, critic or None), got {type(models).__name__}. "
            f"Return (actor, None) to train without a critic."
        )
    return models


def _check_budget_left(cfg: TrainConfig, state: dict, run_dir: Path) -> None:
    """A resumed run must have something left to do: it never trains past its budget."""
    if state["frames"] >= cfg.total_frames:
        raise CheckpointError(
            f"The run in {run_dir} has already trained {state['frames']} frames, and "
            f"total_frames={cfg.total_frames} asks for no more. Raise --total-frames above "
            f"{state['frames']} to continue it."
        )
    if cfg.total_updates is not None and state["updates"] >= cfg.total_updates:
        raise CheckpointError(
            f"The run in {run_dir} has already made {state['updates']} updates, and "
            f"total_updates={cfg.total_updates} asks for no more. Raise --total-updates "
            f"above {state['updates']} to continue it."
        )


def _new_run_dir(recipe: str, seed: int) -> Path:
    # Time-stamped, so that running a recipe twice never collides with an earlier run.
    return Path("runs") / f"{recipe}-seed{seed}-{time.strftime('%Y%m%d-%H%M%S')}"


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


def _make_collector(cfg: TrainConfig, env: EnvBase, make_env, actor, state: _State):
    n_envs = max(1, math.prod(env.batch_size))
    if cfg.batch_mode == "episodes":
        kwargs = {
            # Polling granularity only (with trajs_per_batch): about 64 steps, a whole
            # number of steps of the batched environment.
            "frames_per_batch": n_envs * max(1, round(64 / n_envs)),
            "trajs_per_batch": cfg.episodes_per_batch,
            "traj_format": "cat",
        }
    else:
        kwargs = {"frames_per_batch": cfg.segment_length * n_envs * max(1, cfg.workers)}
    # Our policies need no extra environment transform (no recurrent state).
    inner = {"auto_register_policy_transforms": False}
    if not cfg.ray and cfg.workers == 1:
        collector = Collector(env, actor, total_frames=-1, **kwargs, **inner)
        _restart_episodes(collector, cfg.seed, state.updates)
        return collector, None

    env.close()
    if cfg.ray:
        backend_options = {
            "ray_init_config": {
                "num_cpus": cfg.workers,
                "include_dashboard": False,
                # Actors import the recipe's make_env the way this process does.
                "runtime_env": {"env_vars": {"PYTHONPATH": os.pathsep.join(sys.path)}},
            },
            "collector_kwargs": inner,
            # Weights go through Ray's object store (below) rather than the default
            # torch.distributed group, which needs a network set-up many hosts lack.
            "weight_sync_schemes": {},
        }
        # The Ray collector reads -1 as "nothing to collect": give it no limit instead.
        kwargs["total_frames"] = 2**62
    else:
        backend_options = inner
        kwargs["total_frames"] = -1
    collector = Collector(
        [make_env] * cfg.workers,
        actor,
        backend="ray" if cfg.ray else "process",
        num_collectors=cfg.workers,
        sync=True,
        backend_options=backend_options,
        **kwargs,
    )
    if cfg.ray:
        return collector, RayWeightUpdater(
            policy_weights=TensorDict.from_module(actor),
            remote_collectors=collector.remote_collectors,
            max_interval=0,
        )
    collector.set_seed(_derived_seed(cfg.seed, state.updates))
    return collector, collector.update_policy_weights_


def _make_logger(cfg: TrainConfig, run_dir: Path, state: _State) -> _Loggers:
    _trim_csv_logs(run_dir / "logs", state.frames)
    loggers: list[Logger] = [CSVLogger(exp_name="csv", log_dir=str(run_dir / "logs"))]
    if cfg.tensorboard:
        loggers.append(TensorboardLogger(exp_name="tensorboard", log_dir=str(run_dir / "logs")))
    return _Loggers(loggers)


class _Loggers:
    """Sends each scalar to every TorchRL logger."""

    def __init__(self, loggers: list[Logger]) -> None:
        self.loggers = loggers

    def log_scalar(self, name: str, value: float, step: int) -> None:
        for logger in self.loggers:
            logger.log_scalar(name, value, step=step)


def _trim_csv_logs(log_dir: Path, frames: int) -> None:
    """Drops the rows a killed run logged after its last checkpoint (they are redone).

    Each file is replaced atomically: a run killed while trimming leaves the file as
    it was, and the next resume trims it again. A row cut short by the kill (no
    newline, or not two numbers) is dropped with the rest.
    """
    for path in log_dir.glob("csv/scalars/**/*.csv"):
        text = path.read_text()
        rows = text.split("\n")[:-1]  # what follows the last newline is a torn row
        kept = [row for row in rows if (parsed := _parse_row(row)) and parsed[0] <= frames]
        if len(kept) != len(rows) or not text.endswith("\n"):
            write_atomically(path, "".join(f"{row}\n" for row in kept))


def scalar_log_rows(text: str) -> list[tuple[float, float]]:
    """The complete ``step,value`` rows of a CSV scalar log.

    What follows the last newline, or a row that is not two numbers, was cut short by
    a killed run and is left out.

    Examples:
        >>> from rl_pg.trainer import scalar_log_rows
        >>> scalar_log_rows("64,0.5\\n128,0.75\\n19")
        [(64.0, 0.5), (128.0, 0.75)]
    """
    return [parsed for row in text.split("\n")[:-1] if (parsed := _parse_row(row))]


def _parse_row(row: str) -> tuple[float, float] | None:
    fields = row.split(",")
    if len(fields) != 2:
        return None
    try:
        return float(fields[0]), float(fields[1])
    except ValueError:
        return None


# -------------------------------------------------------------------- steps ---
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


def _frames_spent(cfg, collector, batch, last_count: int) -> tuple[int, int]:
    """Environment steps taken since the last update (dropped in-flight ones included)."""
    if cfg.workers > 1 or cfg.ray:
        return last_count, batch.numel()
    count = collector.state_dict()["frames"]
    return count, count - last_count


def _restart_episodes(collector, seed: int, updates: int) -> None:
    """Reseeds and resets the environments: the next batch depends only on (seed, updates)."""
    collector.set_seed(_derived_seed(seed, updates))
    collector.reset()


def _derived_seed(seed: int, updates: int) -> int:
    # Spread runs apart so that run s at update u never replays run s + 1 at update u - 1.
    return (seed * 1_000_003 + updates) % 2**31


class _EpisodeReturns:
    """Undiscounted returns of the training episodes that end in the batches.

    With segments an episode spans batches: each environment's unfinished sum is
    carried into its next segment's first reward, and the same whole-episode return
    kernel reads every ended episode. (A per-step transform such as TorchRL's
    ``RewardSum`` does this at every environment step and cost ~15 % of CartPole's
    collection time.)
    """

    def __init__(self, *, carry: bool) -> None:
        self.carry = carry
        self.partial: torch.Tensor | None = None
        self.ended: list[torch.Tensor] = []

    def reset(self) -> None:
        """The environments restarted: episodes in flight are gone."""
        self.partial = None

    def add(self, batch: TensorDictBase) -> None:
        done = batch["next", "done"].reshape(*batch.shape, -1).any(-1)
        reward = batch["next", "reward"].reshape(*batch.shape, -1).sum(-1)
        done = done.reshape(-1, done.shape[-1])  # [environments, T]
        reward = reward.reshape(done.shape).clone()
        if self.partial is not None and self.partial.shape[0] == reward.shape[0]:
            reward[:, 0] += self.partial
        self.ended.append(discounted_return(reward, done, 1.0, time_dim=-1)[done])
        if self.carry:  # what follows each row's last episode end is still in flight
            in_flight = done.flip(-1).cumsum(-1).flip(-1) == 0
            self.partial = (reward * in_flight).sum(-1)

    def pop_mean(self) -> float:
        """Mean over the episodes ended since the last call (NaN if none)."""
        ended = torch.cat(self.ended) if self.ended else torch.zeros(0)
        self.ended = []
        return ended.float().mean().item() if ended.numel() else float("nan")


def _evaluate(cfg, actor, eval_env, eval_flags, state: _State, logger) -> None:
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


# ------------------------------------------------------------- checkpoints ---
def _config_dict(cfg: TrainConfig) -> dict[str, Any]:
    return {
        key: str(value) if isinstance(value, Path) else value
        for key, value in dataclasses.asdict(cfg).items()
    }


def _save(cfg, recipe, loss, optimizer, state: _State, path: Path) -> None:
    save_checkpoint(
        {
            "recipe": recipe,
            "config": _config_dict(cfg),
            "loss": loss.state_dict(),
            "optimizer": optimizer.state_dict(),
            "state": dataclasses.asdict(state),
            "rng": {
                "torch": torch.get_rng_state(),
                "numpy": np.random.get_state(),
                "random": random.getstate(),
            },
        },
        path,
    )


def _restore(saved: dict, loss, optimizer, path: Path) -> _State:
    try:
        loss.load_state_dict(saved["loss"])
        optimizer.load_state_dict(saved["optimizer"])
    except (RuntimeError, ValueError, KeyError) as err:
        raise CheckpointError(
            f"{path} does not fit the models this configuration builds ({err}). It was "
            f"left as it is; resume it with the configuration that wrote it."
        ) from err
    torch.set_rng_state(saved["rng"]["torch"])
    np.random.set_state(saved["rng"]["numpy"])
    random.setstate(saved["rng"]["random"])
    state = _State(**saved["state"])
    state.history = {k: [tuple(p) for p in v] for k, v in state.history.items()}
    return state


def read_run(run: str | Path) -> dict[str, Any]:
    """The checkpoint of a run directory (or a checkpoint file itself).

    Raises:
        CheckpointError: missing or corrupted checkpoint.

    Examples:
        >>> import tempfile
        >>> from rl_pg.trainer import read_run
        >>> read_run(tempfile.mkdtemp())  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        rl_pg.checkpoint.CheckpointError: No checkpoint at .../checkpoint.pt.
    """
    path = Path(run)
    return load_checkpoint(path / CHECKPOINT if path.is_dir() else path)


def load_models(saved: dict[str, Any], actor: nn.Module, critic: nn.Module | None = None) -> None:
    """Loads a checkpoint's weights into freshly built models.

    The checkpoint comes from [`read_run`][rl_pg.trainer.read_run].

    Raises:
        CheckpointError: the weights do not fit the models.

    Examples:
        >>> import torch
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor
        >>> from rl_pg.trainer import load_models
        >>> actor = mlp_actor(GridWorldEnv(), hidden=(4,))
        >>> saved = {"loss": {f"actor_network.{k}": torch.zeros_like(v)
        ...                   for k, v in actor.state_dict().items()}}
        >>> load_models(saved, actor)
        >>> float(sum(p.abs().sum() for p in actor.parameters()))
        0.0
    """
    if not isinstance(saved, dict) or not isinstance(saved.get("loss"), dict):
        raise CheckpointError(
            "load_models needs a checkpoint as read_run(...) returns it (a dict with the "
            "loss's weights under 'loss')."
        )
    for prefix, module in (("actor_network.", actor), ("critic_network.", critic)):
        if module is None:
            continue
        weights = {
            key.removeprefix(prefix): value
            for key, value in saved["loss"].items()
            if key.startswith(prefix)
        }
        try:
            module.load_state_dict(weights)
        except RuntimeError as err:
            raise CheckpointError(
                f"The checkpoint's {prefix[:-1]} does not fit the model built from its "
                f"config ({err})."
            ) from err


# ------------------------------------------------------------------ results ---
def _summary(cfg: TrainConfig, recipe: str, state: _State, run_dir: Path) -> dict[str, Any]:
    summary = {
        "recipe": recipe,
        "run_dir": str(run_dir),
        "seed": cfg.seed,
        "frames": state.frames,
        "updates": state.updates,
        "train_wall_s": state.train_time,
        "eval_mean_return": state.last_eval.get("eval/mean_return"),
        "eval_std_return": state.last_eval.get("eval/std_return"),
        "threshold": cfg.threshold,
        "solved_at_frames": state.solved_at_frames,
    }
    for key, value in state.last_eval.items():
        if key.endswith("_rate"):
            summary[key.removeprefix("eval/")] = value
    return summary


def _plot(state: _State, threshold: float | None, path: Path, title: str) -> None:
    with png_figure(path) as ax:
        for name, label in (
            ("train/episode_return", "training episodes"),
            ("eval/mean_return", "evaluation"),
        ):
            points = state.history.get(name, [])
            if points:
                frames, values = zip(*points, strict=True)
                marker = "o" if name.startswith("eval") else None
                ax.plot(frames, values, label=label, marker=marker)
        if threshold is not None:
            ax.axhline(threshold, color="grey", linestyle=":", label=f"threshold {threshold:g}")
        ax.set(xlabel="frames", ylabel="episode return", title=title)
        ax.legend(loc="best")
