"""Behaviours plugged into the training loop: a [`Callback`][rl_pg.training.callbacks.Callback]
is called at fixed points of every run, and sees the run's pieces by name.

``train(cfg, ..., callbacks=[...])`` (or ``recipe.train(cfg, callbacks=[...])``) adds
your own; the config's optional behaviours are callbacks too, built by
[`from_config`][rl_pg.training.loop.from_config]: those here, and the policy average
and confirmation of [`selection`][rl_pg.training.selection]. A callback that keeps state
returns it from ``state_dict()``: it is saved in every checkpoint and handed back to
``load_state_dict()`` when the run resumes, so a resumed run continues as it would have.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from tensordict import TensorDictBase

from rl_pg._checks import check_field
from rl_pg.controllers import EntropyTarget, KLStepSize
from rl_pg.gradient_statistics import GradientStatistics
from rl_pg.training.learning import LossSettings, OptimiserSettings, check_kl_lr_range
from rl_pg.training.metric import Metric
from rl_pg.training.optimisation import scale_rewards
from rl_pg.training.settings import CheckpointSettings, EvaluationSettings, LoggingSettings

if TYPE_CHECKING:
    from rl_pg.training.run import Run

__all__ = [
    "Callback",
    "Callbacks",
    "EntropyByTarget",
    "GradientNoise",
    "KeepCheckpoints",
    "LearningRateByKL",
    "StopWhenSolved",
]


class Callback:
    """A behaviour the training loop calls; override the hooks you need.

    Every hook gets the [`Run`][rl_pg.training.run.Run]: ``run.cfg``, ``run.state``
    (``frames``, ``updates``, ``last_eval``, …), ``run.loss``, ``run.actor``,
    ``run.optimizer``, ``run.deployed`` (the policy that evaluations play and
    ``best.pt`` deploys: ``run.actor`` unless a callback such as
    [`PolicyAverage`][rl_pg.training.selection.PolicyAverage] sets another),
    ``run.eval_env``, ``run.path`` (the run directory), ``run.log(name, value)``,
    which sends a scalar to every logger of the run at the current frame count, and
    ``run.save(to=...)``, which writes the run's checkpoint.

    Order within one update: ``on_batch`` (the parameters that collected the batch,
    before the optimiser step), ``on_update`` (after it, frames and updates counted);
    when an evaluation is due, ``keeps_best`` (after the evaluation played) and
    ``on_evaluation`` (after ``best.pt`` was written, if it was); then
    ``stop_training``, ``checkpoint_due``, and ``on_checkpoint`` when a checkpoint was
    written.

    Examples:
        >>> import tempfile
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor_critic
        >>> from rl_pg.training import Callback, TrainConfig, train
        >>> class StopAfter(Callback):
        ...     '''Logs each batch's size; stops the run after `updates` updates.'''
        ...     def __init__(self, updates):
        ...         self.updates = updates
        ...     def on_update(self, run, batch, metrics):
        ...         run.log("train/batch_steps", batch.numel())
        ...     def stop_training(self, run):
        ...         return run.state.updates >= self.updates
        >>> cfg = TrainConfig(run_dir=tempfile.mkdtemp(), eval_episodes=1, progress=False)
        >>> summary = train(
        ...     cfg, recipe="demo", make_env=lambda: GridWorldEnv(batch_size=4),
        ...     make_models=mlp_actor_critic, callbacks=[StopAfter(3)],
        ... )
        >>> summary["updates"]
        3
    """

    key: str | None = None
    """Where the callback's state goes in a checkpoint (default: the class name)."""

    def on_start(self, run: Run) -> None:
        """The run is built (and, when resumed, restored); nothing is collected yet."""

    def on_batch(self, run: Run, batch: TensorDictBase) -> None:
        """A batch arrived; the policy is still the one that collected it."""

    def on_update(self, run: Run, batch: TensorDictBase, metrics: dict[str, float]) -> None:
        """The optimiser stepped on ``batch``; ``metrics`` are the update's (``loss/*``,
        ``train/*``), whether or not this update logs them."""

    def keeps_best(self, run: Run, result: dict[str, float]) -> bool | None:
        """Whether the policy just evaluated (``result``: its ``eval/*`` entries)
        becomes ``best.pt``: True or False decides, None (the default) leaves it to the
        next callback, and to the run's own rule when none decides (the highest
        evaluation mean return so far)."""
        return None

    def on_evaluation(self, run: Run, result: dict[str, float]) -> None:
        """An evaluation ended with ``result`` (``eval/*`` entries)."""

    def stop_training(self, run: Run) -> bool:
        """True ends the run after this update, as a spent budget does."""
        return False

    def checkpoint_due(self, run: Run) -> bool:
        """True asks for a checkpoint after this update (as ``checkpoint_interval`` does)."""
        return False

    def on_checkpoint(self, run: Run) -> None:
        """The run's last checkpoint was just written (``run.save(to="kept")`` keeps a
        copy; every callback's state is in it)."""

    def on_end(self, run: Run) -> None:
        """The run is ending (its last checkpoint written), however it ends."""

    def state_dict(self) -> dict[str, Any]:
        """What a checkpoint keeps of this callback (tensors, numbers, lists, dicts)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores what ``state_dict`` returned, on resume."""


