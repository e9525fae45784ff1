"""What resuming a run may change: the stored configuration against the new one, field
by field, the fields that may change (``RESUMABLE_FIELDS``) and those of them that
change what the rest of the run computes, and the budget left."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from rl_pg.checkpoint import CheckpointError
from rl_pg.training.config import RESUMABLE_FIELDS, TrainConfig, config_dict

__all__ = ["TRAJECTORY_FIELDS", "changed_on_resume", "changed_settings", "check_resumable"]


def check_resumable(cfg: TrainConfig, recipe: str, saved: dict, checkpoint_path: Path) -> None:
    """Refuses to resume ``saved`` (the checkpoint at ``checkpoint_path``) as a run of
    ``recipe`` with ``cfg``: another recipe's, another configuration (bar the
    ``RESUMABLE_FIELDS``), or a budget already spent.

    Raises:
        CheckpointError: the message says which, and how to resume.
    """
    if saved.get("recipe") != recipe:
        raise CheckpointError(
            f"{checkpoint_path} was written by recipe {saved.get('recipe')!r}, not "
            f"{recipe!r}; resume it with that recipe."
        )
    changed = changed_settings(cfg, saved["config"])
    if changed:
        details = ", ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in changed.items())
        raise CheckpointError(
            f"Cannot resume {checkpoint_path} with a different configuration ({details}). "
            f"Only {sorted(RESUMABLE_FIELDS)} may change on resume."
        )
    _check_budget_left(cfg, saved["state"], checkpoint_path.parent)


def changed_settings(
    cfg: TrainConfig, stored: dict[str, Any], *, may_change: frozenset[str] = RESUMABLE_FIELDS
) -> dict[str, tuple[Any, Any]]:
    """The fields of ``cfg`` that differ from a run's stored config (``{name: (stored,
    now)}``; a field newer than the run at the value it had then), but ``may_change``."""
    stored = type(cfg).as_run(stored)
    return {
        key: (stored.get(key), value)
        for key, value in config_dict(cfg).items()
        if key not in may_change and stored.get(key) != value
    }


TRAJECTORY_FIELDS = {
    "workers": "collection is split differently between processes",
    "ray": "collection runs elsewhere",
    "device": "the arithmetic runs on other hardware",
    "threads": "torch's reductions may add in another order",
}
"""Resumable fields that change what the rest of the run computes: a run resumed with
another value goes on, but no longer ends as the uninterrupted run would."""


def changed_on_resume(cfg: TrainConfig, saved: dict) -> dict[str, list]:
    """The resumable fields the resume changes (``{field: [stored, new]}``); says on
    stderr which of them change the run's results."""
    stored = type(cfg).as_run(saved["config"])
    changed = {
        key: [stored.get(key), value]
        for key, value in config_dict(cfg).items()
        if key in RESUMABLE_FIELDS and key not in ("resume", "run_dir")
        and stored.get(key) != value
    }  # fmt: skip
    for key, why in TRAJECTORY_FIELDS.items():
        if key in changed:
            old, new = changed[key]
            print(
                f"Resuming with {key} {old!r} -> {new!r}: the run goes on, but {why}, so it "
                f"will not end as the uninterrupted run would (the summary's sessions record "
                f"the change).",
                file=sys.stderr,
            )
    return changed


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
