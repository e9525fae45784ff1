"""What a run's checkpoint holds, and loading one back (to resume, or to deploy)."""

from __future__ import annotations

import dataclasses
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from rl_pg.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from rl_pg.normalization import popart_output
from rl_pg.training.config import config_dict
from rl_pg.training.metric import Metric
from rl_pg.training.records import check_values
from rl_pg.training.seeds import run_streams

__all__ = [
    "BEST",
    "CHECKPOINT",
    "LATEST",
    "POLICY_AVERAGE",
    "RunState",
    "callback_states",
    "load_models",
    "read_run",
    "resolve_latest",
    "restore",
    "restore_rng",
    "save",
]

CHECKPOINT = "checkpoint.pt"
"""The last checkpoint: what a run resumes from."""
BEST = "best.pt"
"""The checkpoint of the best evaluation so far: what is deployed by default."""
POLICY_AVERAGE = "policy_average"
"""Where a checkpoint keeps the average of the policy's weights (``policy_ema``): the
[`PolicyAverage`][rl_pg.training.selection.PolicyAverage] callback's key."""


@dataclass
class RunState:
    """Everything about the run's progress that a checkpoint must restore."""

    frames: int = 0
    updates: int = 0
    train_time: float = 0.0
    solved_at_frames: int | None = None
    last_eval: dict[str, float] = field(default_factory=dict)
    best_eval: dict[str, float] = field(default_factory=dict)
    """The evaluation ``best.pt`` was kept at (empty until one was kept)."""
    best_at_frames: int | None = None
    best_confirmed: float | None = None
    streams: dict[str, int] = field(default_factory=dict)
    """The seeds of the run's evaluations and confirmations
    ([`run_streams`][rl_pg.training.seeds.run_streams]), fixed when the run starts."""

    def best(self, metric: Metric) -> float | None:
        """The ``metric``'s value at the kept evaluation (None before one was kept)."""
        return metric.read(self.best_eval) if self.best_eval else None

    def is_best(self, metric: Metric) -> bool:
        """Takes in the last evaluation; True if it beat every earlier one on ``metric``
        (and no confirmed evaluation has been kept: from the first on, only
        confirmations count)."""
        if self.best_confirmed is not None or not metric.better(
            metric.read(self.last_eval), than=self.best(metric)
        ):
            return False
        self.best_eval, self.best_at_frames = dict(self.last_eval), self.frames
        return True

    def worth_confirming(self, metric: Metric, threshold: float | None) -> bool:
        """Whether the last evaluation could beat the best confirmed one on ``metric``:
        at ``threshold`` or better (if any) and better than the best confirmed score."""
        value = metric.read(self.last_eval)
        return (threshold is None or metric.reaches(value, threshold)) and metric.better(
            value, than=self.best_confirmed
        )

    def is_best_confirmed(self, metric: Metric, score: float) -> bool:
        """Takes in the last evaluation's confirmation ``score`` (on ``metric``); True if
        it beat every earlier confirmation."""
        if not metric.better(score, than=self.best_confirmed):
            return False
        self.best_confirmed = score
        self.best_eval, self.best_at_frames = dict(self.last_eval), self.frames
        return True


def save(
    cfg, recipe: dict[str, str | None], loss, optimizer, state: RunState, path: Path, **parts
) -> None:
    """Writes the run's checkpoint (atomically, with a checksum) to ``path``.

    ``recipe`` names the recipe (``"recipe"``) and the module defining it
    (``"recipe_module"``), so that the run can be rebuilt to play it; ``parts`` are
    the states of the run's other pieces (collection, episode counters).
    """
    save_checkpoint(
        {
            **recipe,
            **parts,
            "config": config_dict(cfg),
            "loss": loss.state_dict(),
            "optimizer": optimizer.state_dict(),
            "state": dataclasses.asdict(state),
            "rng": {
                "torch": torch.get_rng_state(),
                "numpy": _numpy_state(),
                "random": random.getstate(),
            },
        },
        path,
    )


def restore(saved: dict, loss, optimizer, path: Path) -> RunState:
    """Loads a checkpoint into the run's loss and optimiser and returns the run's
    progress (``restore_rng`` then restores the random number generators; the
    callbacks take their states from
    [`callback_states`][rl_pg.training.checkpoints.callback_states])."""
    try:
        loss.load_state_dict(saved["loss"])
        optimizer.load_state_dict(saved["optimizer"])
    except (RuntimeError, ValueError, KeyError) as err:
        raise CheckpointError(
            f"{path} does not fit the models this configuration builds "
            f"({_first_line(err)}). It was left as it is; resume it with the configuration "
            f"that wrote it."
        ) from err
    # Checkpoints of earlier versions also carried the curve, now read from the logs.
    fields = {f.name for f in dataclasses.fields(RunState)}
    stored = saved["state"]
    state = RunState(**{k: v for k, v in stored.items() if k in fields})
    if stored.get("best_mean_return") is not None and not state.best_eval:
        # Written before runs chose a metric: they kept their best mean return.
        state.best_eval = {"eval/mean_return": stored["best_mean_return"]}
    if not state.streams:  # checkpointed before the run kept them: the ones it played
        state.streams = run_streams(saved["config"]["seed"], stored_before_layout=True)
    return state


