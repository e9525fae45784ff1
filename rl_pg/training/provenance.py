"""Where and on what a run's session ran: the code (rl_pg's version and, in a git
checkout, its commit), the libraries, the machine. A run's summary keeps one record per
session (``sessions``), so a result says which code made it and whether it was resumed:
floating-point results repeat on one machine, not across machines."""

from __future__ import annotations

import importlib.metadata
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

__all__ = ["session_record"]

LIBRARIES = ("torch", "torchrl", "tensordict", "gymnasium", "numpy")


def session_record(frames_at_start: int) -> dict[str, Any]:
    """The record of a session that starts at ``frames_at_start``: its start time (UTC),
    the code, the libraries' versions and the machine."""
    return {
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "frames_at_start": frames_at_start,
        "code": _code(),
        "libraries": {name: _version(name) for name in LIBRARIES},
        "machine": {
            "python": platform.python_version(),
            "system": platform.system(),
            "cpu": _cpu(),
            "cores": os.cpu_count(),
        },
    }


def _code() -> dict[str, Any]:
    """rl_pg's version and, when it is imported from a git checkout, the commit and
    whether the checkout had uncommitted changes."""
    from rl_pg import __version__

    code: dict[str, Any] = {"rl_pg": __version__}
    source = Path(__file__).resolve().parents[2]
    if not (source / ".git").exists():  # installed, not a checkout: no commit of ours
        return code
    try:
        commit = _git(source, "rev-parse", "HEAD")
        changes = _git(source, "status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return code  # an installed package, or no git: the version is all there is
    code.update(commit=commit, uncommitted_changes=bool(changes))
    return code


def _git(directory: Path, *args: str) -> str:
    done = subprocess.run(
        ["git", "-C", str(directory), *args], capture_output=True, text=True, timeout=10,
        check=True,
    )  # fmt: skip
    return done.stdout.strip()


def _version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def _cpu() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo), else what the platform reports."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
