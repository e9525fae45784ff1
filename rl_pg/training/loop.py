"""The on-policy, replay-free training loop every recipe runs.

collect (a TorchRL collector) -> returns (the loss's value estimator) ->
``ReinforceLoss`` -> one optimiser step -> log, evaluate, checkpoint.

Two ways to batch experience:

* ``batch_mode="episodes"``: ``episodes_per_batch`` complete episodes per update,
  REINFORCE as the textbook states it: each an independent episode of the current
  policy (an [`EpisodeCollector`][rl_pg.episode_collector.EpisodeCollector]: every environment
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

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from rl_pg._checks import check_names
from rl_pg.evaluation import EvaluationEnv, reported
from rl_pg.training.callbacks import (
    Callback,
    Callbacks,
    EntropyByTarget,
    GradientNoise,
    KeepCheckpoints,
    LearningRateByKL,
    StopWhenSolved,
)
from rl_pg.training.collection import segments_per_update
from rl_pg.training.config import TrainConfig
from rl_pg.training.interrupt import InterruptRequest
from rl_pg.training.metric import Metric
from rl_pg.training.run import Run
from rl_pg.training.run_dir import RunDirectory, link_latest, new_run_dir
from rl_pg.training.selection import Confirmation, PolicyAverage
from rl_pg.training.threads import torch_threads

__all__ = ["from_config", "train"]


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
    Metric.of(cfg).check(reported(**eval_entries))  # before any environment starts
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
                batch = run.collection.join(
                    batch,
                    segments_per_update(
                        run.collection.settings, run.state.frames, cfg.total_frames
                    ),
                )
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


def from_config(cfg: TrainConfig) -> list[Callback]:
    """The callbacks the config's optional behaviours ask for (``policy_ema``,
    ``confirm_episodes``, ``stop_when_solved`` with a ``threshold``, ``keep_every``,
    ``grad_stats``, ``lr_control``, ``entropy_target``)."""
    callbacks: list[Callback] = []
    metric = Metric.of(cfg)
    if cfg.policy_ema > 0:
        callbacks.append(PolicyAverage(cfg.policy_ema))
    if cfg.confirm_episodes is not None:
        callbacks.append(Confirmation(cfg.confirm_episodes, cfg.threshold, metric))
    if cfg.stop_when_solved and cfg.threshold is not None:
        confirmed = cfg.confirm_episodes is not None
        callbacks.append(StopWhenSolved(cfg.threshold, confirmed=confirmed, metric=metric))
    if cfg.keep_every is not None:
        callbacks.append(KeepCheckpoints(cfg.keep_every))
    if cfg.grad_stats is not None:
        # Episodes of one group share their start: the group is the independent unit.
        grouped = cfg.grouped
        callbacks.append(GradientNoise(cfg.grad_stats, unit="group" if grouped else "episode"))
    if cfg.lr_control == "kl":
        callbacks.append(LearningRateByKL(cfg.target_kl, cfg.kl_lr_range))
    if cfg.entropy_target is not None:
        callbacks.append(
            EntropyByTarget(cfg.entropy_target, cfg.entropy_target_lr, cfg.entropy_coeff_min)
        )
    return callbacks