class Callbacks:
    """The run's callbacks, called in order; their states are keyed by ``key``.

    Raises:
        TypeError: an entry that is not a ``Callback``.
        ValueError: two callbacks with the same key (their states would collide).
    """

    def __init__(self, callbacks: Sequence[Callback]) -> None:
        self.callbacks = list(callbacks)
        keys = []
        for callback in self.callbacks:
            if not isinstance(callback, Callback):
                raise TypeError(
                    f"callbacks must be rl_pg.training.Callback instances, got "
                    f"{type(callback).__name__}: subclass Callback and override its hooks."
                )
            keys.append(_key(callback))
        repeated = sorted({k for k in keys if keys.count(k) > 1})
        if repeated:
            raise ValueError(
                f"Several callbacks have the key(s) {repeated}, under which their states are "
                f"saved: give each instance its own `key`."
            )

    def _each(self, hook: str, *args) -> list:
        """Calls ``hook`` on every callback in order (none is skipped because of an
        earlier one's answer); their answers."""
        return [getattr(callback, hook)(*args) for callback in self.callbacks]

    def on_start(self, run: Run) -> None:
        self._each("on_start", run)

    def on_batch(self, run: Run, batch: TensorDictBase) -> None:
        self._each("on_batch", run, batch)

    def on_update(self, run: Run, batch: TensorDictBase, metrics: dict[str, float]) -> None:
        self._each("on_update", run, batch, metrics)

    def keeps_best(self, run: Run, result: dict[str, float]) -> bool | None:
        """The first answer that is not None."""
        verdicts = self._each("keeps_best", run, result)
        return next((verdict for verdict in verdicts if verdict is not None), None)

    def on_evaluation(self, run: Run, result: dict[str, float]) -> None:
        self._each("on_evaluation", run, result)

    def stop_training(self, run: Run) -> bool:
        return any(self._each("stop_training", run))

    def checkpoint_due(self, run: Run) -> bool:
        return any(self._each("checkpoint_due", run))

    def on_checkpoint(self, run: Run) -> None:
        self._each("on_checkpoint", run)

    def on_end(self, run: Run) -> None:
        self._each("on_end", run)

    def state_dict(self) -> dict[str, dict[str, Any]]:
        return {_key(c): c.state_dict() for c in self.callbacks}

    def load_state_dict(self, states: dict[str, dict[str, Any]]) -> None:
        """Hands each callback the state saved under its key (a callback added since the
        checkpoint was written starts fresh)."""
        for callback in self.callbacks:
            if _key(callback) in states:
                callback.load_state_dict(states[_key(callback)])


def _key(callback: Callback) -> str:
    return callback.key or type(callback).__name__


