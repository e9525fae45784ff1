"""Which policy a run evaluates and keeps as ``best.pt``: the evaluation episodes, the
average of the policy's weights that can be evaluated instead of the weights
([`PolicyAverage`][rl_pg.training.selection.PolicyAverage]), and the replays that
confirm a candidate on more episodes
([`Confirmation`][rl_pg.training.selection.Confirmation])."""

from __future__ import annotations

import contextlib
import time
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDictBase
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from rl_pg._checks import check_field
from rl_pg.evaluation import evaluate
from rl_pg.training.callbacks import Callback
from rl_pg.training.checkpoints import POLICY_AVERAGE, RunState
from rl_pg.training.metric import Metric
from rl_pg.training.settings import EvaluationSettings

if TYPE_CHECKING:
    from rl_pg.training.run import Run

__all__ = ["Confirmation", "PolicyAverage", "confirm", "evaluate_run"]


def confirm(
    device: torch.device, actor, eval_env, state: RunState, logger, *, episodes: int,
    metric: Metric | None = None, entries: dict[str, Any] | None = None,
) -> float:  # fmt: skip
    """Replays ``actor`` (on ``device``) on ``episodes`` episodes greedily, then by
    sampling, both from the confirmation seed; logs both values of ``metric`` (the mean
    return by default; ``entries``, the evaluation's ``flags`` and ``values``, report
    the others) and returns the worse one. Training's random stream is left as
    it was: confirming changes which checkpoint is kept, not the run."""
    metric = metric or Metric()
    start = time.perf_counter()
    scores = {}
    for mode, greedy in (("greedy", True), ("sampled", False)):
        with _random_stream(device, state.streams["confirmation"]):
            eval_env.set_seed(state.streams["confirmation"])
            result = evaluate(
                actor, eval_env, episodes=episodes, deterministic=greedy, **(entries or {})
            )
        scores[f"confirm/{mode}_{metric.key}"] = metric.read(
            {f"eval/{key}": value for key, value in result.items()}
        )
    score = metric.worst(scores.values())
    logged = {**scores, "confirm/score": score, "time/confirm_s": time.perf_counter() - start}
    for name, value in logged.items():
        logger.log_scalar(name, value, step=state.frames)
    return score


def evaluate_run(
    settings: EvaluationSettings, device: torch.device, actor, eval_env, eval_entries,
    state: RunState, logger,
) -> None:  # fmt: skip
    """Plays the run's evaluation (``eval_episodes`` from the evaluation seed, the
    same start states every time and, sampled, the same random numbers), logs it under
    ``eval/`` and keeps it as ``state.last_eval``. Training's random stream is left as
    it was: how often a run evaluates does not change what it learns."""
    start = time.perf_counter()
    with _random_stream(device, state.streams["evaluation"]):
        eval_env.set_seed(state.streams["evaluation"])
        result = evaluate(
            actor, eval_env, episodes=settings.eval_episodes, deterministic=settings.eval_greedy,
            **eval_entries,
        )  # fmt: skip
    result = {f"eval/{key}": value for key, value in result.items()}
    result["time/eval_s"] = time.perf_counter() - start
    result["time/train_s"] = state.train_time
    state.last_eval = result
    for name, value in result.items():
        logger.log_scalar(name, value, step=state.frames)


class PolicyAverage(Callback):
    """Evaluates, keeps as ``best.pt`` and deploys an exponential moving average of the
    actor's weights (torch's ``AveragedModel``) instead of the weights themselves
    (``--policy-ema``); the environments are still played with the trained weights.

    After every update the average moves towards the trained weights by
    ``1 - decay``; it starts as a copy of the initial weights. Its buffers (a
    [`RunningNorm`][rl_pg.normalization.RunningNorm]'s statistics) are copied, not
    averaged, so the averaged weights read observations standardised as the trained
    ones do. Checkpoints keep it under ``policy_average``, where
    [`load_models`][rl_pg.training.checkpoints.load_models] finds it.

    Args:
        decay (float): in [0, 1): the weight of the average's past at each update.
    """

    key = POLICY_AVERAGE

    def __init__(self, decay: float) -> None:
        self.decay = check_field(EvaluationSettings, "policy_ema", decay, "decay")
        self.average: AveragedModel | None = None
        self._saved: dict[str, Any] | None = None

    def on_start(self, run: Run) -> None:
        self.average = AveragedModel(run.actor, multi_avg_fn=get_ema_multi_avg_fn(self.decay))
        self.average.update_parameters(run.actor)
        if self._saved is not None:
            self.average.load_state_dict(self._saved["weights"])
        run.deployed = self.average.module

    def on_update(self, run: Run, batch: TensorDictBase, metrics: dict[str, float]) -> None:
        self.average.update_parameters(run.actor)

    def state_dict(self) -> dict[str, Any]:
        return {"weights": self.average.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._saved = state  # loaded once on_start has built the average


class Confirmation(Callback):
    """Replays each evaluation that could become ``best.pt`` on ``episodes`` more
    episodes, greedily and by sampling, and keeps the policy whose worse score of the
    two is best (``--confirm-episodes``), scored on ``metric``.

    Replayed are the evaluations at ``threshold`` or better (when given) that are
    better than the best confirmed score; they play the run's confirmation seed, with
    random numbers of their own, so confirming changes which checkpoint is kept, not
    the run. Once one evaluation was confirmed, only confirmations decide. Each replay
    logs ``confirm/greedy_<key>``, ``confirm/sampled_<key>`` (``confirm/greedy_mean_return``
    for the return), ``confirm/score`` and its cost ``time/confirm_s``.

    Args:
        episodes (int): episodes of each replay, in each mode.
        threshold (float, optional): only evaluations at it or better are replayed.
        metric (Metric, optional): what is scored. Defaults to the mean return.
    """

    def __init__(
        self, episodes: int, threshold: float | None = None, metric: Metric | None = None
    ) -> None:
        self.episodes = check_field(EvaluationSettings, "confirm_episodes", episodes, "episodes")
        self.threshold = check_field(EvaluationSettings, "threshold", threshold, optional=True)
        self.metric = metric or Metric()

    def keeps_best(self, run: Run, result: dict[str, float]) -> bool | None:
        state = run.state
        if not state.worth_confirming(self.metric, self.threshold):
            return None  # the run's own rule, which keeps nothing once a replay decided
        score = confirm(
            run.device, run.deployed, run.eval_env, state, run.logger,
            episodes=self.episodes, metric=self.metric, entries=run.eval_entries,
        )  # fmt: skip
        return state.is_best_confirmed(self.metric, score)


@contextlib.contextmanager
def _random_stream(device: torch.device, seed: int):
    """torch's generators (those of ``device`` too) seeded with ``seed`` inside, restored
    to training's after."""
    cuda = (
        [torch.cuda.current_device() if device.index is None else device.index]
        if device.type == "cuda"
        else []
    )
    with torch.random.fork_rng(devices=cuda):
        torch.manual_seed(seed)
        yield
