"""The heap of a process that rl_pg runs from start to end: the ``rl-pg`` command, an
evaluation worker, a collector's worker."""

from __future__ import annotations

import gc
import os
import signal
import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any


@contextmanager
def frozen_heap() -> Iterator[None]:
    """Runs the body of a whole process with what it has built so far out of the
    garbage collector's sight, and leaves the collector nothing to walk at exit.

    What the imports build (torch, TorchRL, tensordict and the compiler stack that
    tensordict imports: about a million objects) lives as long as the process, yet
    every full collection walks it, and so does the interpreter's teardown (what that
    costs a command: ``benchmarks/command.py``). ``gc.freeze()`` moves the objects
    that exist into a generation the collector never visits; objects made afterwards
    are collected as before. At the end the rest is frozen too: the process is ending,
    the operating system takes the memory back, and ``atexit`` handlers (loggers'
    uploads, temporary directories) still run.

    Only for a process's own entry point: frozen objects are never collected, so a
    caller that goes on living (a test calling ``main``) must not use it.
    """
    gc.freeze()
    try:
        yield
    finally:
        # What the run left in cycles (a closed simulator's bindings among them) is
        # collected first: frozen, the bindings would report it as leaked at exit.
        # Only what the run made is walked, the imports being frozen.
        # (14 ms after rl-pg play, 64 ms after rl-pg train cartpole on the CI machine.)
        gc.collect()
        gc.freeze()


class FrozenInWorkers:
    """An environment factory that, called in a worker process (one of TorchRL's
    multi-process collector, or a Ray actor), first freezes what the process holds:
    the imports it made or inherited from the server it forked from, which live as long
    as the worker does (see ``frozen_heap``). Full collections there (those a
    simulator's allocations trigger as it steps, the two ``gc.collect()`` MetaDrive
    calls when it closes its engine) then walk what the environment builds, not the
    hundreds of thousands of objects the imports made.

    A worker is any process but the one that made the factory: called there (TorchRL
    calls factories in the main process to read specs), it only builds the
    environment, that heap being the caller's. Picklable when ``make_env`` is.

    Args:
        make_env (callable): the factory to wrap.
    """

    def __init__(self, make_env: Callable[[], Any]) -> None:
        self.make_env = make_env
        self._maker = _this_process()

    def __call__(self) -> Any:
        if _this_process() != self._maker:
            gc.freeze()
        return self.make_env()


def _this_process() -> tuple[str, int]:
    """This process, among those of every machine of a cluster."""
    return socket.gethostname(), os.getpid()


STOP_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)
"""The signals that ask a run to stop: Ctrl-C, ``kill`` (and schedulers), a closed
terminal (POSIX only)."""


_MASKS = hasattr(signal, "pthread_sigmask")


@contextmanager
def signal_handlers_kept() -> Iterator[None]:
    """Sets the Python handlers of the ``STOP_SIGNALS`` again after the block, over
    whatever its C code installed (``ray.init`` installs handlers of its own that abort
    the process on SIGTERM, losing a run's stop: wrap it in this).

    The processes the block starts (Ray's GCS, raylet, and the workers the raylet forks
    later) are started with SIGTERM and SIGHUP blocked, as Ray itself blocks SIGINT in
    them: a stop sent to the whole process group (a scheduler's ``kill -TERM -PGID``, a
    closed terminal) reaches the run, which checkpoints and then shuts Ray down, rather
    than Ray's processes, which would die under the run while it saves."""
    main = threading.current_thread() is threading.main_thread()
    before = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS} if main else {}
    group = {getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, group) if _MASKS and main else None
    try:
        yield
    finally:
        if mask is not None:  # a signal that came meanwhile is delivered here, handled
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for sig, handler in before.items():
            if handler is not None:  # None: set outside Python, nothing to restore
                signal.signal(sig, handler)
