"""The pieces of one run (its environments, models, loss, optimiser, collection,
loggers and state) and the steps the training loop calls them through: a
[`Run`][rl_pg.training.run.Run], which every callback receives."""

from __future__ import annotations

import math
import time
from pathlib import Path

from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from rl_pg.training.checkpoints import RunState, callback_states, restore, restore_rng
from rl_pg.training.collection import Collection
from rl_pg.training.config import config_dict
from rl_pg.training.console import Console
from rl_pg.training.learning import LearningSettings
from rl_pg.training.loggers import Loggers
from rl_pg.training.metric import Metric
from rl_pg.training.metrics import EpisodeReturns
from rl_pg.training.optimisation import (
    entropy_coeff,
    learning_rate,
    make_loss,
    make_optimizer,
    update,
    warm_up,
)
from rl_pg.training.seeds import run_streams, seed_everything
from rl_pg.training.selection import evaluate_run
from rl_pg.training.settings import CollectionSettings, EvaluationSettings, LoggingSettings

__all__ = ["Run"]


class Run:
    """The pieces of one run and the steps the loop calls them through.

    Callbacks read it: ``cfg``, ``state`` (a ``RunState``: ``frames``, ``updates``,
    ``last_eval``, …), ``metric`` (what picks ``best.pt``), ``loss``, ``actor``,
    ``deployed``, ``optimizer``, ``device``, ``eval_env``, ``logger``, ``path``,
    ``log`` and ``save``.
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
        self.device = device = cfg.torch_device()
        self.actor, critic = _models(make_models, env)
        self.learning = LearningSettings.of(cfg)  # what the updates read of the config
        self.evaluation = EvaluationSettings.of(cfg)
        self.metric = Metric.of(self.evaluation)  # what picks best.pt
        self.loss = make_loss(self.learning, self.actor, critic).to(device)
        warm_up(self.loss, env, device)
        self.optimizer = make_optimizer(self.learning, self.loss)
        # What evaluations play and best.pt deploys (a callback may set another).
        self.deployed = self.actor
        self.state = RunState(streams=run_streams(cfg.seed))
        if saved is not None:
            self.state = restore(saved, self.loss, self.optimizer, directory.checkpoint_path)
        self.eval_env = (make_eval_env or make_env)()
        self.collection = Collection(
            CollectionSettings.of(cfg), env, make_env, self.actor, seed=cfg.seed,
            updates=self.state.updates, group_size=cfg.group_size if cfg.grouped else None,
            greedy=cfg.baseline == "greedy", device=device,
            resumed=saved.get("collection") if saved is not None else None,
        )  # fmt: skip
        self.logger = Loggers(
            LoggingSettings.of(cfg), directory.path, directory.recipe["recipe"],
            hparams=config_dict(cfg),
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
            self.learning,
            self.loss,
            self.optimizer,
            batch,
            lr=learning_rate(self.learning, state.frames, cfg.total_frames),
            entropy_coeff=entropy_coeff(self.learning, state.frames, cfg.total_frames),
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
        evaluate_run(
            self.evaluation, self.device, self.deployed, self.eval_env, self.eval_entries,
            state, self.logger,
        )  # fmt: skip
        metric = self.metric
        best = self.hooks.keeps_best(self, state.last_eval)
        if best is None:
            best = state.is_best(metric)
        if best:
            self.save(to="best")
        solved = cfg.threshold is not None and metric.reaches(
            metric.read(state.last_eval), cfg.threshold
        )
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


def _models(make_models, env: EnvBase):
    models = make_models(env)
    if not (isinstance(models, tuple) and len(models) == 2):
        raise TypeError(
            f"make_models must return (actor, critic or None), got {type(models).__name__}. "
            f"Return (actor, None) to train without a critic."
        )
    return models