def restore_rng(saved: dict) -> None:
    """Sets torch's, numpy's and Python's generators to the checkpoint's states."""
    torch.set_rng_state(saved["rng"]["torch"])
    np.random.set_state(_numpy_state_of(saved["rng"]["numpy"]))
    random.setstate(saved["rng"]["random"])


def _numpy_state() -> dict[str, Any]:
    """numpy's global generator state as a tensor and plain data (what a weights-only
    load reads back), not the pickled array ``np.random.get_state()`` holds."""
    state = np.random.get_state(legacy=False)
    return {
        **state,
        "state": {
            **state["state"],
            "key": torch.from_numpy(state["state"]["key"].astype(np.int64)),
        },
    }


def _numpy_state_of(saved) -> dict[str, Any] | tuple:
    """What ``np.random.set_state`` takes, from either form checkpoints have held."""
    if isinstance(saved, tuple):  # earlier checkpoints: get_state()'s own tuple
        return saved
    key = saved["state"]["key"].numpy().astype(np.uint32)
    return {**saved, "state": {**saved["state"], "key": key}}


LATEST = "latest"
"""The file beside the time-stamped run directories that names the newest of them."""


def resolve_latest(path: str | Path) -> Path:
    """The run directory a ``latest`` file names (see
    [`link_latest`][rl_pg.training.run_dir.link_latest]), or ``path`` itself when it is
    not such a file.

    Raises:
        CheckpointError: the file names no run directory beside it (the message says
            what it holds).
    """
    path = Path(path)
    if path.name != LATEST or path.is_symlink() or not path.is_file():
        return path
    try:
        name = path.read_text(encoding="utf-8").strip() if path.stat().st_size < 4096 else ""
    except (OSError, UnicodeDecodeError):
        name = ""
    target = path.parent / name
    if not name or Path(name).name != name or name in (".", "..") or not target.is_dir():
        raise CheckpointError(
            f"{path} should name the newest run directory beside it, and holds "
            f"{name[:80]!r}, which is none: give the run directory itself."
        )
    return target


def read_run(run: str | Path, *, which: str = "last") -> dict[str, Any]:
    """A checkpoint of a run directory (or a checkpoint file itself).

    Keyword Args:
        which (str): ``"last"`` (``checkpoint.pt``, what a run resumes from) or
            ``"best"`` (``best.pt``, the best evaluation so far). Ignored when ``run``
            is a file. Defaults to ``"last"``.

    Raises:
        CheckpointError: missing or corrupted checkpoint.
        ValueError: an unknown ``which``.

    Examples:
        >>> import tempfile
        >>> from rl_pg.training import read_run
        >>> read_run(tempfile.mkdtemp())  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        rl_pg.checkpoint.CheckpointError: ... holds no checkpoint.pt: not a run directory, ...
        >>> read_run("runs/nothing-here")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        rl_pg.checkpoint.CheckpointError: runs/nothing-here does not exist: give a run ...
    """
    files = {"last": CHECKPOINT, "best": BEST}
    if which not in files:
        raise ValueError(f"which must be 'last' or 'best', got {which!r}.")
    path = resolve_latest(run)  # runs/latest: the newest run
    if not path.exists():
        raise CheckpointError(f"{path} does not exist: give a run directory or a checkpoint file.")
    if not path.is_dir():
        return _checked(load_checkpoint(path), path)
    if not (path / files[which]).is_file() and not (path / CHECKPOINT).is_file():
        raise CheckpointError(
            f"{path} holds no {files[which]}: not a run directory, or its run stopped "
            f"before its first checkpoint; give a run directory or a checkpoint file."
        )
    if which == "best" and not (path / BEST).is_file() and (path / CHECKPOINT).is_file():
        raise CheckpointError(
            f"{path} has no {BEST} (the run never evaluated, or predates best "
            f"checkpoints); deploy its last checkpoint with which='last'."
        )
    return _checked(load_checkpoint(path / files[which]), path / files[which])


RUN_CHECKPOINT = {"recipe": "text", "recipe_module?": "text?", "config": "object",
                  "loss": "object", "state?": "object"}  # fmt: skip
