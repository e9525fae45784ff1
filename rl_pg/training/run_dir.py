"""A run directory: its lock, fresh or resumed opening, the summary and the curve.

[`RunDirectory`][rl_pg.training.run_dir.RunDirectory] holds an exclusive lock on
``<run_dir>/.lock`` for as long as a run uses the directory. The operating system
releases the lock when the process ends, however it ends (a ``kill -9`` included), so
a lock is never stale: a second run started on the same directory is refused with
the holder's process id, instead of both writing the same checkpoint and logs.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rl_pg.checkpoint import (
    CheckpointError,
    clean_temporary_files,
    load_checkpoint,
    write_atomically,
)
from rl_pg.training.checkpoints import BEST, CHECKPOINT, LATEST, RunState, save
from rl_pg.training.config import TrainConfig, config_dict
from rl_pg.training.curves import CURVE, plot_run
from rl_pg.training.metric import Metric
from rl_pg.training.provenance import session_record
from rl_pg.training.resuming import changed_on_resume, check_resumable

__all__ = [
    "LATEST",
    "LOCK_FILE",
    "RunDirBusy",
    "RunDirUnusable",
    "RunDirectory",
    "link_latest",
    "locked",
    "new_run_dir",
    "run_directory_of",
]

LOCK_FILE = ".lock"
SUMMARY = "summary.json"
CONFIG = "config.json"
KEPT = "checkpoints"
RUN_FILES = frozenset({CHECKPOINT, BEST, CONFIG, SUMMARY, LOCK_FILE, KEPT, CURVE, "logs"})
"""What a run writes into its directory; no other command's output replaces them."""

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None
    import msvcrt


class RunDirBusy(RuntimeError):
    """Another live process is using the run directory."""


class RunDirUnusable(OSError):
    """The run directory cannot be made or locked: a file, not writable, or its lock a
    symbolic link."""


