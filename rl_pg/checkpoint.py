"""Checkpoints that are written atomically, carry a checksum, and fail loudly when they
cannot be used.

A checkpoint file is a short header followed by the ``torch.save`` bytes of the state::

    b"RLPGCKPT" | format (4 bytes, little endian) | SHA-256 of the payload | payload

[`load_checkpoint`][rl_pg.checkpoint.load_checkpoint] recomputes the digest before it
unpickles anything, so a file damaged on disk (a flipped byte, a truncated copy) is an
error instead of weights that load and play wrong. The digest proves a file whole, not
who made it: the state is read with ``torch.load(weights_only=True)``, which rebuilds
tensors and plain Python data (and, for files of earlier versions, numpy arrays) and
refuses anything else, so a file shared by somebody else cannot run code when it loads.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import re
import stat
import tempfile
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = [
    "FORMAT",
    "CheckpointError",
    "clean_temporary_files",
    "load_checkpoint",
    "save_checkpoint",
    "write_atomically",
]

FORMAT = 2
"""Version of the checkpoint layout; bumped when it changes incompatibly."""
_MAGIC = b"RLPGCKPT"
_HEADER = len(_MAGIC) + 4 + hashlib.sha256().digest_size
_TEMPORARY_SUFFIX = ".rl_pg-tmp"


class CheckpointError(RuntimeError):
    """A checkpoint is missing, corrupted, or belongs to another run configuration."""


def write_atomically(path: str | Path, data: bytes | str) -> Path:
    """Replaces ``path`` by ``data`` so that a reader, or a process killed half-way,
    sees the old file or the new one, never a torn one.

    The bytes go to a temporary file in the same directory, are flushed to disk, then
    renamed over ``path`` (a rename within a file system is atomic).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.checkpoint import write_atomically
        >>> path = write_atomically(Path(tempfile.mkdtemp()) / "summary.json", "{}")
        >>> path.read_text()
        '{}'
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=_TEMPORARY_SUFFIX)
    try:
        if hasattr(os, "fchmod"):  # mkstemp's 0600 would make the file private
            os.fchmod(fd, _mode_for(path))
        with os.fdopen(fd, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if hasattr(os, "O_DIRECTORY"):  # make the rename itself durable (POSIX)
        directory = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)
    return path


def _mode_for(path: Path) -> int:
    """The permissions a file written to ``path`` gets: those of the file it replaces,
    else those ``open`` would give a new file (0666 less the umask)."""
    try:
        return stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def clean_temporary_files(directory: str | Path) -> list[Path]:
    """Deletes what writes killed half-way left in ``directory`` (recursively).

    Only call this while no other process writes there (e.g. under a run's lock).

    Returns:
        The files removed.
    """
    removed = []
    for tmp in Path(directory).rglob(f".*{_TEMPORARY_SUFFIX}"):
        tmp.unlink(missing_ok=True)
        removed.append(tmp)
    return removed


def save_checkpoint(state: dict[str, Any], path: str | Path) -> Path:
    """Writes ``state`` to ``path`` atomically, with a checksum of its contents.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> from rl_pg.checkpoint import load_checkpoint, save_checkpoint
        >>> path = Path(tempfile.mkdtemp()) / "checkpoint.pt"
        >>> _ = save_checkpoint({"frames": 10, "weights": torch.ones(2)}, path)
        >>> load_checkpoint(path)["frames"]
        10
    """
    if not isinstance(state, dict):
        raise TypeError(f"save_checkpoint saves a dict of state, got {type(state).__name__}.")
    buffer = io.BytesIO()
    torch.save({**state, "format": FORMAT}, buffer)
    payload = buffer.getvalue()
    with torch.serialization.safe_globals(_NUMPY_DATA):
        foreign = torch.serialization.get_unsafe_globals_in_checkpoint(io.BytesIO(payload))
    if foreign:  # a file that needs them could not be loaded again: say so now
        raise TypeError(
            f"save_checkpoint saves tensors and plain data (dicts, lists, numbers, "
            f"strings, numpy arrays), which load without running code; the state holds "
            f"{', '.join(sorted(foreign))}. Store its state_dict() or plain values instead."
        )
    header = _MAGIC + FORMAT.to_bytes(4, "little") + hashlib.sha256(payload).digest()
    return write_atomically(path, header + payload)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Reads and verifies a checkpoint written by
    [`save_checkpoint`][rl_pg.checkpoint.save_checkpoint].

    Raises:
        CheckpointError: when the file is missing, is not an rl_pg checkpoint, has
            another format, or its contents do not match its checksum; the file is
            left untouched.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> from rl_pg.checkpoint import load_checkpoint, save_checkpoint
        >>> path = save_checkpoint({"w": torch.zeros(4)}, Path(tempfile.mkdtemp()) / "c.pt")
        >>> data = bytearray(path.read_bytes())
        >>> data[-20] ^= 0xFF  # one damaged byte
        >>> _ = path.write_bytes(bytes(data))
        >>> load_checkpoint(path)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        rl_pg.checkpoint.CheckpointError: The checkpoint ... is corrupted: ...
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"No checkpoint at {path}.")
    data = path.read_bytes()
    if not data:
        _raise_corrupted(path, "the file is empty")
    if not data.startswith(_MAGIC):
        return _load_unverified(path)
    if len(data) < _HEADER:
        _raise_corrupted(path, "the file is shorter than its header")
    version = int.from_bytes(data[len(_MAGIC) : len(_MAGIC) + 4], "little")
    if version != FORMAT:
        raise CheckpointError(
            f"{path} has checkpoint format {version}, this rl_pg reads format {FORMAT}. "
            f"Resume it with the rl_pg version that wrote it."
        )
    digest, payload = data[len(_MAGIC) + 4 : _HEADER], data[_HEADER:]
    if hashlib.sha256(payload).digest() != digest:
        _raise_corrupted(path, "its contents do not match the checksum written with them")
    return _unpickle(path, io.BytesIO(payload))


