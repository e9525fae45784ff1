"""What the variance lab reads of its runs: each estimator's logged gradient-noise
measurements, the noise scale and SNR pooled over frame windows, one estimator's
variance relative to another's, and the unit (episode or group) they were measured by.

A noise scale is a ratio of means, `B = mean(tr Σ) / mean(|∇J|²)` over the
measurements of a window, as McCandlish et al. (2018) average it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.groups import GROUP_BASELINES
from rl_pg.training.curves import read_curve
from rl_pg.training.records import read_json

__all__ = [
    "comparable",
    "measurements",
    "noise_scale_curve",
    "relative_variance",
    "stored_config",
    "units",
    "windowed",
]


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
        >>> from rl_pg.app.noise import noise_scale_curve
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


def stored_config(run_dir: Path) -> dict[str, Any]:
    """A seed's stored config, or a ValueError naming the file."""
    return read_json(run_dir / "config.json", what="a run's config", schema={},
                     fix=f"remove {run_dir} to train that seed anew")  # fmt: skip


def units(runs: dict[int, Path]) -> dict[str, Any]:
    """The unit the runs were measured by: ``{"unit": "episode"}``, or for runs
    collected in groups ``{"unit": "group", "group_size": K}`` (K sampled episodes each,
    so a noise scale of B groups is about K·B episodes)."""
    configs = [stored_config(run_dir) for run_dir in runs.values()]
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


def windowed(run_dir: Path, metric: str, edges: np.ndarray) -> np.ndarray | None:
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
        >>> from rl_pg.app.noise import relative_variance
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


def comparable(estimator: str, runs: dict[int, Path]) -> bool:
    """Whether ``estimator``'s variance is at the scale of the returns': the loss's own
    `Ψ` is not when the runs standardise it (``normalize_advantage``), nor a group
    advantage divided by its group's standard deviation."""
    if estimator == "group_mean_scaled":
        return False
    if estimator != "loss":
        return True
    configs = [stored_config(run_dir) for run_dir in runs.values()]
    return not any(c.get("normalize_advantage", False) for c in configs)
