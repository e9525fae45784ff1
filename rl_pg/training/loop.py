"""The on-policy, replay-free training loop every recipe runs.

collect (a TorchRL collector) -> returns (the loss's value estimator) ->
``ReinforceLoss`` -> one optimiser step -> log, evaluate, checkpoint.

Two ways to batch experience:

* ``batch_mode="episodes"``: ``episodes_per_batch`` complete episodes per update,
  REINFORCE as the textbook states it: each an independent episode of the current
  policy (an [`EpisodeCollector`][rl_pg.collectors.EpisodeCollector]: every environment
  plays a share fixed in advance, and the environments restart after each update, so
  no episode began under the previous policy). The dropped steps count as spent.
* ``batch_mode="segments"``: ``segment_length`` steps from every environment per
  update; unfinished episodes bootstrap from the critic (the Pong recipe's set-up).

``resume=True`` continues from the run directory's checkpoint; with one worker, a run
killed at any time and resumed ends exactly as the uninterrupted run with the same
seed would, however often either checkpointed (see
[`collection`][rl_pg.training.collection]).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from rl_pg._checks import check_names
from rl_pg.evaluation import EvaluationEnv
from rl_pg.groups import GROUP_BASELINES
from rl_pg.training.callbacks import (
    Callback,
    Callbacks,
    EntropyByTarget,
    GradientNoise,
    KeepCheckpoints,
    LearningRateByKL,
    StopWhenSolved,
)
from rl_pg.training.checkpoints import RunState, callback_states, restore, restore_rng
from rl_pg.training.collection import Collection, segments_per_update
from rl_pg.training.config import TrainConfig
from rl_pg.training.console import Console
from rl_pg.training.interrupt import InterruptRequest
from rl_pg.training.metrics import EpisodeReturns, Loggers
from rl_pg.training.optimisation import (
    entropy_coeff,
    learning_rate,
    make_loss,
    make_optimizer,
    update,
    warm_up,
)
from rl_pg.training.run_dir import RunDirectory, link_latest, new_run_dir
from rl_pg.training.seeds import run_streams, seed_everything
from rl_pg.training.selection import Confirmation, PolicyAverage, evaluate_run
from rl_pg.training.threads import torch_threads

__all__ = ["Run", "from_config", "train"]


def train(
    cfg: TrainConfig,
    *,
    recipe: str,
    make_env: Callable[[], EnvBase],
    make_models: Callable[[EnvBase], tuple[TensorDictModuleBase, TensorDictModuleBase | None]],
    make_eval_env: Callable[[], EvaluationEnv] | None = None,
    eval_flags: Sequence[str] = (),
    eval_values: Sequence[str] = (),
    recipe_module: str | None = None,
    summarise: Callable[[Path], dict[str, Any]] | None = None,
    callbacks: Sequence[Callback] = (),
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
        make_eval_env (callable, optional): builds the evaluation environment (an
            ``EnvBase`` or an [`EpisodeWorkers`][rl_pg.episode_workers.EpisodeWorkers]).
            Defaults to ``make_env``.
        eval_flags (sequence of str): boolean entries reported as rates by evaluations,
            e.g. ``("crashed",)``. Defaults to ``()``.
        eval_values (sequence of str): entries whose value at an episode's end
            evaluations average, e.g. ``("route_completion",)``. Defaults to ``()``.
        recipe_module (str, optional): the importable module that defines the recipe
            (a [`Recipe`][rl_pg.training.recipe.Recipe] passes its own); recorded so
            that ``rl-pg play`` can rebuild the run.
        summarise (callable, optional): ``run_dir -> dict`` of fields added to the
            summary, computed from the run's logs when it ends.
        callbacks (sequence of Callback): behaviours of your own, called after those
            the config asks for (see [`Callback`][rl_pg.training.callbacks.Callback]).
            Defaults to ``()``.

    Returns:
        The summary written to ``run_dir/summary.json``.

    Raises:
        CheckpointError: a fresh run in a directory that already holds a run, a resume
            from a missing, corrupted or incompatible checkpoint, or one whose budget
            (``total_frames`` / ``total_updates``) is already spent (nothing is
            overwritten).
        RunDirBusy: another process is running in ``run_dir``.
        TrainingDiverged: the loss or gradient became non-finite.
        ValueError: an invalid configuration (the message names the field), or two
            callbacks with the same key.

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
    eval_entries = {
        "flags": check_names("eval_flags", eval_flags),
        "values": check_names("eval_values", eval_values),
    }
    hooks = Callbacks([*from_config(cfg), *callbacks])
    run_dir = Path(cfg.run_dir) if cfg.run_dir is not None else new_run_dir(recipe, cfg.seed)
    # The directory is held until the run ends, however it ends; Ctrl-C ends the update
    # in progress, then the run saves and stops.
    with (
        torch_threads(cfg.threads),
        RunDirectory(run_dir) as directory,
        InterruptRequest() as interrupt,
    ):
        saved = directory.open(cfg, recipe, recipe_module)
        run = Run(cfg, directory, saved, make_env, make_models, make_eval_env, eval_entries, hooks)
        interrupted = False  # the run stopped on a signal before its budget was spent
        try:
            for batch in run.collection:
                interrupt.reclaim()  # Ray's workers and evaluators set handlers of their own
                batch = run.collection.join(batch, segments_per_update(cfg, run.state.frames))
                hooks.on_batch(run, batch)
                metrics = run.update(batch)
                if not directory.kept and cfg.run_dir is None:
                    link_latest(run_dir)  # runs/latest: the newest run that trained
                directory.keep()  # it trained: its logs stay, however the run ends
                hooks.on_update(run, batch, metrics)
                done = run.budget_spent()
                evaluated = done or run.evaluation_due()
                if evaluated:
                    run.evaluate()
                    hooks.on_evaluation(run, run.state.last_eval)
                done = hooks.stop_training(run) or done
                # Read once: a signal landing after this read (during the calls below)
                # stops the run after the next update, which then checkpoints.
                stop = done or interrupt.requested
                run.console.update(
                    run.state.frames,
                    run.spent,
                    metrics if run.logs_update() else None,
                    run.state.last_eval,
                    evaluated=evaluated,
                    updates=run.state.updates,
                )
                if stop or run.checkpoint_due() or hooks.checkpoint_due(run):
                    run.checkpoint()
                if stop:
                    interrupted = not done
                    break
        finally:
            try:
                run.logger.flush()  # a callback's on_end may read the logs
                hooks.on_end(run)
            finally:
                run.close()
        try:
            extra = summarise(run_dir) if summarise is not None else None
        except Exception:  # the recipe's own fields failed: the run's summary still stands
            directory.finish(run.state, interrupted=interrupted)
            raise
        summary = directory.finish(run.state, interrupted=interrupted, extra=extra)
    if interrupted:
        print(
            f"Interrupted ({interrupt.signal_name}) at {run.state.frames} frames; checkpoint "
            f"and summary saved in "
            f"{run_dir}. Continue with: rl-pg resume {run_dir}",
            file=sys.stderr,
        )
        raise KeyboardInterrupt
    return summary


class Run:
    """The pieces of one run and the steps the loop calls them through.

    Callbacks read it: ``cfg``, ``state`` (a ``RunState``: ``frames``, ``updates``,
    ``last_eval``, …), ``loss``, ``actor``, ``deployed``, ``optimizer``, ``eval_env``,
    ``logger``, ``path``, ``log`` and ``save``.
    """

    def __init__(
        self, cfg, directory, saved, make_env, make_models, make_eval_env, eval_entries, hooks
    ) -> None:
        self.cfg, self.directory, self.eval_entries = cfg, directory, eval_entries
        self.hooks = hooks
        seed_everything(cfg.seed)
        env = make_env()
        if not isinstance(env, EnvBase):
            raise TypeError(
                f"make_env must return a TorchRL environment (EnvBase), got "
                f"{type(env).__name__}. Wrap gymnasium environments with rl_pg.envs.gym_env."
            )
        device = cfg.torch_device()
        self.actor, critic = _models(make_models, env)
        self.loss = make_loss(cfg, self.actor, critic).to(device)
        warm_up(self.loss, env, device)
        self.optimizer = make_optimizer(cfg, self.loss)
        # What evaluations play and best.pt deploys (a callback may set another).
        self.deployed = self.actor
        self.state = RunState(streams=run_streams(cfg.seed))
        if saved is not None:
            self.state = restore(saved, self.loss, self.optimizer, directory.checkpoint_path)
        self.eval_env = (make_eval_env or make_env)()
        self.collection = Collection(
            cfg, env, make_env, self.actor, updates=self.state.updates, device=device,
            resumed=saved.get("collection") if saved is not None else None,
        )  # fmt: skip
        self.logger = Loggers(
            cfg, directory.path, directory.recipe["recipe"],
            resume_at=self.state.frames if saved is not None else None,
        )  # fmt: skip
        self.console = Console(
            total_frames=cfg.total_frames,
            initial_frames=self.state.frames,
            enabled=cfg.progress,
            total_updates=cfg.total_updates,
        )
        self.episode_returns = EpisodeReturns(carry=cfg.batch_mode == "segments")
        if saved is not None:  # the environments and counters where the run left them
            self.collection.replay()
            if "episodes" in saved:
                self.episode_returns.load_state_dict(saved["episodes"])
            restore_rng(saved)
            hooks.load_state_dict(callback_states(saved))
        self.next_eval = self._next_evaluation()
        self.spent = 0
        hooks.on_start(self)
        self._clock = time.perf_counter()  # training time excludes evaluations and saving

    @property
    def path(self) -> Path:
        """The run directory."""
        return self.directory.path

    def log(self, name: str, value: float) -> None:
        """Sends ``name = value`` to every logger of the run, at the current frames."""
        self.logger.log_scalar(name, value, step=self.state.frames)

    def logs_update(self) -> bool:
        """Whether the update just made logs its metrics (every ``log_interval``)."""
        return self.state.updates % self.cfg.log_interval == 0

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One optimiser step on ``batch``; returns its metrics (logged every
        ``log_interval`` updates)."""
        cfg, state = self.cfg, self.state
        metrics = update(
            cfg,
            self.loss,
            self.optimizer,
            batch,
            lr=learning_rate(cfg, state.frames),
            entropy_coeff=entropy_coeff(cfg, state.frames),
        )
        # The training return is the policy's: a group's greedy episode is not one.
        greedy = batch.get("greedy", None)
        self.episode_returns.add(batch if greedy is None else batch[~greedy.squeeze(-1)])
        state.updates += 1
        self.spent = self.collection.frames_spent(batch)
        state.frames += self.spent
        if self.collection.after_update(state.updates):
            self.episode_returns.reset()
        if not self.logs_update():
            return metrics
        metrics["train/episode_return"] = self.episode_returns.pop_mean()
        finite = {name: value for name, value in metrics.items() if math.isfinite(value)}
        self.logger.log_metrics(finite, step=state.frames)  # one call per backend
        return metrics

    def budget_spent(self) -> bool:
        cfg, state = self.cfg, self.state
        return state.frames >= cfg.total_frames or (
            cfg.total_updates is not None and state.updates >= cfg.total_updates
        )

    def evaluation_due(self) -> bool:
        return self.state.frames >= self.next_eval

    def evaluate(self) -> None:
        """Evaluates, keeping the best checkpoint and noting when the run first solved."""
        cfg, state = self.cfg, self.state
        self._pause()
        self.next_eval = self._next_evaluation()
        evaluate_run(cfg, self.deployed, self.eval_env, self.eval_entries, state, self.logger)
        best = self.hooks.keeps_best(self, state.last_eval)
        if best is None:
            best = state.is_best()
        if best:
            self.save(to="best")
        solved = cfg.threshold is not None and state.last_eval["eval/mean_return"] >= cfg.threshold
        if solved and state.solved_at_frames is None:
            state.solved_at_frames = state.frames
        self._resume_clock()

    def checkpoint_due(self) -> bool:
        return self.state.updates % self.cfg.checkpoint_interval == 0

    def checkpoint(self) -> None:
        """Writes the last checkpoint, then lets the callbacks write theirs."""
        self._pause()
        self.save()
        self.hooks.on_checkpoint(self)
        self._resume_clock()

    def save(self, *, to: str = "last") -> None:
        """Writes the run's checkpoint ``to`` ``"last"`` (``checkpoint.pt``), ``"best"``
        (``best.pt``) or ``"kept"`` (``checkpoints/update_<updates>.pt``)."""
        self.directory.save(
            self.loss, self.optimizer, self.state, to=to,
            collection=self.collection.state_dict(), episodes=self.episode_returns.state_dict(),
            callbacks=self.hooks.state_dict(),
        )  # fmt: skip

    def close(self) -> None:
        self.console.close()
        self.logger.close()
        self.collection.shutdown()
        if not self.eval_env.is_closed:  # a process-backed one that never started is
            self.eval_env.close()

    def _next_evaluation(self) -> int:
        return (self.state.frames // self.cfg.eval_interval + 1) * self.cfg.eval_interval

    def _pause(self) -> None:
        """Stops the training clock for an evaluation or a checkpoint, whose logs and
        checkpoint then agree on disk (the CSV rows held back are written)."""
        self.state.train_time += time.perf_counter() - self._clock
        self.logger.flush()

    def _resume_clock(self) -> None:
        self._clock = time.perf_counter()


def from_config(cfg: TrainConfig) -> list[Callback]:
    """The callbacks the config's optional behaviours ask for (``policy_ema``,
    ``confirm_episodes``, ``stop_when_solved`` with a ``threshold``, ``keep_every``,
    ``grad_stats``, ``lr_control``, ``entropy_target``)."""
    callbacks: list[Callback] = []
    if cfg.policy_ema > 0:
        callbacks.append(PolicyAverage(cfg.policy_ema))
    if cfg.confirm_episodes is not None:
        callbacks.append(Confirmation(cfg.confirm_episodes, cfg.threshold))
    if cfg.stop_when_solved and cfg.threshold is not None:
        callbacks.append(StopWhenSolved(cfg.threshold, confirmed=cfg.confirm_episodes is not None))
    if cfg.keep_every is not None:
        callbacks.append(KeepCheckpoints(cfg.keep_every))
    if cfg.grad_stats is not None:
        # Episodes of one group share their start: the group is the independent unit.
        grouped = cfg.baseline in GROUP_BASELINES
        callbacks.append(GradientNoise(cfg.grad_stats, unit="group" if grouped else "episode"))
    if cfg.lr_control == "kl":
        callbacks.append(LearningRateByKL(cfg.target_kl, cfg.kl_lr_range))
    if cfg.entropy_target is not None:
        callbacks.append(
            EntropyByTarget(cfg.entropy_target, cfg.entropy_target_lr, cfg.entropy_coeff_min)
        )
    return callbacks


def _models(make_models, env: EnvBase):
    models = make_models(env)
    if not (isinstance(models, tuple) and len(models) == 2):
        raise TypeError(
            f"make_models must return (actor, critic or None), got {type(models).__name__}. "
            f"Return (actor, None) to train without a critic."
        )
    return models
