"""A stop during a run (Ctrl-C, or a plain ``kill``): finish the update, save, say how
to resume, stop.

The first SIGINT (Ctrl-C), SIGTERM (``kill``, a batch scheduler's or ``docker stop``'s
request to stop) or SIGHUP (the terminal closed) is deferred to the end of the update
in progress, where the run's state is consistent: the loop then writes a checkpoint
and the summary and raises ``KeyboardInterrupt`` (so a notebook cell or a caller still
sees an interruption). A second one interrupts at once. Command-line entry points wrap themselves in
[`exit_quietly_on_interrupt`][rl_pg.training.interrupt.exit_quietly_on_interrupt] to
exit with status 130 and the one line the loop printed, instead of a traceback.

A terminal sends Ctrl-C to every process of the command, and a scheduler may send
SIGTERM to all of them, worker processes included;
[`MainProcessInterrupts`][rl_pg.training.interrupt.MainProcessInterrupts] wraps the
environment factories that run in workers so that only the main process reacts (it
then shuts the workers down itself).
"""

from __future__ import annotations

import multiprocessing
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from rl_pg._process import STOP_SIGNALS

__all__ = ["InterruptRequest", "MainProcessInterrupts", "exit_quietly_on_interrupt"]


SIGNALS = STOP_SIGNALS


class InterruptRequest:
    """A context manager that turns the first of the ``SIGNALS`` into ``requested =
    True`` (and names it in ``signal_name``); the second raises ``KeyboardInterrupt``.

    Signal handlers can only be set from the main thread; elsewhere both signals keep
    their usual effect.

    Examples:
        >>> import os, signal
        >>> from rl_pg.training.interrupt import InterruptRequest
        >>> with InterruptRequest() as interrupt:
        ...     os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C sends
        ...     interrupt.requested
        True
    """

    def __init__(self) -> None:
        self.requested = False
        self.signal_name: str | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> InterruptRequest:
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._handle) for sig in SIGNALS}
        return self

    def reclaim(self) -> None:
        """Takes the ``SIGNALS`` back from a library that set its own handlers while
        the run was starting or running: ``ray.init`` installs C-level handlers that
        abort the process on SIGTERM, unseen by ``signal.getsignal``, so every signal is
        set again. Cheap enough to call every update."""
        if self._previous and threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                signal.signal(sig, self._handle)

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested, self.signal_name = True, signal.Signals(signum).name

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)


class MainProcessInterrupts:
    """An environment factory for a worker process, which then ignores the ``SIGNALS``.

    Called in a worker process (as TorchRL's collectors and ``ParallelEnv`` call their
    factories), it sets the ``SIGNALS`` to be ignored there, then builds the
    environment: the main process handles the stop and closes the worker. Called in the main
    process, it only builds the environment. Picklable when ``make_env`` is.

    Args:
        make_env (callable): the factory to wrap.
    """

    def __init__(self, make_env: Callable[[], Any]) -> None:
        self.make_env = make_env

    def __call__(self) -> Any:
        # Only in a worker: TorchRL also calls factories in the main process (to read
        # specs), whose Ctrl-C handling must stay; and not from a thread (Ray).
        in_worker = multiprocessing.parent_process() is not None
        if in_worker and threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                signal.signal(sig, signal.SIG_IGN)
        return self.make_env()


@contextmanager
def exit_quietly_on_interrupt() -> Iterator[None]:
    """Exits with status 130 (the shell's code for Ctrl-C) on ``KeyboardInterrupt``.

    The frames the interruption left (a stopped run's among them) are cleared first:
    its traceback would keep their variables, the run's environments with them, alive
    as the process exits (a simulator's bindings then report them leaked)."""
    try:
        yield
    except KeyboardInterrupt as interruption:
        traceback.clear_frames(interruption.__traceback__)
        sys.exit(130)
