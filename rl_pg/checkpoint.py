"""Checkpoints that are written atomically and fail loudly when they cannot be used."""

from __future__ import annotations

import os
import pickle
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import torch

__all__ = ["FORMAT", "CheckpointError", "load_checkpoint", "save_checkpoint"]

FORMAT = 1
"""Version of the checkpoint layout; bumped when it changes incompatibly."""


class CheckpointError(RuntimeError):
    """A checkpoint is missing, corrupted, or belongs to another run configuration."""


def save_checkpoint(state: dict[str, Any], path: str | Path) -> Path:
    """Writes ``state`` to ``path`` atomically: a temporary file, fsync, then a rename.

    A reader (or a run killed half-way through the write) sees either the previous
    checkpoint or the new one, never a torn file.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> from rl_pg.checkpoint import load_checkpoint, save_checkpoint
        >>> path = Path(tempfile.mkdtemp()) / "checkpoint.pt"
        >>> _ = save_checkpoint({"frames": 10, "weights": torch.ones(2)}, path)
        >>> load_checkpoint(path)["frames"]
        10
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as file:
            torch.save({**state, "format": FORMAT}, file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)  # make the rename itself durable
    finally:
        os.close(directory)
    return path


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Reads a checkpoint written by [`save_checkpoint`][rl_pg.checkpoint.save_checkpoint].

    Raises:
        CheckpointError: when the file is missing or cannot be read; the file is left
            untouched.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"No checkpoint at {path}.")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError) as err:
        raise CheckpointError(
            f"The checkpoint {path} is corrupted and cannot be read ({err}). It was left as "
            f"it is; restore it from a backup, or start a new run in another --run-dir."
        ) from err
    if not isinstance(state, dict) or "format" not in state:
        raise CheckpointError(f"{path} is not an rl_pg checkpoint.")
    if state["format"] != FORMAT:
        raise CheckpointError(
            f"{path} has checkpoint format {state['format']}, this rl_pg reads format "
            f"{FORMAT}. Resume it with the rl_pg version that wrote it."
        )
    return state
