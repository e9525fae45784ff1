"""Hyperparameter search over a recipe with Optuna: ``rl-pg tune RECIPE``.

Each trial trains the recipe with sampled settings on one or more seeds, scores each run
(its last evaluation, its best, or its best checkpoint replayed on fresh episodes both
greedily and by sampling) and the trial by the mean or the worst of its runs' scores.
The study lives in the study directory (``study.db``, SQLite), next to every trial's
run directories, so an interrupted search continues where it stopped when the same
command is run again; ``best.json`` holds the best settings found so far::

    pip install -c constraints.txt -e ".[tune]"
    rl-pg tune lunarlander --trials 30 --tune-seeds 0 1 --params lr gamma entropy_coeff \\
        --total-frames 300000 --run-dir runs/tune-lunarlander
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

from rl_pg._checks import require_extra
from rl_pg.checkpoint import write_atomically
from rl_pg.training.callbacks import Callback
from rl_pg.training.checkpoints import read_run
from rl_pg.training.config import Count, TrainConfig
from rl_pg.training.metric import Metric
from rl_pg.training.recipe import Recipe
from rl_pg.training.run_dir import locked
from rl_pg.training.seeds import replay_seed
from rl_pg.training.studies import (
    STUDY_LOCK,
    TRIAL_LOCK,
    abandoned,
    open_study,
    same_study,
    study_settings,
    trial_line,
)

__all__ = ["SEARCH_SPACE", "STUDY_LOCK", "TRIAL_LOCK", "TuneArgs", "tune"]

# What each tunable setting may take: ``trial -> value``. Ranges are those that make
# sense for the recipes' MLP policies; a setting the config lacks cannot be tuned.
SEARCH_SPACE: dict[str, Callable[[Any], Any]] = {
    "lr": lambda trial: trial.suggest_float("lr", 1e-4, 1e-2, log=True),
    "gamma": lambda trial: 1 - trial.suggest_float("one_minus_gamma", 1e-3, 5e-2, log=True),
    "entropy_coeff": lambda trial: trial.suggest_float("entropy_coeff", 1e-4, 5e-2, log=True),
    "critic_coeff": lambda trial: trial.suggest_float("critic_coeff", 0.25, 1.0),
    "max_grad_norm": lambda trial: trial.suggest_categorical("max_grad_norm", [0.5, 1.0, 5.0]),
    "segment_length": lambda trial: trial.suggest_categorical(
        "segment_length", [8, 16, 32, 64, 128, 256]
    ),
    "num_envs": lambda trial: trial.suggest_categorical("num_envs", [4, 8, 16, 32]),
    "normalize_advantage": lambda trial: trial.suggest_categorical(
        "normalize_advantage", [True, False]
    ),
    "returns": lambda trial: trial.suggest_categorical("returns", ["reward_to_go", "gae"]),
    "gae_lambda": lambda trial: trial.suggest_float("gae_lambda", 0.8, 1.0),
    "lr_schedule": lambda trial: trial.suggest_categorical("lr_schedule", ["constant", "linear"]),
    "reward_scale": lambda trial: trial.suggest_float("reward_scale", 1e-3, 1.0, log=True),
    "value_norm": lambda trial: trial.suggest_categorical("value_norm", ["none", "popart"]),
}
# The settings searched under another name: setting -> (Optuna's name, setting -> its value).
_SEARCHED_AS: dict[str, tuple[str, Callable[[Any], Any]]] = {
    "gamma": ("one_minus_gamma", lambda gamma: 1 - gamma),
}


@dataclasses.dataclass
class TuneArgs:
    """Search the recipe's hyperparameters with Optuna. Every other flag is the recipe's
    (rl-pg train RECIPE --help) and applies to every trial: the budget (--total-frames),
    the evaluations, the study directory (--run-dir)."""

    params: list[str]
    """The settings searched (names of SEARCH_SPACE that the recipe's config has)."""
    trials: int = 20
    """Trials the study should hold, completed or pruned."""
    tune_seeds: list[int] = dataclasses.field(default_factory=lambda: [0])
    """Seeds each trial trains on."""
    objective: Literal["final", "best", "held_out"] = "final"
    """Score a run by its last evaluation, its best, or held out. 'held_out': its best
    checkpoint replayed on held_out_episodes fresh episodes, greedily and by sampling
    (the worse of the two: a checkpoint that holds both ways). Scored on the runs'
    select_by (the mean return unless the recipe selects by another entry)."""
    held_out_episodes: Count = 100
    """Episodes of each replay (objective held_out)."""
    seed_score: Literal["mean", "worst"] = "mean"
    """A trial's score: the mean of its runs' scores, or the worst. The worst favours
    settings that work on every seed."""
    pruner: Literal["median", "none"] = "median"
    """Stop trials whose evaluations fall below the earlier trials' median; none: never."""
    jobs: Count = 1
    """Trials trained at once, each search a process of its own on the same study."""


def tune(
    recipe: Recipe,
    base: TrainConfig,
    *,
    params: Sequence[str],
    trials: int,
    seeds: Sequence[int] = (0,),
    objective: Literal["final", "best", "held_out"] = "final",
    held_out_episodes: int = 100,
    seed_score: Literal["mean", "worst"] = "mean",
    study_dir: Path,
    sampler_seed: int = 0,
    pruner: Literal["median", "none"] = "median",
    report: Callable[[str], None] | None = print,
) -> dict[str, Any]:
    """Searches ``params`` for the settings whose runs score highest.

    Args:
        recipe (Recipe): what to train.
        base (TrainConfig): the settings of every trial but the tuned ones (its budget,
            evaluations, ...); ``seed``, ``run_dir`` and ``resume`` are set per run.

    Keyword Args:
        params (sequence of str): the settings searched, names of ``SEARCH_SPACE``.
        trials (int): trials the study should hold, completed or pruned; a study
            that already holds some runs only the rest.
        seeds (sequence of int): seeds each trial trains on. Defaults to ``(0,)``.
        objective (str): ``"final"`` (each run's last evaluation, which rewards settings
            that stay good), ``"best"`` (its best evaluation) or ``"held_out"`` (its best
            checkpoint replayed on ``held_out_episodes`` fresh episodes, greedily and by
            sampling, as ``Recipe.evaluate_checkpoint`` plays it; the worse of the
            two). Every score is of ``base.select_by`` (the mean return by default), and
            a study maximises it (minimises it for ``select_mode="min"``). Defaults to
            ``"final"``.
        held_out_episodes (int): episodes of each replay (``"held_out"``). Defaults
            to ``100``.
        seed_score (str): ``"mean"`` or ``"worst"`` of the runs' scores. Defaults to
            ``"mean"``.
        study_dir (Path): where the study (``study.db``), the trials' runs
            (``trial<N>/seed<S>``) and ``best.json`` go.
        sampler_seed (int): seed of Optuna's TPE sampler in the study's first search;
            the study's n-th search uses ``sampler_seed + n``. Defaults to ``0``.
        pruner (str): ``"median"`` stops a trial whose evaluation falls below the
            median of the earlier trials' at the same point (Optuna's ``MedianPruner``,
            from the 6th trial on, after each run's second evaluation; runs of one
            trial are compared seed by seed); the reference trial trains whole.
            ``"none"`` trains every trial whole. Pruned trials do not count among
            ``trials``. Defaults to ``"median"``.
        report (callable, optional): called with one line as each trial ends (its
            score, its settings and the best so far); ``None`` is silent. Defaults to
            ``print``.

    A new study's first trial runs ``base``'s own values of ``params`` (when they lie in
    the search space): the reference the sampled trials are compared with.

    Returns:
        ``best.json``'s content: the best trial's number, score and settings (the
        recipe's flags), the number of completed trials and the reference trial's score.

    Raises:
        ImportError: Optuna is not installed (the message says how to install it).
        ValueError: an unknown or untunable setting, no seeds, fewer than one trial, or
            an unknown objective or seed score.
    """
    require_extra("optuna", "tune", "rl-pg tune (Optuna)")
    import optuna

    fields = {f.name for f in dataclasses.fields(base)}
    unknown = [p for p in params if p not in SEARCH_SPACE or p not in fields]
    if not params or unknown:
        tunable = sorted(name for name in SEARCH_SPACE if name in fields)
        raise ValueError(
            f"Cannot tune {unknown or 'nothing'}: pick settings of {recipe.name!r} among {tunable}."
        )
    if not seeds:
        raise ValueError("tune needs at least one seed (--tune-seeds 0 1 ...).")
    if trials < 1:
        raise ValueError(f"trials must be at least 1, got {trials}.")
    if objective not in ("final", "best", "held_out"):
        raise ValueError(f"objective must be 'final', 'best' or 'held_out', got {objective!r}.")
    if seed_score not in ("mean", "worst"):
        raise ValueError(f"seed_score must be 'mean' or 'worst', got {seed_score!r}.")
    if held_out_episodes < 1:
        raise ValueError(f"held_out_episodes must be at least 1, got {held_out_episodes}.")
    if pruner not in ("median", "none"):
        raise ValueError(f"pruner must be 'median' or 'none', got {pruner!r}.")

    metric = Metric.of(base)
    recipe.check_metric(metric)
    study_dir = Path(study_dir)
    study_dir.mkdir(parents=True, exist_ok=True)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    # One search at a time opens the study: two creating the SQLite tables at once
    # collide, and two would both fail a killed search's trial.
    with locked(study_dir / STUDY_LOCK, wait=True):
        study = open_study(recipe.name, study_dir / "study.db", metric)
        # Each search on the study (a second one beside it, or the same command run
        # again after a kill) draws its own settings: with one seed, its random first
        # trials would repeat the other's.
        same_study(study, study_settings(recipe, base, params, seeds, objective,
                                           held_out_episodes, seed_score), study_dir)  # fmt: skip
        searches = study.user_attrs.get("searches", 0)
        study.set_user_attr("searches", searches + 1)
        study.sampler = optuna.samplers.TPESampler(seed=sampler_seed + searches)
        study.pruner = (
            optuna.pruners.MedianPruner(n_startup_trials=5)
            if pruner == "median"
            else optuna.pruners.NopPruner()
        )
        reference, outside = _reference_params(base, params)
        if not study.trials and reference is not None:
            # The first trial runs the settings as given (the recipe's defaults, or the
            # flags): the yardstick every sampled trial is compared with.
            study.enqueue_trial(reference, user_attrs={"reference": True})
        elif not study.trials and report is not None:
            report(
                f"No reference trial: {outside}, outside the searched range, so no trial "
                f"can run the settings as given; the sampled trials compare among "
                f"themselves (set it inside the range to have one)."
            )
        for running in study.get_trials(states=[optuna.trial.TrialState.RUNNING]):
            if abandoned(running, study_dir):  # not a live search's: a killed one's
                study.tell(running.number, state=optuna.trial.TrialState.FAIL)

    def score(summary: dict[str, Any], run_dir: Path) -> dict[str, float]:
        if objective == "final":
            return {"score": float(summary["eval_value"])}
        if objective == "best":
            return {"score": float(summary["best_eval_value"])}
        saved = read_run(run_dir, which="best")
        replays = {
            mode: recipe.evaluate_checkpoint(
                saved, episodes=held_out_episodes, sample=mode == "sampled",
                seed=replay_seed(saved["config"]["seed"]),
            )[metric.key]
            for mode in ("greedy", "sampled")
        }  # fmt: skip
        return {"score": metric.worst(replays.values()), **replays}

    def run_trial(trial) -> float:
        trial_dir = study_dir / f"trial{trial.number}"
        trial_dir.mkdir(exist_ok=True)
        with locked(trial_dir / TRIAL_LOCK):  # a new number: no other search has it
            return run_seeds(trial, trial_dir)

    def run_seeds(trial, trial_dir: Path) -> float:
        settings = _settings(trial, params, base)
        trial.set_user_attr("settings", settings)
        scores, runs = [], {}
        for position, seed in enumerate(seeds):
            run_dir = trial_dir / f"seed{seed}"
            cfg = dataclasses.replace(
                base, **settings, seed=seed, run_dir=run_dir, resume=False, progress=False
            )
            judge = _Pruning(trial, position)
            summary = recipe.train(cfg, callbacks=[] if _is_reference(trial) else [judge])
            if judge.pruned:
                trial.set_user_attr("pruned_at", {"seed": seed, "frames": summary["frames"]})
                raise optuna.TrialPruned()
            runs[str(seed)] = score(summary, run_dir)
            scores.append(runs[str(seed)]["score"])
            trial.set_user_attr("scores", scores)
            trial.set_user_attr("runs", runs)  # with held_out, the greedy and sampled means
        return min(scores) if seed_score == "worst" else statistics.fmean(scores)

    complete = (optuna.trial.TrialState.COMPLETE,)
    finished = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)
    if len(study.get_trials(states=finished)) < trials:
        # Until the study holds `trials` finished ones, counting those of any other
        # search running on the same directory (each finishes the trial it is in).
        done = [optuna.study.MaxTrialsCallback(trials, finished)]
        if report is not None:
            done.append(lambda study, trial: report(trial_line(study, trial, trials)))
        study.optimize(run_trial, callbacks=done)
    best = study.best_trial
    result = {
        "recipe": recipe.name,
        "objective": objective,
        "seed_score": seed_score,
        "seeds": list(seeds),
        "trials": len(study.get_trials(states=finished)),
        "pruned": len(study.get_trials(states=[optuna.trial.TrialState.PRUNED])),
        "best_trial": best.number,
        "best_score": best.value,
        "best_scores": best.user_attrs.get("scores"),
        "best_runs": best.user_attrs.get("runs"),
        "best_settings": best.user_attrs["settings"],
        "reference_score": next(
            (t.value for t in study.get_trials(states=complete) if t.user_attrs.get("reference")),
            None,
        ),
    }
    write_atomically(study_dir / "best.json", json.dumps(result, indent=2))
    return result


