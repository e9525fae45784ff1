"""The heap of a process that rl_pg runs from start to end: the ``rl-pg`` command, an
evaluation worker."""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager


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
        gc.freeze()
