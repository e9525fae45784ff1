"""Every plot of the harness, drawn from the runs' CSV logs (the one copy of a curve),
and the PNG figure they are drawn on.

Figures use matplotlib's object API, which needs no backend: plotting here never
switches the backend of the user's process (a notebook keeps its inline figures) and
opens no window.
"""

from __future__ import annotations

import io
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rl_pg.checkpoint import write_atomically
from rl_pg.training.metrics import scalar_log_rows

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["plot_curves", "plot_run", "plot_runs", "png_figure", "read_curve"]

CURVE = "learning_curve.png"


def read_curve(run_dir: str | Path, metric: str) -> tuple[np.ndarray, np.ndarray]:
    """Steps (frames) and values of ``metric`` from a run's CSV log.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.training.curves import read_curve
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


def _threshold_line(ax, threshold: float | None) -> None:
    """The target as a dotted grey line, labelled, where there is one."""
    if threshold is not None:
        ax.axhline(threshold, color="grey", linestyle=":", label=f"threshold {threshold:g}")


def plot_run(run_dir: str | Path, *, threshold: float | None, title: str) -> Path:
    """``run_dir/learning_curve.png``: training-episode and evaluation returns by frame."""
    path = Path(run_dir) / CURVE
    with png_figure(path) as ax:
        for name, label in (
            ("train/episode_return", "training episodes"),
            ("eval/mean_return", "evaluation"),
        ):
            try:
                frames, values = read_curve(run_dir, name)
            except FileNotFoundError:
                continue
            ax.plot(frames, values, label=label, marker="o" if name.startswith("eval") else None)
        _threshold_line(ax, threshold)
        ax.set(xlabel="frames", ylabel="episode return", title=title)
        ax.legend(loc="best")
    return path


def plot_runs(
    runs: dict[str, Path],
    path: Path,
    *,
    metric: str,
    title: str,
    threshold: float | None = None,
    ylim: tuple[float, float] | None = None,
) -> Path:
    """One line per run (``{label: run_dir}``): its logged ``metric`` by frame."""
    with png_figure(path) as ax:
        for label, run_dir in runs.items():
            ax.plot(*read_curve(run_dir, metric), marker=".", label=label)
        _threshold_line(ax, threshold)
        ax.set(xlabel="frames", ylabel=metric, title=title)
        if ylim is not None:
            ax.set_ylim(*ylim)
        ax.legend(loc="best", fontsize="small")
    return path


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


@contextmanager
def png_figure(path: str | Path, *, size: tuple[float, float] = (7, 4)) -> Iterator[Axes]:
    """Yields the axes of a new figure; on exit, lays it out and writes it to ``path``
    atomically.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.training.curves import png_figure
        >>> path = Path(tempfile.mkdtemp()) / "line.png"
        >>> with png_figure(path) as ax:
        ...     _ = ax.plot([0, 1], [0, 1])
        >>> path.read_bytes()[:4]
        b'\\x89PNG'
    """
    # Imported here: a process that never plots (a collector's worker) never loads it.
    from matplotlib.figure import Figure

    figure = Figure(figsize=size)
    yield figure.subplots()
    figure.tight_layout()
    image = io.BytesIO()
    figure.savefig(image, format="png", dpi=100)
    write_atomically(path, image.getvalue())
