"""A run's settings by concern: one dataclass per group of fields, each with the rules
among its own fields (the groups of what the run learns from are in
[`rl_pg.training.learning`][rl_pg.training.learning]).

[`TrainConfig`][rl_pg.training.config.TrainConfig] is all of them at once (one flat
set of flags, one ``config.json``); each part of the harness takes the group it acts
on, made with ``Group.of(cfg)``, and reads nothing else of the run's settings::

    >>> from rl_pg.training import TrainConfig
    >>> from rl_pg.training.settings import EvaluationSettings
    >>> EvaluationSettings.of(TrainConfig(eval_episodes=5)).eval_episodes
    5

A recipe whose environments come as a batch of copies adds ``BatchedEnvironments`` to
its config (and ``EnvPoolBackend`` where EnvPool can step them), so that the rules
that read those fields can name them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

from rl_pg._checks import Range

__all__ = [
    "BatchedEnvironments",
    "CheckpointSettings",
    "CollectionSettings",
    "Count",
    "EnvPoolBackend",
    "EvaluationSettings",
    "LoggingSettings",
    "NonNegative",
    "Positive",
    "RunSettings",
    "Settings",
]

Count = Annotated[int, Range(low=1)]
"""An integer >= 1 (a config field type: the bound is checked when a config is made)."""
Positive = Annotated[float, Range(low=0, low_open=True)]
"""A finite number > 0."""
NonNegative = Annotated[float, Range(low=0)]
"""A finite number >= 0."""


class Settings:
    """A group of settings: the fields of one concern, and the rules among them.

    A subclass is a dataclass declared with its group's name (``class
    RunSettings(Settings, group="run")``) and its docstring's first line says what the
    group holds (``--help`` shows both).
    """

    group: ClassVar[str | None] = None
    """The group's name in ``--help`` (None: no group of its own)."""
    acts_only_with: ClassVar[dict[str, tuple[str, Any]]] = {}
    """Fields that act only when another field of the group takes one of some values
    (``"not None"``: any value but None): field -> (that field, those values)."""
    resumable: ClassVar[frozenset[str]] = frozenset()
    """The group's fields that may change when a run is resumed."""

    def __init_subclass__(cls, group: str | None = None, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.group = group

    def check(self) -> None:
        """Refuses values of the group's fields that do not go together (their types and
        bounds are checked apart, field by field)."""

    @classmethod
    def of(cls, cfg: Any) -> Any:
        """The group's fields of ``cfg`` (a config that has them all), as this group
        alone: code handed it reads its own settings and nothing else."""
        return cls(**{field.name: getattr(cfg, field.name) for field in dataclasses.fields(cls)})


@dataclass
class RunSettings(Settings, group="run"):
    """What to train for how long, where, on what."""

    seed: Annotated[int, Range(low=0, high=2**32 - 1)] = 0
    """Seed of torch, numpy, random and the environments."""
    total_frames: Count = 100_000
    """Environment steps to train for (at most)."""
    total_updates: Count | None = None
    """Updates to train for (at most; None: no limit)."""
    run_dir: Path | None = None
    """Where checkpoints, logs and the summary go. None:
    runs/<recipe>-seed<seed>-<time>."""
    resume: bool = False
    """Continue the run in run_dir from its checkpoint."""
    device: Literal["auto", "cpu", "cuda"] = "cpu"
    """Where the models and the optimiser live. 'auto': CUDA when available.
    Environments step on the CPU. The recipes' small networks train fastest on the CPU,
    next to their environments; a GPU pays for large models (Pong's trunk)."""
    threads: Count | None = 1
    """torch threads of this process (None: torch's default). The same while rl-pg
    evaluate and rl-pg play run its checkpoints: small models update fastest on one, and
    a second thread only contends with the environment on a busy machine."""
    progress: bool = True
    """Show a progress bar."""

    resumable: ClassVar[frozenset[str]] = frozenset(
        {"total_frames", "total_updates", "run_dir", "resume", "device", "threads", "progress"}
    )

    def check(self) -> None:
        if self.resume and self.run_dir is None:
            raise ValueError("--resume needs --run-dir: the directory of the run to continue.")


@dataclass
class CollectionSettings(Settings, group="collection"):
    """How the batches are collected."""

    workers: Count = 1
    """Collector processes. More than 1 uses TorchRL's multi-process collector."""
    ray: bool = False
    """Collect on Ray actors (rl_pg[ray]). TorchRL's Ray collector runs `workers`
    actors; segments only."""
    overlap: bool = False
    """Step half the environments while the policy acts on the other half. Segments
    from one local collector, on environments built in two groups (the EnvPool backend);
    strictly on-policy."""
    batch_mode: Literal["episodes", "segments"] = "episodes"
    """Whole episodes per update, or fixed-length segments. Segments bootstrap from the
    critic where they cut an episode."""
    episodes_per_batch: Count = 8
    """Complete episodes per update (batch_mode='episodes')."""
    segment_length: Count = 50
    """Steps per environment per update (batch_mode='segments')."""
    segments_late: Count = 1
    """Segments per update from segments_late_start on. Each update then joins this many
    consecutive segments collected with the same policy: a batch that grows late in the
    run, strictly on-policy (1: one segment per update throughout)."""
    segments_late_start: Annotated[float, Range(0, 1, high_open=True)] = 0.5
    """Share of total_frames after which each update takes segments_late segments."""
    env_restart_interval: Count = 50
    """Updates between restarts of every environment. With segments and one worker;
    episodes in flight are cut there. A resumed run replays the actions since the last
    restart, so the results do not depend on when, or how often, the run checkpoints."""

    resumable: ClassVar[frozenset[str]] = frozenset({"workers", "ray"})

    @property
    def local(self) -> bool:
        """One collector in this process (no worker processes, no Ray)."""
        return self.workers == 1 and not self.ray

    def check(self) -> None:
        if self.segments_late > 1 and self.batch_mode != "segments":
            raise ValueError(
                f"--segments-late {self.segments_late} joins segments into one update, but "
                f"--batch-mode is {self.batch_mode!r}: use --batch-mode segments, or "
                "--episodes-per-batch for more whole episodes per update."
            )
        if self.overlap and (self.batch_mode != "segments" or not self.local):
            raise ValueError(
                "--overlap steps the two halves of this process's environments in turn, "
                "segment by segment: use it with --batch-mode segments and one local "
                f"collector (got --batch-mode {self.batch_mode}, --workers {self.workers}"
                f"{', --ray' if self.ray else ''})."
            )
        if self.ray and self.batch_mode != "segments":
            raise ValueError(
                "The Ray collector yields fixed-length batches: use --batch-mode segments with "
                "--ray (whole-episode batches need the local or multi-process collectors)."
            )


@dataclass
class EvaluationSettings(Settings, group="evaluation"):
    """Evaluations during training and the checkpoint they keep as best."""

    eval_interval: Count = 10_000
    """Frames between evaluations."""
    eval_episodes: Count = 20
    """Episodes per evaluation."""
    eval_greedy: bool = True
    """Evaluate greedily (argmax / mean action) rather than by sampling. Sampled
    evaluations draw their own random numbers (the same ones each time, from the run's
    evaluation seed), so they change nothing in the training."""
    policy_ema: Annotated[float, Range(0, 1, high_open=True)] = 0.0
    """Deploy an average of the actor's weights. Evaluations, best.pt and play use an
    exponential moving average (torch's AveragedModel), moved towards the trained
    weights by 1 - policy_ema after every update; the environments are still played with
    the trained weights. 0: evaluate the trained weights themselves."""
    confirm_episodes: Count | None = None
    """Episodes that confirm a new best, greedily and by sampling. Each evaluation that
    could become best.pt is replayed on this many more episodes both ways, and best.pt
    is the checkpoint whose worse select_by of the two is best: the best of many short
    evaluations is partly the luckiest, and a policy can act well greedily and badly by
    sampling. Evaluations at or above threshold (when set) and better than the best
    confirmed score are replayed. None: best.pt is the best evaluation."""
    select_by: str = "mean_return"
    """Evaluation entry that picks best.pt. Confirmations score it and threshold is
    compared with it too: mean_return, or a rate or mean the recipe's evaluations report
    (arrive_dest_rate, mean_route_completion, crashed_rate)."""
    select_mode: Literal["max", "min"] = "max"
    """Which select_by is best: the highest (max) or the lowest (min, a crash rate)."""
    threshold: float | None = None
    """Value of select_by that counts as solved. Reached at or above it (select_mode max),
    at or below it (min)."""
    stop_when_solved: bool = True
    """Stop at the first evaluation that reaches the threshold."""


@dataclass
class CheckpointSettings(Settings, group="checkpoints"):
    """When the run is saved."""

    checkpoint_interval: Count = 50
    """Updates between checkpoints (one is always written at the end)."""
    keep_every: Count | None = None
    """Also keep a checkpoint every N updates (None: never). Kept as
    run_dir/checkpoints/update_<N>.pt beside the last and the best."""

    resumable: ClassVar[frozenset[str]] = frozenset({"keep_every"})


@dataclass
class LoggingSettings(Settings, group="logging"):
    """What is logged, and where."""

    log_interval: Count = 1
    """Updates between training-metric log lines."""
    grad_stats: Count | None = None
    """Measure the gradient's noise every N updates (None: never). The noise scale, SNR
    and half-batch cosine of every return estimator on that update's batch, logged as
    grad/<estimator>/<statistic>. Changes nothing in the training."""
    tensorboard: bool = False
    """Also log to TensorBoard (rl_pg[tensorboard]). The events go to
    run_dir/logs/tensorboard."""
    wandb: bool = False
    """Also log to Weights & Biases (rl_pg[wandb]). The run is named after run_dir."""
    wandb_project: str = "rl_pg"
    """W&B project of the run."""
    wandb_mode: Literal["offline", "online"] = "offline"
    """W&B without an account, or streamed to its server. 'offline': files in
    run_dir/wandb (upload later with `wandb sync`); 'online': stream to the W&B server
    (after `wandb login`)."""
    mlflow: bool = False
    """Also log to MLflow (rl_pg[mlflow]). One MLflow run in the experiment named after
    the recipe."""
    mlflow_uri: str | None = None
    """MLflow tracking URI (None: MLflow's default). For example sqlite:///mlflow.db or
    http://host:5000; None also reads $MLFLOW_TRACKING_URI."""

    resumable: ClassVar[frozenset[str]] = frozenset(
        {"grad_stats", "tensorboard", "wandb", "wandb_project", "wandb_mode", "mlflow",
         "mlflow_uri"}
    )  # fmt: skip


@dataclass
class BatchedEnvironments(Settings):
    """A recipe whose environments step as one batch of copies."""

    num_envs: Count = 1
    """Copies of the environment stepped together as one batch. With --workers, the
    copies are split evenly over them (1: a single environment)."""


@dataclass
class EnvPoolBackend(Settings):
    """A recipe whose training environments EnvPool can step."""

    backend: Literal["gymnasium", "envpool"] = "gymnasium"
    """What steps the training environments. Gymnasium in this process, or EnvPool's
    C++ threads (pip install "rl_pg[envpool]"). Evaluation always plays gymnasium's."""
