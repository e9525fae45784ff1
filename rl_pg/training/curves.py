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
from rl_pg.training.aggregates import performance_profile, seed_aggregate, solved_share
from rl_pg.training.loggers import scalar_log_rows

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = [
    "plot_curves",
    "plot_run",
    "plot_runs",
    "plot_seeds",
    "plot_settings",
    "plot_solved_settings",
    "png_figure",
    "read_curve",
]

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


def _frame_axes(ax, *, ylabel: str, title: str, threshold, ylim) -> None:
    """Curves by frame: the threshold line, labels, range and a small legend."""
    _threshold_line(ax, threshold)
    ax.set(xlabel="frames", ylabel=ylabel, title=title)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.legend(loc="best", fontsize="small")


def _threshold_line(ax, threshold: float | None) -> None:
    """The target as a dotted grey line, labelled, where there is one."""
    if threshold is not None:
        ax.axhline(threshold, color="grey", linestyle=":", label=f"threshold {threshold:.4g}")


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
        _frame_axes(ax, ylabel=metric, title=title, threshold=threshold, ylim=ylim)
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


def plot_profiles(
    scores: dict[str, np.ndarray],
    path: Path,
    *,
    xlabel: str,
    title: str,
    threshold: float | None = None,
) -> Path:
    """Performance profiles of several settings (``{name: one score per run}``) in one
    figure, each with its 95 % bootstrap band (see
    [`performance_profile`][rl_pg.training.aggregates.performance_profile])."""
    every = np.concatenate([np.asarray(s, dtype=np.float64) for s in scores.values()])
    margin = 0.05 * (every.max() - every.min() or 1.0)
    taus = np.linspace(every.min() - margin, every.max() + margin, 400)
    with png_figure(path) as ax:
        for i, (name, runs) in enumerate(scores.items()):
            color = f"C{i}"
            share, low, high = performance_profile(runs, taus)
            ax.step(taus, share, where="post", color=color, linewidth=2,
                    label=f"{name} ({len(runs)} runs)")  # fmt: skip
            ax.fill_between(taus, low, high, step="post", color=color, alpha=0.2)
        if threshold is not None:
            ax.axvline(threshold, color="black", linestyle=":", linewidth=1,
                       label=f"threshold {threshold:.4g}")  # fmt: skip
        ax.set_xlabel(xlabel)
        ax.set_ylabel("share of runs scoring above τ")
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(title)
        ax.legend(fontsize=8)
    return path


def plot_solved(reached: dict[str, float | None], path: Path, *, budget: int, title: str) -> Path:
    """Runs that stop when solved (``{name: frames to the threshold, or None}``): the
    share of them solved by each frame up to ``budget``, with its 95 % bootstrap band
    (see [`solved_share`][rl_pg.training.aggregates.solved_share]), and a tick per run."""
    return plot_solved_settings({"": reached}, path, budget=budget, title=title)


def plot_solved_settings(
    settings: dict[str, dict[str, float | None]], path: Path, *, budget: int, title: str
) -> Path:
    """Several settings of runs that stop when solved (``{setting: {name: frames to the
    threshold, or None}}``), one colour each: the share of its runs solved by each frame
    up to ``budget``, with its 95 % bootstrap band, and a tick per solved run."""
    right = budget * 1.03  # a margin: a run solved at the budget shows its step
    frames = np.linspace(0, right, 500)
    with png_figure(path) as ax:
        for number, (setting, reached) in enumerate(settings.items()):
            at = np.array([np.inf if f is None else f for f in reached.values()], dtype=np.float64)
            share, low, high = solved_share(at, frames)
            color, named = f"C{number}", f"{setting}: " if setting else ""
            ax.step(frames, share, where="post", color=color, linewidth=2,
                    label=f"{named}share of {len(at)} seeds solved")  # fmt: skip
            ax.fill_between(frames, low, high, step="post", color=color, alpha=0.25,
                            label=None if named else "95 % bootstrap CI")  # fmt: skip
            solved = at[np.isfinite(at)]
            tick = None if named else "a seed's first evaluation at the threshold"
            ax.plot(solved, np.zeros_like(solved), "|", color=color if named else "black",
                    markersize=12, label=tick)  # fmt: skip
        if named:  # one legend entry for every setting's band
            ax.fill_between([], [], color="grey", alpha=0.25, label="bands: 95 % bootstrap CI")
        ax.set_xlabel("frames")
        ax.set_ylabel("share of seeds solved")
        ax.set_xlim(0, right)
        ax.set_ylim(-0.04, 1.02)
        ax.set_title(title)
        ax.legend(fontsize=8, loc="lower right")
    return path