"""What every checkpoint and agent file of a run holds (the rest is checked by what reads
it: the config by the recipe's config class, the weights by the models)."""
CHECKPOINT_STATE = {"frames?": "count?", "updates?": "count?", "best_mean_return?": "number?",
                    "best_eval?": "object"}  # fmt: skip


def _first_line(err: BaseException) -> str:
    """Of torch's "Error(s) in loading state_dict" (a line per mismatch), the first
    mismatch; any other error as it is."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    if len(lines) > 1 and lines[0].startswith("Error(s) in loading state_dict"):
        return lines[1].rstrip(".")
    return " ".join(lines)


def _checked(saved: dict[str, Any], path: Path) -> dict[str, Any]:
    """``saved`` when its fields hold values of their kinds; else a CheckpointError that
    names the file and the field."""
    try:
        check_values(saved, RUN_CHECKPOINT, str(path))
        check_values(saved.get("state", {}), CHECKPOINT_STATE, f"{path}, state")
        bad = [k for k, v in saved["loss"].items() if not isinstance(v, torch.Tensor)]
        if bad:
            raise ValueError(f'{path}: "loss" should hold tensors, and {bad[0]!r} is not one.')
    except ValueError as err:
        raise CheckpointError(f"{err} It is not a checkpoint rl_pg wrote, or was edited.") from None
    return saved


def callback_states(saved: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The states of a checkpoint's callbacks, by key. Checkpoints written before the
    policy average became a callback keep it at their top level; it is read from there."""
    states = dict(saved.get("callbacks", {}))
    if POLICY_AVERAGE in saved:
        states.setdefault(POLICY_AVERAGE, {"weights": saved[POLICY_AVERAGE]})
    return states


def _averaged_weights(saved: dict[str, Any]) -> dict[str, torch.Tensor] | None:
    """The ``AveragedModel`` state of a run trained with ``policy_ema`` (None without)."""
    state = callback_states(saved).get(POLICY_AVERAGE)
    return None if state is None else state["weights"]


def has_average(saved: dict[str, Any]) -> bool:
    """Whether the checkpoint keeps an average of the policy's weights (``policy_ema``)."""
    return _averaged_weights(saved) is not None


def check_average(saved: dict[str, Any], average: bool) -> None:
    """Raises CheckpointError if ``average=False`` asks for the trained weights of a
    checkpoint that keeps no average (see
    [`load_models`][rl_pg.training.checkpoints.load_models])."""
    if not average and not has_average(saved):
        raise CheckpointError(
            "This checkpoint keeps no average of the policy's weights (its run trained "
            "without policy_ema): its trained weights are the ones loaded anyway; "
            "leave average=False (--trained-weights) out."
        )


def load_models(
    saved: dict[str, Any],
    actor: nn.Module,
    critic: nn.Module | None = None,
    *,
    average: bool = True,
) -> None:
    """Loads a checkpoint's weights into freshly built models.

    The actor gets the averaged weights of a run trained with ``policy_ema`` (those its
    evaluations played), otherwise the trained ones. A critic trained with
    ``value_norm='popart'`` gets its [`PopArt`][rl_pg.normalization.PopArt] output layer
    first, as in training.

    The checkpoint comes from [`read_run`][rl_pg.training.checkpoints.read_run].

    Keyword Args:
        average (bool): give the actor the averaged weights where the checkpoint has
            them; ``False`` gives it the trained ones (which played the training
            episodes), to compare the two. Defaults to ``True``.

    Raises:
        CheckpointError: the weights do not fit the models, or ``average=False`` asks
            for the trained weights of a checkpoint that keeps no average (its trained
            weights are the ones loaded anyway).

    Examples:
        >>> import torch
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor
        >>> from rl_pg.training import load_models
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
    if critic is not None and saved.get("config", {}).get("value_norm") == "popart":
        popart_output(critic)  # as make_loss built it for training

    def part(source: dict, prefix: str) -> dict:
        return {k.removeprefix(prefix): v for k, v in source.items() if k.startswith(prefix)}

    check_average(saved, average)
    averaged = _averaged_weights(saved)  # an AveragedModel's: the actor's under "module."
    parts = {
        "actor": (actor, part(averaged, "module.") if average and averaged is not None
                  else part(saved["loss"], "actor_network.")),
        "critic": (critic, part(saved["loss"], "critic_network.")),
    }  # fmt: skip
    for name, (module, weights) in parts.items():
        if module is None:
            continue
        try:
            module.load_state_dict(weights)
        except RuntimeError as err:
            raise CheckpointError(
                f"The checkpoint's {name} does not fit the model built from its config "
                f"({_first_line(err)}): its weights were edited, or come from another model."
            ) from err