def _settings(trial, params: Sequence[str], base: TrainConfig) -> dict[str, Any]:
    """The values ``trial`` gives ``params``."""
    settings = {}
    for name in sorted(params, key=lambda name: name == "gae_lambda"):  # λ after returns
        if name == "gae_lambda" and settings.get("returns", base.returns) != "gae":
            continue  # read by GAE alone: not a dimension of trials without it
        settings[name] = SEARCH_SPACE[name](trial)
    return settings


def _reference_params(
    base: TrainConfig, params: Sequence[str]
) -> tuple[dict[str, Any] | None, str | None]:
    """``base``'s own values of ``params`` as Optuna's parameters, or ``None`` and the
    first setting that lies outside the search space (no trial can run it then)."""
    import optuna

    values = {}
    for name in params:
        key, to_param = _SEARCHED_AS.get(name, (name, lambda value: value))
        values[key] = to_param(getattr(base, name))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # a float out of its range only warns
                _settings(optuna.trial.FixedTrial(values), params[: params.index(name) + 1], base)
        except (ValueError, UserWarning):
            return None, f"{name} is {getattr(base, name)!r}"
    return values, None


WARMUP_EVALUATIONS = 2
"""A run's first evaluations, which the pruner never judges (early curves cross)."""
_SEED_STEPS = 1_000_000
"""Evaluations one run may report before the next seed's: run k's i-th is step k*this+i."""


class _Pruning(Callback):
    """Reports each evaluation of a trial's run to Optuna and stops the run when its
    pruner says so. A trial's runs report one after the other, seed by seed, so each is
    compared with the other trials' runs of the same seed at the same evaluation."""

    key = "tune_pruning"

    def __init__(self, trial, position: int) -> None:
        self.trial, self.offset = trial, position * _SEED_STEPS
        self.evaluations, self.pruned = 0, False

    def on_evaluation(self, run, result: dict[str, float]) -> None:
        self.trial.report(float(run.metric.read(result)), self.offset + self.evaluations)
        self.evaluations += 1
        if self.evaluations > WARMUP_EVALUATIONS:
            self.pruned = self.trial.should_prune()

    def stop_training(self, run) -> bool:
        return self.pruned


def _is_reference(trial) -> bool:
    """Whether a trial runs the settings as given (enqueued first, never pruned)."""
    return bool(trial.user_attrs.get("reference"))
