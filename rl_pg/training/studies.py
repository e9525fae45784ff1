"""The Optuna study a search lives in: what makes its trials' scores comparable,
opening it, refusing a search that would join it with other settings, each trial's
line, and the trials left running by a process that died."""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any

from rl_pg.training.config import config_dict
from rl_pg.training.metric import Metric
from rl_pg.training.run_dir import locked

__all__ = [
    "STUDY_LOCK",
    "TRIAL_LOCK",
    "UNSCORED_FIELDS",
    "abandoned",
    "open_study",
    "same_study",
    "study_settings",
    "trial_line",
]

STUDY_LOCK = ".study.lock"
"""Held in the study directory while a search opens the study."""
TRIAL_LOCK = ".trial.lock"
"""Held in ``trial<N>/`` by the process running the trial: a trial left running whose
lock is free was cut short (its process died) and is marked failed."""

UNSCORED_FIELDS = frozenset(
    {"seed", "run_dir", "resume", "progress", "threads", "tensorboard", "wandb",
     "wandb_project", "wandb_mode", "mlflow", "mlflow_uri"}
)  # fmt: skip
"""Config fields that do not change what a trial scores (where and how it is watched)."""


def study_settings(
    recipe, base, params, seeds, objective, held_out_episodes, seed_score
) -> dict[str, Any]:
    """What makes two trials' scores comparable: the recipe, the searched settings,
    the seeds, the objective and every other setting of the runs."""
    fixed = {
        key: value
        for key, value in config_dict(base).items()
        if key not in UNSCORED_FIELDS and key not in params
    }
    return {
        "recipe": recipe.name,
        "params": sorted(params),
        "seeds": list(seeds),
        "objective": objective,
        "held_out_episodes": held_out_episodes if objective == "held_out" else None,
        "seed_score": seed_score,
        "fixed": fixed,
    }


def open_study(name: str, path: Path, metric: Metric | None = None):
    """The study stored in ``path`` (created if absent) that maximises ``metric`` (the
    mean return by default; minimises one whose lowest value is best), or a
    ValueError naming the file when it is not one this Optuna can open (another file,
    a damaged one, a newer Optuna's, one that scores the other way)."""
    import optuna
    from sqlalchemy.exc import SQLAlchemyError

    metric = metric or Metric()
    direction = "maximize" if metric.mode == "max" else "minimize"
    try:
        study = optuna.create_study(
            study_name=name, storage=f"sqlite:///{path}", load_if_exists=True,
            direction=direction,
        )  # fmt: skip
    except (SQLAlchemyError, RuntimeError) as err:  # RuntimeError: another schema version
        reason = str(getattr(err, "orig", None) or err).splitlines()[0]
        raise ValueError(
            f"{path} is not a study this Optuna can open ({reason}). Move it away to start "
            f"a new study there, or pass another --study-dir."
        ) from err
    if study.direction.name.lower() != direction:  # a stored study keeps its own
        raise ValueError(
            f"{path} holds a study that {study.direction.name.lower()}s its score, and "
            f"--select-by {metric} asks to {direction} it. Select as its trials were "
            f"scored, or pass another --study-dir."
        )
    return study


def trial_line(study, trial, trials: int) -> str:
    """One line when a trial ends: its score and settings, and the best so far."""
    import optuna

    states = optuna.trial.TrialState
    finished = len(study.get_trials(states=(states.COMPLETE, states.PRUNED)))
    settings = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                         for k, v in trial.user_attrs.get("settings", {}).items())  # fmt: skip
    if trial.state == states.PRUNED:
        at = trial.user_attrs.get("pruned_at", {})
        return (
            f"trial {trial.number} ({finished} of {trials} done) pruned at "
            f"{at.get('frames', 0):,} frames of seed {at.get('seed')}: below the median "
            f"of the trials before it ({settings})"
        )
    if trial.state != states.COMPLETE:
        return f"trial {trial.number} {trial.state.name.lower()} ({settings})"
    best = study.best_trial
    return (
        f"trial {trial.number} ({finished} of {trials} done): score {trial.value:.2f} "
        f"with {settings}; best so far: trial {best.number}, {best.value:.2f}"
    )


def same_study(study, settings: dict[str, Any], study_dir: Path) -> None:
    """Records the settings of a new study; refuses a search that would join a study
    made with other ones (its trials' scores would not compare)."""
    stored = study.user_attrs.get("settings")
    if stored is None:
        if not study.trials:  # a new study: what every later search must match
            study.set_user_attr("settings", settings)
        return
    changed = [f"{key}: {stored.get(key)!r} -> {settings[key]!r}" for key in
               ("recipe", "params", "seeds", "objective", "held_out_episodes", "seed_score")
               if stored.get(key) != settings[key]]  # fmt: skip
    fixed = stored.get("fixed", {})
    changed += [
        f"--{key.replace('_', '-')}: {fixed.get(key)!r} -> {value!r}"
        for key, value in settings["fixed"].items()
        if key in fixed and fixed[key] != value
    ]
    if changed:
        raise ValueError(
            f"{study_dir} holds a study made with other settings ({'; '.join(changed)}): "
            f"its trials' scores would not compare with this search's. Run it with the "
            f"study's settings, or give this search another --run-dir."
        )


def abandoned(trial, study_dir: Path) -> bool:
    """Whether a trial the study lists as running has no live process running it."""
    lock = study_dir / f"trial{trial.number}" / TRIAL_LOCK
    if lock.exists():
        with locked(lock) as free:
            return free
    # No lock yet: a search that has just asked for it, or one killed before it
    # locked (or older than trial locks). Only the first is young.
    started = trial.datetime_start
    return started is None or datetime.datetime.now() - started > datetime.timedelta(minutes=1)
