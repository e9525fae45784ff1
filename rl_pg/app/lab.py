"""The variance lesson on a real task: train a recipe's seeds while measuring the policy
gradient's noise for every return estimator, then draw and tabulate it.

``rl-pg lab variance RECIPE`` runs [`variance_lab`][rl_pg.app.lab.variance_lab]:
each seed trains with ``grad_stats`` set (the same batches, the same parameters, every
estimator), in ``ROOT/seed<S>`` (a stopped seed resumes, a finished one is kept), and
[`summarise`][rl_pg.app.lab.summarise] reads their logs into
``ROOT/variance.png`` (noise scale and SNR by frame, seeds aggregated),
``ROOT/variance_by_seed.png`` (the loss's own noise beside each seed's evaluations,
seeds whose best checkpoint holds the threshold on fresh episodes, greedily and by
sampling, drawn solid and the others dashed: run ``rl-pg evaluate`` on each seed first)
and ``ROOT/variance.md`` / ``ROOT/variance.json`` (a table).

A noise scale is a ratio of means, `B = mean(tr Σ) / mean(|∇J|²)` over the measurements
of a window, as McCandlish et al. (2018) average it: each batch's `|∇J|²` estimate is
unbiased but often negative, their ratio per batch is not.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.app.stores import read_report
from rl_pg.checkpoint import write_atomically
from rl_pg.gradient_statistics import ESTIMATORS
from rl_pg.groups import GROUP_BASELINES
from rl_pg.training.checkpoints import CHECKPOINT
from rl_pg.training.config import TrainConfig
from rl_pg.training.curves import png_figure, read_curve
from rl_pg.training.records import read_json
from rl_pg.training.run_dir import SUMMARY, changed_settings

__all__ = ["LabArgs", "measurements", "noise_scale_curve", "summarise", "variance_lab"]


@dataclasses.dataclass
class LabArgs:
    """Train a recipe's seeds measuring the gradient noise of every return estimator,
    then draw it (ROOT/variance.png) and tabulate it (ROOT/variance.md). Every other
    flag is the recipe's (rl-pg train RECIPE --help) and applies to every seed; --run-dir
    is ROOT (default runs/lab-variance-RECIPE)."""

    seeds: list[int] = dataclasses.field(default_factory=lambda: [0, 1, 2])
    """Seeds trained, each in ROOT/seedS (S the seed). A finished one is kept, a stopped
    one resumes."""
    every: int = 20
    """Updates between measurements. Measuring every estimator on one batch costs about
    one to two updates of the recipes' small networks."""


WINDOWS = 10
"""Equal frame windows the measurements are pooled in, for the curves."""


def variance_lab(recipe, cfg: TrainConfig, *, seeds: Sequence[int], every: int, root: Path):
    """Trains ``recipe`` with ``cfg`` on each seed, measuring every ``every`` updates,
    then writes the figure and the table; returns the table's data.

    Raises:
        ValueError: no seed, or ``every`` below 1.
    """
    if not seeds:
        raise ValueError("The lab needs at least one seed (--seeds).")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"--every must be a positive number of updates, got {every!r}.")
    root = Path(root)
    runs = {seed: root / f"seed{seed}" for seed in seeds}
    for seed, run_dir in runs.items():  # before any training: one setting per folder
        own = dataclasses.replace(cfg, seed=seed, run_dir=run_dir, grad_stats=every)
        _same_setting(own if recipe.prepare is None else recipe.prepare(own), run_dir)
    for seed, run_dir in runs.items():
        if _finished(run_dir):
            continue
        resume = (run_dir / CHECKPOINT).exists()
        recipe.train(
            dataclasses.replace(cfg, seed=seed, run_dir=run_dir, grad_stats=every, resume=resume)
        )
    return summarise(runs, root, title=f"{recipe.name}: gradient noise of each return estimator")


def _same_setting(cfg: TrainConfig, run_dir: Path) -> None:
    """Refuses a lab folder whose seed ``run_dir`` was trained with other settings than
    ``cfg``'s: its seeds would be measured under two settings and pooled as one."""
    if not (run_dir / "config.json").is_file():
        return
    stored = _config(run_dir)
    keep = frozenset({"resume", "run_dir", "progress", "threads", "workers", "ray"})
    changed = changed_settings(cfg, stored, may_change=keep | _LOGGING)
    if changed:
        details = ", ".join(
            f"--{k.replace('_', '-')} {_shown(old)} (now {_shown(new)})"
            for k, (old, new) in changed.items()
        )
        raise ValueError(
            f"{run_dir} was trained with {details}: a lab folder holds the seeds of one "
            f"setting. Give these flags another --run-dir, or repeat that seed's."
        )


