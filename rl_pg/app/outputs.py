"""Which files a command may write: its own outputs, never a run's files, and another
file only when the user says to replace it."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from rl_pg.training.run_dir import RUN_FILES, run_directory_of

__all__ = ["claim_output"]


def claim_output(
    path: str | Path,
    *,
    flag: str,
    writes: str,
    ours: Callable[[Path], bool],
    suffix: str,
    replace: bool = False,
) -> Path:
    """Checks, before a command does its work, that it may write its output ``path``.

    A command writes only names it owns: a new file, or a file it wrote itself before
    (``ours(path)`` says so, e.g. a table store of ``rl-pg report``); a file of a run
    directory that is not its own (a checkpoint, the config, the logs) never, and any
    other existing file only when told to ``replace`` it.

    Args:
        path: the output the user named.
        flag: the option that named it, for the messages (``"--store"``).
        writes: what the command writes there (``"a table store (JSON)"``).
        ours: whether an existing file is one this command writes.
        suffix: how the name of what it writes ends (``".json"``): another name would
            hide what the file is (a PNG named ``plot.txt``, an agent file ``newdir``
            where a folder was meant).
        replace: the user's leave to replace a file that is not ``ours``.

    Raises:
        ValueError: the path is a directory, a name that does not end in ``suffix``, or
            a file the command may not replace.
    """
    path = Path(path)
    if path.is_dir():
        example = {".pt": "agent", ".json": "table"}.get(suffix, "figure") + suffix
        raise ValueError(
            f"{flag} {path} is a directory: name the file to write there ({writes}), e.g. "
            f"{path / example}."
        )
    if path.exists() or path.is_symlink():
        run = run_directory_of(path)
        own = run is not None and path.absolute().relative_to(run).parts[0] in RUN_FILES
        if own or (run is not None and (path.is_symlink() or not ours(path))):
            raise ValueError(
                f"{flag} {path} is a file of the run {run}, not {writes}: rl_pg never "
                f"replaces a run's own files. Name a file outside the run, or a new name."
            )
        if (path.is_symlink() or not ours(path)) and not replace:
            what = "a symbolic link" if path.is_symlink() else "a file this command did not write"
            raise ValueError(
                f"{flag} {path} exists and is {what}; it was left as it is. Name another "
                f"file for {writes}, or pass --replace to overwrite it."
            )
    if path.suffix.lower() != suffix:
        raise ValueError(
            f"{flag} {path}: it writes {writes}, so its name ends in {suffix}, e.g. "
            f"{path.with_suffix(suffix)}."
        )
    return path
