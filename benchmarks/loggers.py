"""What does each logger backend cost a training run?

CartPole's recipe at its defaults, once with the CSV logs alone (what every run writes)
and once with each optional backend added: TensorBoard, Weights & Biases (offline: no
account, no network) and MLflow (a SQLite store, as the docs recommend). Each run is a
fresh process; the contenders take turns in every round, so a slower moment of the
machine slows all of them. Reported per backend, as medians over the rounds:

* the training's own time (``train_wall_s`` of the run's summary: the loop, with every
  scalar logged and every flush), against the CSV-only run's: the target is at most
  1.10;
* the whole command's time, start to exit (what a user waits for), which adds each
  backend's import and set-up once (MLflow's store creation, W&B's service process).

    pip install -c constraints.txt -e ".[dev]"
    python benchmarks/loggers.py [--repeats 5]
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro
from common import REPO, ratio_interval, table, write_json

BACKENDS = {
    "csv only": [],
    "tensorboard": ["--tensorboard"],
    "wandb (offline)": ["--wandb", "--wandb-mode", "offline"],
    "mlflow (sqlite)": ["--mlflow", "--mlflow-uri", "sqlite:///{folder}/mlflow.db"],
}


@dataclass
class Config:
    """Training and command time of CartPole with each logger backend."""

    repeats: int = 5
    """Rounds; each runs every backend once."""
    recipe: str = "cartpole"
    """The recipe trained (at its defaults)."""
    out: Path = REPO / "benchmarks" / "results" / "loggers.json"
    """Where the results go."""


def one_run(recipe: str, flags: list[str]) -> tuple[float, float]:
    """(training seconds, command seconds) of one run in a fresh process and folder."""
    with tempfile.TemporaryDirectory() as folder:
        args = [flag.format(folder=folder) for flag in flags]
        command = [sys.executable, "-m", "rl_pg.app", "train", recipe,
                   "--run-dir", f"{folder}/run", "--no-progress", *args]  # fmt: skip
        start = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True, text=True, cwd=folder)
        wall = time.perf_counter() - start
        summary = json.loads((Path(folder) / "run" / "summary.json").read_text())
        return summary["train_wall_s"], wall


def main(cfg: Config) -> dict:
    train = {name: [] for name in BACKENDS}
    wall = {name: [] for name in BACKENDS}
    for round_ in range(cfg.repeats):
        for name, flags in BACKENDS.items():
            seconds, waited = one_run(cfg.recipe, flags)
            train[name].append(seconds)
            wall[name].append(waited)
            print(f"round {round_ + 1}: {name}: training {seconds:.2f} s, command {waited:.1f} s")
    base = "csv only"
    rows, ratios = [], {}
    for name in BACKENDS:
        ratio = statistics.median(train[name]) / statistics.median(train[base])
        ratios[name] = {
            "training": round(ratio, 3),
            "training_interval_90": ratio_interval(train[name], train[base]),
            "command_extra_s": round(
                statistics.median(wall[name]) - statistics.median(wall[base]), 2
            ),
        }
        rows.append([
            name, statistics.median(train[name]), f"{ratio:.2f}",
            "{:.2f}–{:.2f}".format(*ratios[name]["training_interval_90"]),
            statistics.median(wall[name]), ratios[name]["command_extra_s"],
        ])  # fmt: skip
    print(table(rows, ["backend", "training (s)", "× csv only", "90 % interval",
                       "command (s)", "command − csv only (s)"]))  # fmt: skip
    return write_json(
        cfg.out, vars(cfg) | {"out": str(cfg.out)}, training_s=train, command_s=wall,
        ratios=ratios,
        training_over_csv_only={name: r["training"] for name, r in ratios.items()},
        command_extra_s={name: r["command_extra_s"] for name, r in ratios.items()},
    )  # fmt: skip


if __name__ == "__main__":
    main(tyro.cli(Config))