class GradientNoise(Callback):
    """Measures the policy gradient's noise every ``every`` updates and logs it as
    ``grad/<estimator>/<statistic>`` (see [`rl_pg.gradient_statistics`][rl_pg.gradient_statistics]),
    with its cost as ``time/grad_stats_s``.

    Measured on the batch the update learns from (rewards scaled as the loss sees
    them), at the parameters that collected it. It draws no random number and changes
    no state: a run measured this way trains exactly as one that is not. A batch of
    fewer than two units (one episode, or one environment's unfinished segment) has
    no spread to measure and is skipped.

    Args:
        every (int): updates between measurements.

    Keyword Args:
        estimators (sequence of str, optional): as ``GradientStatistics`` takes them.
            Defaults to all the loss can compute.
        unit (str): ``"episode"``, ``"row"`` or ``"group"``. Defaults to
            ``"episode"``.
    """

    STATISTICS = (
        "noise_scale",
        "snr",
        "half_cosine",
        "trace_covariance",
        "grad_norm_sq",
        "mean_grad_norm_sq",
    )
    """The scalars logged for each estimator (and ``units`` once)."""

    def __init__(
        self, every: int, *, estimators: Sequence[str] | None = None, unit: str = "episode"
    ) -> None:
        self.every = check_field(LoggingSettings, "grad_stats", every, "every")
        self.estimators, self.unit = estimators, unit
        self._statistics: GradientStatistics | None = None
        self._pending: dict[str, float] | None = None

    def on_start(self, run: Run) -> None:
        self._statistics = GradientStatistics(run.loss, estimators=self.estimators, unit=self.unit)

    def on_batch(self, run: Run, batch: TensorDictBase) -> None:
        if (run.state.updates + 1) % self.every != 0:
            return
        start = time.perf_counter()
        scale = run.cfg.reward_scale
        if scale != 1.0:
            batch = scale_rewards(batch, scale, run.loss.tensor_keys.reward)
        try:
            stats = self._statistics(batch)
        except ValueError as err:
            if "at least 2 independent units" not in str(err):
                raise
            self._pending = None  # a batch of one episode has no spread to measure
            return
        logged = {}
        for name in stats.keys():
            logged[f"grad/{name}/units"] = float(stats[name, "units"])
            for stat in self.STATISTICS:
                logged[f"grad/{name}/{stat}"] = float(stats[name, stat])
        logged["time/grad_stats_s"] = time.perf_counter() - start
        self._pending = logged

    def on_update(self, run: Run, batch: TensorDictBase, metrics: dict[str, float]) -> None:
        if self._pending is None:
            return
        for name, value in self._pending.items():
            run.log(name, value)
        self._pending = None


class KeepCheckpoints(Callback):
    """Keeps a copy of the run's checkpoint every ``every`` updates, as
    ``run_dir/checkpoints/update_<updates>.pt`` (``--keep-every``).

    Args:
        every (int): updates between kept checkpoints.
    """

    def __init__(self, every: int) -> None:
        self.every = check_field(CheckpointSettings, "keep_every", every, "every")

    def checkpoint_due(self, run: Run) -> bool:
        return run.state.updates % self.every == 0

    def on_checkpoint(self, run: Run) -> None:
        if self.checkpoint_due(run):
            run.save(to="kept")


