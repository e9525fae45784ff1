"""The variance lab's figures: every estimator's noise by frame, seeds aggregated
(``variance.png``), and the loss's own noise beside each seed's evaluations
(``variance_by_seed.png``)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.app.noise import (
    comparable,
    measurements,
    noise_scale_curve,
    relative_variance,
    units,
    windowed,
)
from rl_pg.training.curves import png_figure, read_curve

__all__ = ["WINDOWS", "log_scale", "seed_figure", "variance_figure"]

WINDOWS = 10
"""Equal frame windows the measurements are pooled in, for the curves."""


_GROUPS = {"holds": "tab:green", "drops": "tab:red", "not evaluated": "tab:grey"}


def _group(verdict: dict[str, Any] | None) -> str:
    if verdict is None:
        return "not evaluated"
    return "holds" if verdict["holds"] else "drops"


def seed_figure(runs, held, path: Path, *, title: str, estimator: str) -> None:
    """The seeds whose best checkpoint held beside those that dropped: each seed's
    evaluations (thin), and for each group the noise scale and SNR of ``estimator``
    (its seeds' measurements pooled in windows) and the policy's mean entropy during
    training (where it is logged)."""
    groups: dict[str, list[Path]] = {}
    for seed, run_dir in runs.items():
        groups.setdefault(_group(held[seed]), []).append(run_dir)
    end = max(measurements(r, estimator)["frames"].max() for r in runs.values()) + 1
    edges = np.linspace(0.0, end, WINDOWS + 1)
    with png_figure(path, size=(8, 11)) as ax, warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        figure = ax.figure
        ax.remove()
        top, scale_ax, snr_ax, entropy_ax = figure.subplots(4, 1, sharex=True)
        for name, members in groups.items():
            colour = _GROUPS[name]
            for i, run_dir in enumerate(members):
                label = f"{name} ({len(members)} seeds)" if i == 0 else None
                top.plot(*read_curve(run_dir, "eval/mean_return"), color=colour, lw=0.8,
                         label=label)  # fmt: skip
            frames, scale, snr = noise_scale_curve(
                [measurements(r, estimator) for r in members], edges
            )
            scale_ax.plot(frames, scale, marker=".", color=colour)
            snr_ax.plot(frames, snr, marker=".", color=colour)
            entropy = [windowed(r, "train/entropy", edges) for r in members]
            if all(e is not None for e in entropy):
                entropy_ax.plot(frames, np.nanmean(np.stack(entropy), 0), marker=".", color=colour)
        returns = np.concatenate([read_curve(r, "eval/mean_return")[1] for r in runs.values()])
        top.set_ylim(bottom=np.percentile(returns, 5))
        recipe = title.split(":")[0]
        top.set(
            ylabel="evaluation mean return", title=f"{recipe}: seeds that hold, seeds that drop"
        )
        top.legend(loc="best", fontsize="small", title="best checkpoint on fresh episodes")
        log_scale(scale_ax, f"noise scale B, {estimator}")
        log_scale(snr_ax, "SNR at the batch size")
        entropy_ax.set(ylabel="policy entropy (training)", xlabel="frames")


def log_scale(ax, label: str) -> None:
    """A log scale for a panel of positive quantities, labelled. A noise scale or an SNR
    measured on few batches can come out at or below 0 (``|G|²``'s estimate is a
    difference), and such points are left out of a log scale; a panel with no positive
    point at all (a short run, one seed) stays linear and says why."""
    values = np.concatenate(
        [np.asarray(line.get_ydata(), dtype=float) for line in ax.lines] or [np.empty(0)]
    )
    if np.any(np.isfinite(values) & (values > 0)):
        ax.set(yscale="log", ylabel=label)
    else:
        ax.set(ylabel=f"{label} (none > 0 yet: linear)")


def variance_figure(
    runs: dict[int, Path], estimators: list[str], path: Path, *, title: str
) -> None:
    """Three panels by frame: each estimator's variance relative to the whole-episode
    return's on the same batches (every seed pooled; shaded from seed to seed), the
    noise scale B, and each seed's evaluations."""
    reference = "episode_return" if "episode_return" in estimators else estimators[0]
    measured = {e: [measurements(r, e) for r in runs.values()] for e in estimators}
    end = max(m["frames"].max() for m in measured[reference]) + 1
    edges = np.linspace(0.0, end, WINDOWS + 1)
    with png_figure(path, size=(8, 9)) as ax, warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # windows where no seed has a B
        figure = ax.figure
        ax.remove()
        top, middle, bottom = figure.subplots(3, 1, sharex=True)
        centres = (edges[:-1] + edges[1:]) / 2
        for estimator in estimators:
            if comparable(estimator, runs):
                ratio = relative_variance(measured[estimator], measured[reference], edges)
            else:  # keeps its colour in the other panels
                ratio = np.full_like(centres, np.nan)
            (line,) = top.plot(centres, ratio, marker=".", label=estimator)
            frames, scale, _ = noise_scale_curve(measured[estimator], edges[::2])
            middle.plot(frames, scale, marker=".", color=line.get_color())
            if len(runs) > 1 and comparable(estimator, runs):
                seeds = np.stack(
                    [
                        relative_variance([m], [r], edges)
                        for m, r in zip(measured[estimator], measured[reference], strict=True)
                    ]
                )
                top.fill_between(
                    centres,
                    np.nanmin(seeds, 0),
                    np.nanmax(seeds, 0),
                    color=line.get_color(),
                    alpha=0.15,
                )
        for seed, run_dir in runs.items():
            bottom.plot(*read_curve(run_dir, "eval/mean_return"), label=f"seed {seed}")
        returns = np.concatenate([read_curve(r, "eval/mean_return")[1] for r in runs.values()])
        bottom.set_ylim(bottom=np.percentile(returns, 5))  # early collapses off the scale
        log_scale(top, f"tr Σ relative to {reference}")
        top.set(title=title)
        top.legend(loc="best", fontsize="small")
        measured_by = units(runs)
        unit = (
            f"groups of {measured_by['group_size']}" if measured_by["unit"] == "group" else "units"
        )
        log_scale(middle, f"noise scale B ({unit})")
        bottom.set(ylabel="evaluation mean return", xlabel="frames")
        bottom.legend(loc="best", fontsize="small")
