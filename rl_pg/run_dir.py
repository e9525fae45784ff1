"""A run directory owned by one run at a time.

[`RunDirectory`][rl_pg.run_dir.RunDirectory] holds an exclusive lock on
``<run_dir>/.lock`` for as long as a run uses the directory. The operating system
releases the lock when the process ends, however it ends (a ``kill -9`` included), so
a lock is never stale: a second run started on the same directory is refused with
the holder's process id, instead of both writing the same checkpoint and logs.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from rl_pg.checkpoint import clean_temporary_files

__all__ = ["LOCK_FILE", "RunDirBusy", "RunDirectory"]

LOCK_FILE = ".lock"

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None
    import msvcrt


class RunDirBusy(RuntimeError):
    """Another live process is using the run directory."""


class RunDirectory:
    """Creates (if needed) and locks a run directory; a context manager.

    On entry the directory is locked and the temporary files of writes that a killed
    run left half-way are removed. On exit the lock is released. A directory that was
    empty on entry is emptied again (and removed, if this object created it) when the
    run fails before calling [`keep`][rl_pg.run_dir.RunDirectory.keep]: a run that
    crashed while starting leaves no half-made directory behind.

    Args:
        path (str or Path): the run directory.

    Raises:
        RunDirBusy: on entry, when another process holds the directory (the message
            gives its process id).
        NotADirectoryError: when ``path`` is a file.
        OSError: when the directory cannot be created or written.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.run_dir import RunDirBusy, RunDirectory
        >>> path = Path(tempfile.mkdtemp()) / "run"
        >>> with RunDirectory(path):
        ...     with RunDirectory(path):  # doctest: +ELLIPSIS
        ...         pass
        Traceback (most recent call last):
        ...
        rl_pg.run_dir.RunDirBusy: .../run is in use by another run (process ...). ...
        >>> path.exists()  # created here, and nothing was written to it
        False
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fd: int | None = None
        self._created = False
        self._empty_at_entry = False
        self._keep = False

    def __enter__(self) -> RunDirectory:
        if self.path.exists() and not self.path.is_dir():
            raise NotADirectoryError(
                f"The run directory {self.path} is a file; choose another --run-dir."
            )
        self._created = not self.path.exists()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise OSError(
                f"Cannot use {self.path} as a run directory ({err.strerror}); choose a "
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

    def contents(self) -> list[str]:
        """Names in the directory, the lock file aside."""
        return sorted(p.name for p in self.path.iterdir() if p.name != LOCK_FILE)


def _lock(fd: int) -> None:
    """An exclusive, non-blocking lock on ``fd``; ``OSError`` if another process has it."""
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    else:
        msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