class LearningRateByKL(Callback):
    """Sets the learning rate from the KL divergence each update causes
    (``--lr-control kl``; [`KLStepSize`][rl_pg.controllers.KLStepSize]): the policy
    before the update is kept at ``on_batch``, the KL divergence measured at
    ``on_update`` and logged as ``train/kl``. The rate lives in the optimiser, whose
    state every checkpoint holds.

    Args:
        target_kl (float): the KL divergence per update aimed at.
        lr_range (tuple of float): the rate's bounds, as factors of the run's ``lr``.
            Defaults to ``(0.01, 10.0)``.
    """

    def __init__(self, target_kl: float, lr_range: tuple[float, float] = (0.01, 10.0)) -> None:
        self.target_kl = check_field(OptimiserSettings, "target_kl", target_kl)
        check_kl_lr_range(lr_range)
        self.lr_range = (float(lr_range[0]), float(lr_range[1]))
        self._step_size: KLStepSize | None = None

    def on_start(self, run: Run) -> None:
        low, high = self.lr_range
        self._step_size = KLStepSize(
            run.optimizer, run.loss.actor_network, target_kl=self.target_kl,
            lr_min=low * run.cfg.lr, lr_max=high * run.cfg.lr,
            action_key=run.loss.tensor_keys.action,
        )  # fmt: skip

    def on_batch(self, run: Run, batch: TensorDictBase) -> None:
        self._step_size.before(batch)

    def on_update(self, run: Run, batch: TensorDictBase, metrics: dict[str, float]) -> None:
        measured = self._step_size.after(batch)
        if run.logs_update():
            run.log("train/kl", measured["kl"])


class EntropyByTarget(Callback):
    """Learns the entropy coefficient that holds the policy's entropy at ``target``
    (``--entropy-target``; [`EntropyTarget`][rl_pg.controllers.EntropyTarget]), from
    each update's ``train/entropy``; its state is in every checkpoint.

    Args:
        target (float): the entropy to hold, in nats.
        lr (float): the change of the coefficient per nat of difference, per update.
        min_coeff (float): the lowest coefficient (negative: it may become a penalty).
    """

    def __init__(self, target: float, lr: float, min_coeff: float = 0.0) -> None:
        self.target = check_field(LossSettings, "entropy_target", target, "target")
        self.lr = check_field(LossSettings, "entropy_target_lr", lr, "lr")
        self.min_coeff = check_field(LossSettings, "entropy_coeff_min", min_coeff, "min_coeff")
        self._controller: EntropyTarget | None = None
        self._restored: dict[str, Any] | None = None

    def on_start(self, run: Run) -> None:
        self._controller = EntropyTarget(
            run.loss, target=self.target, lr=self.lr, min_coeff=self.min_coeff
        )
        if self._restored is not None:
            self._controller.load_state_dict(self._restored)

    def on_update(self, run: Run, batch: TensorDictBase, metrics: dict[str, float]) -> None:
        entropy = metrics.get("train/entropy")
        if entropy is not None:
            self._controller.update(entropy)

    def state_dict(self) -> dict[str, Any]:
        return self._controller.state_dict() if self._controller is not None else {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state:
            self._restored = state
            if self._controller is not None:
                self._controller.load_state_dict(state)


class StopWhenSolved(Callback):
    """Ends the run after an evaluation whose ``metric`` (the mean return by default)
    reaches ``threshold`` (``--stop-when-solved`` with a recipe's ``threshold``); with
    ``confirmed``, once a checkpoint is confirmed at the threshold both greedily and by
    sampling (the run's ``best_confirmed``, kept by ``--confirm-episodes``): what the
    run keeps is then done, not only its greedy play.

    Args:
        threshold (float): the value of ``metric`` that counts as solved.
        confirmed (bool): solved means a confirmed checkpoint at the threshold.
        metric (Metric, optional): the entry judged. Defaults to the mean return.
    """

    def __init__(
        self, threshold: float, *, confirmed: bool = False, metric: Metric | None = None
    ) -> None:
        self.threshold = check_field(EvaluationSettings, "threshold", threshold)
        self.confirmed = confirmed
        self.metric = metric or Metric()
        self._solved = False

    def on_evaluation(self, run: Run, result: dict[str, float]) -> None:
        if self.confirmed:  # the confirmation ran in this evaluation, before this call
            best = run.state.best_confirmed
            self._solved = best is not None and self.metric.reaches(best, self.threshold)
        else:
            self._solved = self.metric.reaches(self.metric.read(result), self.threshold)

    def stop_training(self, run: Run) -> bool:
        solved, self._solved = self._solved, False
        return solved