def _common_grid(grids: list[np.ndarray]) -> np.ndarray:
    """The median frames of evaluations that differ by less than half an interval."""
    if any(len(grid) != len(grids[0]) for grid in grids) or len(grids[0]) == 0:
        raise ValueError(
            "plot_seeds needs every seed evaluated at the same frames; these runs were "
            "evaluated a different number of times (another eval_interval, or a run not "
            "finished)."
        )
    stacked = np.stack(grids)
    median = np.median(stacked, axis=0)
    spacing = np.diff(median).min() if len(median) > 1 else np.inf
    if ((stacked.max(axis=0) - stacked.min(axis=0)) >= spacing / 2).any():
        raise ValueError(
            "plot_seeds needs every seed evaluated at the same frames (within half an "
            "interval); these runs were evaluated at different ones (another eval_interval)."
        )
    return median


def plot_seeds(
    curves: dict[str, tuple[np.ndarray, np.ndarray]],
    path: Path,
    *,
    ylabel: str,
    title: str,
    threshold: float | None = None,
    ylim: tuple[float, float] | None = None,
) -> Path:
    """Several seeds of one setting (``{name: (frames, values)}``, evaluated at the same
    frames): each seed as a thin line, and their interquartile mean with its 95 %
    bootstrap confidence band (see [`seed_aggregate`][rl_pg.training.aggregates.seed_aggregate]).

    Runs whose batches are whole episodes evaluate at the first batch past each
    interval, so their frames differ a little: evaluations that differ by less than half
    an interval are aggregated at their median frames."""
    return plot_settings(
        {"": curves}, path, ylabel=ylabel, title=title, threshold=threshold, ylim=ylim
    )


def plot_settings(
    settings: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]],
    path: Path,
    *,
    ylabel: str,
    title: str,
    threshold: float | None = None,
    ylim: tuple[float, float] | None = None,
) -> Path:
    """Several settings' seeds (``{setting: {name: (frames, values)}}``), one colour
    each: each setting's interquartile mean with its 95 % bootstrap band, as
    [`plot_seeds`][rl_pg.training.curves.plot_seeds] draws one (without its seeds'
    thin lines, which would hide the bands)."""
    with png_figure(path) as ax:
        for number, (setting, curves) in enumerate(settings.items()):
            grids = [np.asarray(frames) for frames, _ in curves.values()]
            if any(not np.array_equal(grid, grids[0]) for grid in grids):
                grids = [_common_grid(grids)] * len(grids)
            iqm, low, high = seed_aggregate(np.stack([vals for _, vals in curves.values()]))
            color, named = f"C{number}", f"{setting}: " if setting else ""
            if not named:  # one setting: its seeds too (several: the bands say enough)
                for frames, vals in curves.values():
                    ax.plot(frames, vals, color="grey", linewidth=0.6, alpha=0.6)
            ax.plot(grids[0], iqm, color=color, linewidth=2,
                    label=f"{named}interquartile mean of {len(curves)} seeds")  # fmt: skip
            ax.fill_between(grids[0], low, high, color=color, alpha=0.25,
                            label=None if named else "95 % bootstrap CI")  # fmt: skip
        if named:  # one legend entry for every setting's band
            ax.fill_between([], [], color="grey", alpha=0.25, label="bands: 95 % bootstrap CI")
        _frame_axes(ax, ylabel=ylabel, title=title, threshold=threshold, ylim=ylim)
    return path


def is_png(path: str | Path) -> bool:
    """Whether ``path`` is a PNG image (what the figure commands may draw over)."""
    with open(path, "rb") as file:
        return file.read(8) == b"\x89PNG\r\n\x1a\n"


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