class RunDirectory:
    """Creates (if needed) and locks a run directory; a context manager.

    On entry the directory is locked and the temporary files of writes that a killed
    run left half-way are removed. On exit the lock is released. A directory that was
    empty on entry is emptied again (and removed, if this object created it) when the
    run fails before calling [`keep`][rl_pg.training.run_dir.RunDirectory.keep]: a run that
    crashed while starting leaves no half-made directory behind. The loop calls it after
    its first update, so a run that fails while training keeps its logs.

    Args:
        path (str or Path): the run directory.

    Raises:
        RunDirBusy: on entry, when another process holds the directory (the message
            gives its process id).
        RunDirUnusable: when ``path`` is a file, or cannot be made or locked (not
            writable, its lock a symbolic link).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.training.run_dir import RunDirBusy, RunDirectory
        >>> path = Path(tempfile.mkdtemp()) / "run"
        >>> with RunDirectory(path):
        ...     with RunDirectory(path):  # doctest: +ELLIPSIS
        ...         pass
        Traceback (most recent call last):
        ...
        rl_pg.training.run_dir.RunDirBusy: .../run is in use by another run (process ...). ...
        >>> path.exists()  # created here, and nothing was written to it
        False
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.cfg: TrainConfig | None = None
        self.recipe: dict[str, str | None] = {}
        self._fd: int | None = None
        self._created = False
        self._empty_at_entry = False
        self._keep = False

    def __enter__(self) -> RunDirectory:
        if self.path.exists() and not self.path.is_dir():
            raise RunDirUnusable(
                f"The run directory {self.path} is a file; choose another --run-dir."
            )
        self._created = not self.path.exists()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            fd = _open_lock(self.path / LOCK_FILE)
        except OSError as err:
            raise RunDirUnusable(
                f"Cannot use {self.path} as a run directory ({err.strerror or err}); choose a "
                f"writable --run-dir."
            ) from err
        try:
            _lock(fd)
        except OSError as err:
            os.lseek(fd, 0, os.SEEK_SET)
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise RunDirBusy(
                f"{self.path} is in use by another run (process {holder}). Wait for it to "
                f"finish, stop it, or choose another --run-dir."
            ) from err
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        clean_temporary_files(self.path)
        self._empty_at_entry = not self.contents()
        return self

    def keep(self) -> None:
        """Marks the directory as holding something worth keeping (e.g. a checkpoint)."""
        self._keep = True

    @property
    def kept(self) -> bool:
        """Whether [`keep`][rl_pg.training.run_dir.RunDirectory.keep] was called."""
        return self._keep

    def __exit__(self, exc_type, exc, traceback) -> None:
        if self._fd is None:
            return
        discard = (
            self._empty_at_entry
            and not self._keep
            and (exc_type is not None or not self.contents())
        )
        if discard:  # still locked: no other run can be writing here
            for name in self.contents():
                target = self.path / name
                shutil.rmtree(target) if target.is_dir() else target.unlink()
        os.ftruncate(self._fd, 0)
        os.close(self._fd)  # closing the descriptor releases the lock
        self._fd = None
        if discard and self._created:
            (self.path / LOCK_FILE).unlink(missing_ok=True)
            self.path.rmdir()

    @property
    def checkpoint_path(self) -> Path:
        """``<run_dir>/checkpoint.pt``."""
        return self.path / CHECKPOINT

    def open(self, cfg: TrainConfig, recipe: str, module: str | None = None) -> dict | None:
        """Starts the run of ``recipe`` (defined in ``module``, if importable) with
        ``cfg``; returns the checkpoint to resume from (``cfg.resume``), or None.

        Raises:
            CheckpointError: a fresh run where a run already is; a resume from a
                missing, corrupted or foreign checkpoint, with a changed configuration
                or with no budget left.
        """
        saved = _open(cfg, recipe, self)
        if saved is not None:
            self.keep()
        self.cfg, self.recipe = cfg, {"recipe": recipe, "recipe_module": module}
        self.sessions = _earlier_sessions(self.path) if saved is not None else []
        self.session = session_record(saved["state"]["frames"] if saved is not None else 0)
        if saved is not None:
            self.session["changed"] = changed_on_resume(cfg, saved)
        # Readable by people; the checkpoint's own copy is what resuming checks.
        write_atomically(
            self.path / CONFIG, json.dumps({**self.recipe, **config_dict(cfg)}, indent=2)
        )
        return saved

    def save(self, loss, optimizer, state: RunState, *, to: str = "last", **parts) -> None:
        """Writes a checkpoint atomically, with the states ``parts`` of the run's other
        pieces, ``to`` the last one (``checkpoint.pt``), the best one (``best.pt``) or
        a copy kept for good (``"kept"``: ``checkpoints/update_<updates>.pt``); the
        directory is worth keeping from then on."""
        files = {"last": CHECKPOINT, "best": BEST, "kept": f"{KEPT}/update_{state.updates}.pt"}
        save(self.cfg, self.recipe, loss, optimizer, state, self.path / files[to], **parts)
        self.keep()

    def finish(
        self, state: RunState, *, interrupted: bool = False, extra: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        """Writes ``summary.json`` (with the recipe's ``extra`` fields, and under
        ``sessions`` one record per session of the run: frames at its start and end, the
        code, libraries and machine it ran on; see
        [`provenance`][rl_pg.training.provenance]) and the learning curve; returns the
        summary."""
        summary = {**_summary(self.cfg, self.recipe["recipe"], state, self.path), **(extra or {})}
        summary["interrupted"] = interrupted
        this = {**self.session, "frames_at_end": state.frames, "interrupted": interrupted}
        summary["sessions"] = [*self.sessions, this]
        write_atomically(self.path / SUMMARY, json.dumps(summary, indent=2))
        plot_run(self.path, threshold=self.cfg.threshold, title=self.recipe["recipe"])
        return summary

    def contents(self) -> list[str]:
        """Names in the directory, the lock file aside."""
        return sorted(p.name for p in self.path.iterdir() if p.name != LOCK_FILE)


@contextmanager
def locked(path: Path, *, wait: bool = False) -> Iterator[bool]:
    """Holds an exclusive lock on the file ``path`` (created if missing) for the block
    and yields True; if another process holds it, yields False, holding nothing (or,
    with ``wait``, waits for it). Like a run directory's, the lock dies with its
    process, however that ends."""
    fd = _open_lock(Path(path))
    try:
        try:
            _lock(fd, wait=wait)
        except OSError:
            yield False
        else:
            yield True
    finally:
        os.close(fd)  # releases the lock


def _open_lock(path: Path) -> int:
    """A lock file's descriptor, never through a symbolic link: the holder's process id
    is written into it, and a link planted there would have it truncate the link's
    target."""
    if path.is_symlink():
        raise OSError(
            f"{path} is a symbolic link, where rl_pg keeps a lock file of its own; remove "
            f"the link (its target is left as it is)"
        )
    return os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)


def _lock(fd: int, *, wait: bool = False) -> None:
    """An exclusive lock on ``fd``; ``OSError`` if another process has it (unless
    ``wait``: then it waits for it)."""
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
    else:
        msvcrt.locking(fd, msvcrt.LK_LOCK if wait else msvcrt.LK_NBLCK, 1)


def run_directory_of(path: str | Path) -> Path | None:
    """The run directory ``path`` lies in (a folder with a run's ``config.json`` and its
    lock, checkpoint or summary), or None."""
    for folder in Path(path).absolute().parents:
        if (folder / CONFIG).is_file() and any(
            (folder / name).exists() for name in (LOCK_FILE, CHECKPOINT, SUMMARY)
        ):
            return folder
    return None


def new_run_dir(recipe: str, seed: int) -> Path:
    # Time-stamped, so that running a recipe twice never collides with an earlier run.
    return Path("runs") / f"{recipe}-seed{seed}-{time.strftime('%Y%m%d-%H%M%S')}"


def link_latest(run_dir: Path) -> None:
    """Writes ``run_dir.parent / "latest"``, a one-line file naming ``run_dir``, so
    ``rl-pg play runs/latest`` finds the newest run. A file, not a symbolic link: tools
    that walk the folder (``tensorboard --logdir runs``) see each run once. A directory
    named ``latest`` is left alone; the symbolic link of earlier versions is replaced."""
    link = run_dir.parent / LATEST
    if link.is_dir() and not link.is_symlink():
        return
    with contextlib.suppress(OSError):  # a read-only folder: the run is what matters
        write_atomically(link, f"{run_dir.name}\n")


def _open(cfg, recipe, directory: RunDirectory) -> dict | None:
    run_dir, checkpoint_path = directory.path, directory.checkpoint_path
    if cfg.resume:
        if not checkpoint_path.exists() and directory.contents():
            raise CheckpointError(
                f"{run_dir} holds {directory.contents()} but no checkpoint: its run stopped "
                f"before writing its first one (every --checkpoint-interval updates), so "
                f"there is nothing to resume. Start the run again with another --run-dir; "
                f"these logs stay as they are."
            )
        saved = load_checkpoint(checkpoint_path)
        check_resumable(cfg, recipe, saved, checkpoint_path)
        return saved
    if checkpoint_path.exists():
        raise CheckpointError(
            f"{run_dir} already holds a checkpoint; pass --resume to continue it, or choose "
            f"another --run-dir. Nothing was overwritten."
        )
    if directory.contents():
        # A run that died before its first checkpoint: its logs would interleave with ours.
        raise CheckpointError(
            f"{run_dir} holds {directory.contents()} but no checkpoint (a run that stopped "
            f"before its first checkpoint?). Delete it or choose another --run-dir; nothing "
            f"was overwritten."
        )
    return None


def _earlier_sessions(run_dir: Path) -> list[dict[str, Any]]:
    """The sessions an earlier summary of the run recorded (none if it has no readable
    summary, or one written before sessions were recorded)."""
    try:
        sessions = json.loads((run_dir / SUMMARY).read_text()).get("sessions", [])
    except (OSError, ValueError, AttributeError):
        return []
    return sessions if isinstance(sessions, list) else []


def _summary(cfg: TrainConfig, recipe: str, state: RunState, run_dir: Path) -> dict[str, Any]:
    metric = Metric.of(cfg)
    summary = {
        "recipe": recipe,
        "run_dir": str(run_dir),
        "seed": cfg.seed,
        "frames": state.frames,
        "updates": state.updates,
        "train_wall_s": state.train_time,
        "eval_mean_return": state.last_eval.get("eval/mean_return"),
        "eval_std_return": state.last_eval.get("eval/std_return"),
        "threshold": cfg.threshold,
        "solved_at_frames": state.solved_at_frames,
        "best_eval_mean_return": state.best_eval.get("eval/mean_return"),
        "best_at_frames": state.best_at_frames,
        "select_by": metric.key,
        "select_mode": metric.mode,
        "eval_value": state.last_eval.get(metric.logged),
        "best_eval_value": state.best(metric),
        "best_confirmed": state.best_confirmed,
    }
    for key, value in state.last_eval.items():
        if key.endswith("_rate"):
            summary[key.removeprefix("eval/")] = value
        elif key.startswith("eval/mean_") and key not in ("eval/mean_return", "eval/mean_length"):
            summary[key.replace("/", "_")] = value  # a recipe's eval_values
    return summary
