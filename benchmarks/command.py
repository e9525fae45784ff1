"""How long does an ``rl-pg`` command take from the shell's point of view, start to exit?

Each contender is a fresh Python process, timed from its start to its exit by this
script (what a user waits for), repetitions interleaved:

* the imports alone (``import torch``; the command's module), exiting normally;
* the command's module imported, its heap frozen (``gc.freeze()``) before exiting: the
  difference is the interpreter's teardown walking what the imports built;
* each command through ``main`` (the command as it ran before its heap was frozen) and
  through ``run`` (what the console script and ``python -m rl_pg.app`` start).

A ``train`` command gets a fresh run directory and ``--no-progress``; its own training
time (``train_wall_s`` of its summary) is read too, to say how much of the wait is
training.

    python benchmarks/command.py
"""

from __future__ import annotations

import json
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro
from common import REPO, table, write_json

IMPORTS = {
    "import torch": "import torch",
    "import the command's module": "import rl_pg.app.cli",
    "import the command's module, heap frozen at exit": ("import gc, rl_pg.app.cli; gc.freeze()"),
}
ENTRY = "import sys; from rl_pg.app.cli import {0}; {0}(sys.argv[1:])"


@dataclass
class Config:
    """Seconds from a process's start to its exit: imports, teardown, whole commands."""

    commands: list[str] = field(default_factory=lambda: ["--help", "train cartpole --seed 2"])
    """rl-pg commands, each run through main and through run."""
    repeats: int = 5
    """Interleaved repetitions of every contender (medians are reported)."""
    json_path: Path = REPO / "benchmarks/results/command.json"
    """Where the results are written."""


def timed(code: str, args: list[str]) -> tuple[float, float | None]:
    """Seconds ``python -c code ARGS`` took to exit, and the training seconds its run
    directory records (None for a command that trains nothing)."""
    with tempfile.TemporaryDirectory() as scratch:
        if args[:1] == ["train"]:
            args = [*args, "--run-dir", str(Path(scratch) / "run"), "--no-progress"]
        begin = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=scratch
        )
        seconds = time.perf_counter() - begin
        if done.returncode != 0:
            raise SystemExit(f"`{shlex.join(args)}` failed:\n{done.stderr[-2000:]}")
        summary = Path(scratch) / "run" / "summary.json"
        trained = json.loads(summary.read_text())["train_wall_s"] if summary.exists() else None
    return seconds, trained


def main(cfg: Config) -> dict:
    if cfg.repeats < 1:
        raise SystemExit(f"--repeats must be at least 1, got {cfg.repeats}.")
    contenders = {
        f"rl-pg {command} (entry: {entry})": (ENTRY.format(entry), shlex.split(command))
        for command in cfg.commands
        for entry in ("main", "run")
    }  # first, so that a command that fails stops the run at once
    contenders.update({name: (code, []) for name, code in IMPORTS.items()})
    seconds: dict[str, list[float]] = {name: [] for name in contenders}
    training: dict[str, list[float]] = {}
    for _ in range(cfg.repeats):
        for name, (code, args) in contenders.items():
            wall, trained = timed(code, args)
            seconds[name].append(wall)
            if trained is not None:
                training.setdefault(name, []).append(trained)
    median = {name: statistics.median(times) for name, times in seconds.items()}
    median_training = {name: statistics.median(times) for name, times in training.items()}
    ratios = {
        command: median[f"rl-pg {command} (entry: run)"] / median[f"rl-pg {command} (entry: main)"]
        for command in cfg.commands
    }
    teardown = (
        median["import the command's module"]
        - median["import the command's module, heap frozen at exit"]
    )
    rows = [[name, median[name], median_training.get(name)] for name in contenders]
    print(table(rows, ["process", "seconds to exit (median)", "of which training (median)"]))
    for command, ratio in ratios.items():
        print(f"rl-pg {command}: run / main {ratio:.2f}x the time")
    return write_json(
        cfg.json_path,
        cfg,
        seconds=seconds,
        median_seconds=median,
        median_training_seconds=median_training,
        run_over_main=ratios,
        teardown_s=teardown,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