def _load_unverified(path: Path) -> dict[str, Any]:
    """Format 1 (before checksums): a bare ``torch.save`` of the state."""
    state = _unpickle(path, path)
    if state.get("format") != 1:
        raise CheckpointError(
            f"{path} has checkpoint format {state['format']}, this rl_pg reads format "
            f"{FORMAT}. Resume it with the rl_pg version that wrote it."
        )
    warnings.warn(
        f"{path} was written before checkpoints carried a checksum (format 1): it loads, "
        f"but its integrity cannot be verified. It is rewritten in format {FORMAT} at the "
        f"next checkpoint of a resumed run.",
        stacklevel=3,
    )
    return state


# Earlier versions stored numpy's generator state as a pickled array: data, not code.
# numpy 2 moved its array constructor from numpy.core to numpy._core; a file names the
# module it was written with.
_reconstruct = np.ndarray.__reduce__(np.zeros(1))[0]
_scalar = np.float64(0).__reduce__()[0]
_NUMPY_DATA = [
    np.ndarray,
    np.dtype,
    *{type(np.dtype(code)) for code in np.typecodes["All"] if code != "O"},
    *[
        (f, f"numpy.{core}.multiarray.{f.__name__}")
        for f in (_reconstruct, _scalar)
        for core in ("core", "_core")
    ],
]


def _unpickle(path: Path, source) -> dict[str, Any]:
    """The state, read with ``weights_only=True``: tensors and plain data only."""
    try:
        with torch.serialization.safe_globals(_NUMPY_DATA):
            state = torch.load(source, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        # torch names what a weights-only load refused: "... GLOBAL posix.system ..."
        refused = re.search(r"GLOBAL ([\w.]+)", str(err))
        if refused is None:
            _raise_corrupted(path, f"it cannot be read ({_first_line(err)})", err)
        raise CheckpointError(
            f"{path} holds more than tensors and plain data (it refers to "
            f"{refused.group(1)}): loading it could run code its author put in it, so "
            f"rl_pg does not load it. Files rl_pg writes hold no code; train or export "
            f"the agent again with rl_pg, or ask its author for one."
        ) from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, ValueError) as err:
        _raise_corrupted(path, f"it cannot be read ({_first_line(err) or type(err).__name__})", err)
    if not isinstance(state, dict) or "format" not in state:
        raise CheckpointError(f"{path} is not an rl_pg checkpoint.")
    return state


def _first_line(err: BaseException) -> str:
    """torch's weights-only errors are paragraphs; their reason is the WeightsUnpickler's."""
    text = str(err)
    reason = re.search(r"WeightsUnpickler error: (.+)", text, re.DOTALL)
    return " ".join((reason.group(1) if reason else text).strip().split("\n\n")[0].split())


def _raise_corrupted(path: Path, why: str, cause: BaseException | None = None):
    raise CheckpointError(
        f"The checkpoint {path} is corrupted: {why}. It was left as it is; restore it "
        f"from a backup, or start a new run in another --run-dir."
    ) from cause