_LOGGING = frozenset(TrainConfig.groups["logging"][1])


def _shown(value: Any) -> str:
    return (
        "unset"
        if value is None
        else " ".join(map(str, value))
        if isinstance(value, list)
        else str(value)
    )


def _finished(run_dir: Path) -> bool:
    path = run_dir / SUMMARY
    if not path.is_file():
        return False
    try:
        return not json.loads(path.read_text()).get("interrupted", False)
    except json.JSONDecodeError:
        return False


def measurements(run_dir: Path, estimator: str) -> dict[str, np.ndarray]:
    """A run's logged measurements of ``estimator``: ``frames``, ``trace_covariance``,
    ``grad_norm_sq`` and ``units``, one entry per measured update."""
    out = {}
    for name in ("trace_covariance", "grad_norm_sq", "units"):
        out["frames"], out[name] = read_curve(run_dir, f"grad/{estimator}/{name}")
    return out


def noise_scale_curve(
    runs: Sequence[dict[str, np.ndarray]], edges: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(frames, noise scale, snr)`` in each window ``edges[i] <= frames < edges[i+1]``,
    pooling the measurements of every run in it: `B` is the ratio of their means, the
    SNR at the batch size used their mean units over `B`. NaN where a window has no
    measurement or its mean `|∇J|²` is not positive.

    Examples:
        >>> import numpy as np
        >>> from rl_pg.app.lab import noise_scale_curve
        >>> run = {"frames": np.array([64.0, 128.0]), "trace_covariance": np.array([4.0, 8.0]),
        ...        "grad_norm_sq": np.array([1.0, -1.0]), "units": np.array([8.0, 8.0])}
        >>> noise_scale_curve([run], np.array([0.0, 100.0, 200.0]))
        (array([ 50., 150.]), array([ 4., nan]), array([ 2., nan]))
        >>> noise_scale_curve([run], np.array([0.0, 200.0]))[1]  # pooled: 6 / 0
        array([nan])
    """
    centres, scale, snr = [], [], []
    for low, high in itertools.pairwise(edges):
        pooled = {key: [] for key in ("trace_covariance", "grad_norm_sq", "units")}
        for run in runs:
            inside = (run["frames"] >= low) & (run["frames"] < high)
            for key, values in pooled.items():
                values.append(run[key][inside])
        trace, signal, units = (np.concatenate(v) for v in pooled.values())
        b = np.nan
        if len(signal) and signal.mean() > 0:
            b = trace.mean() / signal.mean()
        centres.append((low + high) / 2)
        scale.append(b)
        snr.append(units.mean() / b if np.isfinite(b) else np.nan)
    return np.array(centres), np.array(scale), np.array(snr)


def summarise(runs: dict[int, Path], root: Path, *, title: str) -> dict[str, Any]:
    """The figure (``root/variance.png``) and the table (``root/variance.md``,
    ``root/variance.json``) of the runs ``{seed: run_dir}``; returns the table's data:
    for each estimator measured, each seed's noise scale over its whole run and over
    each half, and the mean units per measurement."""
    estimators = [
        e
        for e in ESTIMATORS
        if all(
            (r / "logs/csv/scalars/grad" / e / "trace_covariance.csv").is_file()
            for r in runs.values()
        )
    ]
    if not estimators:
        raise FileNotFoundError(_nothing_measured(runs, root))
    table: dict[str, Any] = {"seeds": list(runs), **_units(runs), "estimators": {}}
    for estimator in estimators:
        measured = {seed: measurements(run_dir, estimator) for seed, run_dir in runs.items()}
        end = max(m["frames"].max() for m in measured.values()) + 1
        pooled = noise_scale_curve(list(measured.values()), np.array([0.0, end / 2, end]))
        whole = noise_scale_curve(list(measured.values()), np.array([0.0, end]))
        table["estimators"][estimator] = {
            "noise_scale": float(whole[1][0]),
            "noise_scale_first_half": float(pooled[1][0]),
            "noise_scale_second_half": float(pooled[1][1]),
            "snr": float(whole[2][0]),
            "units": float(np.concatenate([m["units"] for m in measured.values()]).mean()),
            "measurements": int(sum(len(m["frames"]) for m in measured.values())),
            "variance_relative_to_episode_return": float(
                relative_variance(
                    list(measured.values()),
                    [measurements(r, "episode_return") for r in runs.values()],
                    np.array([0.0, end]),
                )[0]
            )
            if "episode_return" in estimators and _comparable(estimator, runs)
            else None,
            "noise_scale_by_seed": {
                seed: float(noise_scale_curve([m], np.array([0.0, end]))[1][0])
                for seed, m in measured.items()
            },
        }
    table["held"] = {seed: _held(run_dir) for seed, run_dir in runs.items()}
    # the data first: a figure that fails loses no measurement
    write_atomically(root / "variance.json", json.dumps(table, indent=2))
    write_atomically(root / "variance.md", _markdown(table))
    _figure(runs, estimators, root / "variance.png", title=title)
    # The quietest estimator resolves the signal |∇J|² best (they share it, GAE nearly).
    quietest = next(e for e in ("gae", "reward_to_go_minus_value", *estimators) if e in estimators)
    _seed_figure(
        runs, table["held"], root / "variance_by_seed.png", title=title, estimator=quietest
    )
    return table


def _config(run_dir: Path) -> dict[str, Any]:
    """A seed's stored config, or a ValueError naming the file."""
    return read_json(run_dir / "config.json", what="a run's config", schema={},
                     fix=f"remove {run_dir} to train that seed anew")  # fmt: skip


def _nothing_measured(runs: dict[int, Path], root: Path) -> str:
    """Why no estimator's statistics are in every run, and what to change."""
    short = []
    for seed, run_dir in runs.items():
        try:
            every = json.loads((run_dir / "config.json").read_text()).get("grad_stats")
            updates = json.loads((run_dir / SUMMARY).read_text())["updates"]
        except (OSError, ValueError, KeyError):
            continue
        if not every:
            return (
                f"{run_dir} measured no gradient statistics (a run trained without "
                f"--grad-stats, not by rl-pg lab): give the lab another --run-dir."
            )
        if updates < every:
            short.append(f"seed {seed} trained {updates} updates")
    if short:
        return (
            f"The runs under {root} measured nothing: {', '.join(short)}, and a measurement "
            f"is taken every {every} updates (--every). Lower --every, or give each seed "
            f"a larger budget (--total-frames / --total-updates)."
        )
    return f"No gradient statistics in every run under {root}: train them with --grad-stats N."


def _units(runs: dict[int, Path]) -> dict[str, Any]:
    """The unit the runs were measured by: ``{"unit": "episode"}``, or for runs
    collected in groups ``{"unit": "group", "group_size": K}`` (K sampled episodes each,
    so a noise scale of B groups is about K·B episodes)."""
    configs = [_config(run_dir) for run_dir in runs.values()]
    grouped = {c.get("baseline") in GROUP_BASELINES for c in configs}
    if grouped == {True}:
        sizes = {c["group_size"] for c in configs}
        if len(sizes) == 1:
            return {"unit": "group", "group_size": sizes.pop()}
    if True in grouped:
        raise ValueError(
            "The runs were measured by different units (some in groups, some by episode, or "
            "groups of different sizes): summarise runs of one kind together."
        )
    return {"unit": "episode"}


def _held(run_dir: Path) -> dict[str, Any] | None:
    """Whether the run's best checkpoint held the run's threshold on fresh episodes
    greedily and by sampling (its latest ``rl-pg evaluate`` results), with both means;
    None where either was not measured or the run has no threshold."""
    report = read_report(run_dir)
    threshold = report["threshold"]
    greedy, sampled = report["greedy"], report["sampled"]
    if threshold is None or greedy is None or sampled is None:
        return None
    means = greedy["mean_return"], sampled["mean_return"]
    return {"holds": min(means) >= threshold, "greedy": means[0], "sampled": means[1]}


_GROUPS = {"holds": "tab:green", "drops": "tab:red", "not evaluated": "tab:grey"}


def _group(verdict: dict[str, Any] | None) -> str:
    if verdict is None:
        return "not evaluated"
    return "holds" if verdict["holds"] else "drops"


def _seed_figure(runs, held, path: Path, *, title: str, estimator: str) -> None:
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
            entropy = [_windowed(r, "train/entropy", edges) for r in members]
            if all(e is not None for e in entropy):
                entropy_ax.plot(frames, np.nanmean(np.stack(entropy), 0), marker=".", color=colour)
        returns = np.concatenate([read_curve(r, "eval/mean_return")[1] for r in runs.values()])
        top.set_ylim(bottom=np.percentile(returns, 5))
        recipe = title.split(":")[0]
        top.set(
            ylabel="evaluation mean return", title=f"{recipe}: seeds that hold, seeds that drop"
        )
        top.legend(loc="best", fontsize="small", title="best checkpoint on fresh episodes")
        _log_scale(scale_ax, f"noise scale B, {estimator}")
        _log_scale(snr_ax, "SNR at the batch size")
        entropy_ax.set(ylabel="policy entropy (training)", xlabel="frames")


def _log_scale(ax, label: str) -> None:
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


def _windowed(run_dir: Path, metric: str, edges: np.ndarray) -> np.ndarray | None:
    """The mean of a logged ``metric`` in each window (None if the run did not log it)."""
    try:
        frames, values = read_curve(run_dir, metric)
    except FileNotFoundError:
        return None
    return np.array(
        [
            values[(frames >= low) & (frames < high)].mean()
            if ((frames >= low) & (frames < high)).any()
            else np.nan
            for low, high in itertools.pairwise(edges)
        ]
    )


def _markdown(table: dict[str, Any]) -> str:
    """The table: each estimator's noise scale over every seed's measurements pooled,
    in the first and the second half of training, the SNR at the batch size used, and
    each seed alone (— where the mean signal was not positive: noise dominates)."""
    scale, units = "noise scale B", "units"
    if table.get("unit") == "group":  # B counts groups
        scale, units = f"noise scale B (groups of {table['group_size']})", "groups"
    lines = [
        f"| estimator | tr Σ / tr Σ of R(τ) | {scale} | first half | second half "
        f"| SNR at the batch size ({units}) | B by seed |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for estimator, row in table["estimators"].items():
        by_seed = " / ".join(_number(b) for b in row["noise_scale_by_seed"].values())
        relative = row["variance_relative_to_episode_return"]
        lines.append(
            f"| {estimator} | {_number(np.nan if relative is None else relative)} | "
            f"{_number(row['noise_scale'])} | "
            f"{_number(row['noise_scale_first_half'])} | "
            f"{_number(row['noise_scale_second_half'])} | "
            f"{_number(row['snr'])} ({row['units']:.3g}) | {by_seed} |"
        )
    return "\n".join(lines) + "\n"


def _number(value: float) -> str:
    return "—" if not np.isfinite(value) else f"{value:,.3g}"


def relative_variance(
    runs: Sequence[dict[str, np.ndarray]],
    reference: Sequence[dict[str, np.ndarray]],
    edges: np.ndarray,
) -> np.ndarray:
    """In each window, the summed ``trace_covariance`` of ``runs`` over that of
    ``reference`` (another estimator measured on the very same batches): how much
    noisier or quieter one estimator is than the other on identical data. Unbiased
    estimators share `∇J`, so this is also the ratio of their noise scales.

    Examples:
        >>> import numpy as np
        >>> from rl_pg.app.lab import relative_variance
        >>> a = {"frames": np.array([1.0, 2.0]), "trace_covariance": np.array([1.0, 3.0])}
        >>> b = {"frames": np.array([1.0, 2.0]), "trace_covariance": np.array([8.0, 8.0])}
        >>> relative_variance([a], [b], np.array([0.0, 3.0]))
        array([0.25])
    """
    out = []
    for low, high in itertools.pairwise(edges):
        sums = []
        for measured in (runs, reference):
            inside = [
                m["trace_covariance"][(m["frames"] >= low) & (m["frames"] < high)] for m in measured
            ]
            sums.append(np.concatenate(inside).sum() if inside else 0.0)
        out.append(sums[0] / sums[1] if sums[1] > 0 else np.nan)
    return np.array(out)


def _comparable(estimator: str, runs: dict[int, Path]) -> bool:
    """Whether ``estimator``'s variance is at the scale of the returns': the loss's own
    `Ψ` is not when the runs standardise it (``normalize_advantage``), nor a group
    advantage divided by its group's standard deviation."""
    if estimator == "group_mean_scaled":
        return False
    if estimator != "loss":
        return True
    configs = [_config(run_dir) for run_dir in runs.values()]
    return not any(c.get("normalize_advantage", False) for c in configs)


def _figure(runs: dict[int, Path], estimators: list[str], path: Path, *, title: str) -> None:
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
            if _comparable(estimator, runs):
                ratio = relative_variance(measured[estimator], measured[reference], edges)
            else:  # keeps its colour in the other panels
                ratio = np.full_like(centres, np.nan)
            (line,) = top.plot(centres, ratio, marker=".", label=estimator)
            frames, scale, _ = noise_scale_curve(measured[estimator], edges[::2])
            middle.plot(frames, scale, marker=".", color=line.get_color())
            if len(runs) > 1 and _comparable(estimator, runs):
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
        _log_scale(top, f"tr Σ relative to {reference}")
        top.set(title=title)
        top.legend(loc="best", fontsize="small")
        units = _units(runs)
        unit = f"groups of {units['group_size']}" if units["unit"] == "group" else "units"
        _log_scale(middle, f"noise scale B ({unit})")
        bottom.set(ylabel="evaluation mean return", xlabel="frames")
        bottom.legend(loc="best", fontsize="small")
