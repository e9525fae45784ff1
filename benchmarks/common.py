"""What every benchmark script shares: the machine description, the JSON file, the table."""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rl_pg.training.config import config_dict

REPO = Path(__file__).resolve().parents[1]


def machine() -> dict[str, Any]:
    """Where and when the numbers were measured."""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if "model name" in line)
    except (OSError, StopIteration):
        cpu = platform.processor() or platform.machine()
    return {
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "load_average_1min": os.getloadavg()[0],
    }


def write_json(path: Path, config: Any, **results: Any) -> dict[str, Any]:
    """Writes ``{"config", "machine", **results}`` to ``path`` and returns it."""
    if dataclasses.is_dataclass(config):
        config = config_dict(config)
    result = {"config": config, "machine": machine(), **results}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2))
    return result


def ratio_interval(
    numerator: list[float], denominator: list[float], *, level: float = 0.9, draws: int = 4000
) -> list[float]:
    """The bootstrap interval (``level``, percentile method) of ``median(numerator) /
    median(denominator)``, two contenders' rates over the same rounds of a run.

    Repetition k of both ran in round k, one after the other: what slowed the machine
    during a round slowed both, so rounds are resampled whole, each keeping its pair
    (an interval of the ratio, not of each rate's drift). Seeded: the same rates give
    the same interval.

    Examples:
        >>> ratio_interval([0.9, 1.8, 0.45], [1.0, 2.0, 0.5])  # drift shared by both
        [0.9, 0.9]
    """
    a, b = np.asarray(numerator, dtype=float), np.asarray(denominator, dtype=float)
    if a.ndim != 1 or a.shape != b.shape or len(a) < 1:
        raise ValueError(
            f"two equally long lists of rates, one per round, are needed: got {len(a)} and "
            f"{len(b)}."
        )
    rounds = np.random.default_rng(0).integers(0, len(a), size=(draws, len(a)))
    ratios = np.median(a[rounds], axis=1) / np.median(b[rounds], axis=1)
    low, high = np.quantile(ratios, [(1 - level) / 2, (1 + level) / 2])
    return [round(float(low), 12), round(float(high), 12)]


def table(rows: list[list[Any]], header: list[str]) -> str:
    """A Markdown table (prints well in a terminal and pastes into the docs)."""
    cells = [[_fmt(c) for c in row] for row in [header, *rows]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(header))]
    lines = [
        "| " + " | ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) + " |"
        for row in cells
    ]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def _fmt(value: Any) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value:,.3g}" if abs(value) < 100 else f"{value:,.0f}"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)
