"""How many threads torch runs a run's small models on."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["torch_threads"]


@contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Runs the block on ``threads`` torch threads (a run's ``cfg.threads``; None: as
    they are), then restores the number it found.

    Training, ``rl-pg evaluate`` and ``rl-pg play`` run a checkpoint's small models this
    way: on a machine busy with other work (another run, its environments), torch's
    default of one thread per core makes them wait on each other (an evaluation of a
    LunarLander checkpoint beside a two-process training took 15 s on two threads, 3.6 s
    on one).

    Examples:
        >>> import torch
        >>> from rl_pg.training.threads import torch_threads
        >>> before = torch.get_num_threads()
        >>> with torch_threads(1):
        ...     torch.get_num_threads()
        1
        >>> torch.get_num_threads() == before
        True
    """
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
