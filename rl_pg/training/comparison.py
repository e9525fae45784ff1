"""Run a recipe under several variants and seeds, and plot the curves side by side."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.checkpoint import write_atomically
from rl_pg.plots import png_figure
from rl_pg.training.config import TrainConfig
from rl_pg.training.metrics import scalar_log_rows

__all__ = ["plot_curves", "read_curve", "run_variants"]


def read_curve(run_dir: str | Path, metric: str) -> tuple[np.ndarray, np.ndarray]:
    """Steps (frames) and values of ``metric`` from a run's CSV log.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.training.comparison import read_curve
        >>> run = Path(tempfile.mkdtemp())
        >>> (run / "logs/csv/scalars/eval").mkdir(parents=True)
        >>> _ = (run / "logs/csv/scalars/eval/mean_return.csv").write_text("10,0.5\\n20,0.75\\n")
        >>> read_curve(run, "eval/mean_return")
        (array([10., 20.]), array([0.5 , 0.75]))
    """
    path = Path(run_dir) / "logs" / "csv" / "scalars" / f"{metric}.csv"
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: the run logged no {metric!r}.")
    data = np.array(scalar_log_rows(path.read_text()), dtype=np.float64).reshape(-1, 2)
    return data[:, 0], data[:, 1]


def run_variants(
    main: Callable[[Any], dict],
    cfg: TrainConfig,
    variants: dict[str, dict[str, Any]],
    *,
    seeds: Sequence[int],
    root: Path,
) -> dict[str, list[dict]]:
    """Runs ``main`` for every variant (a dict of config overrides) and seed.

    Each run goes to ``root/<variant>/seed<seed>``; the summaries are returned and
    written to ``root/comparison.json``.
    """
    results: dict[str, list[dict]] = {}
    for name, overrides in variants.items():
        for seed in seeds:
            run_cfg = dataclasses.replace(
                cfg, **overrides, seed=seed, run_dir=root / name / f"seed{seed}", resume=False
            )
            results.setdefault(name, []).append(main(run_cfg))
    write_atomically(root / "comparison.json", json.dumps(results, indent=2))
    return results


def plot_curves(
    curves: dict[str, list[tuple[np.ndarray, np.ndarray]]],
    path: Path,
    *,
    xlabel: str,
    ylabel: str,
    title: str,
    hlines: Sequence[float] = (),
) -> Path:
    """One line per variant: the mean over seeds (on a common grid), shaded min to max."""
    with png_figure(path) as ax:
        for name, runs in curves.items():
            grid = np.unique(np.concatenate([steps for steps, _ in runs]))
            values = np.stack([np.interp(grid, steps, vals) for steps, vals in runs])
            ax.plot(grid, values.mean(0), label=f"{name} ({len(runs)} seeds)")
            ax.fill_between(grid, values.min(0), values.max(0), alpha=0.2)
        for y in hlines:
            ax.axhline(y, color="grey", linestyle=":")
        ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
        ax.legend(loc="best")
    return path
