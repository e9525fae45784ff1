"""Statistics over the seeds of a setting, as the reports and the plots give them:
the interquartile mean with a bootstrap confidence interval, the share of runs above a
score (a performance profile), and the share that reached a threshold by each frame."""

from __future__ import annotations

import numpy as np

__all__ = [
    "bootstrap_interval",
    "interquartile_mean",
    "performance_profile",
    "seed_aggregate",
    "share_of_runs",
    "solved_share",
]


def interquartile_mean(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """The mean of the middle half of ``values`` along ``axis`` (25 % trimmed at each
    end): robust to one seed that fails or one that is lucky, and less noisy than the
    median (Agarwal et al. 2021, "Deep RL at the edge of the statistical precipice").

    Examples:
        >>> import numpy as np
        >>> from rl_pg.training.aggregates import interquartile_mean
        >>> float(interquartile_mean(np.array([-500.0, 1.0, 2.0, 3.0, 4.0, 900.0, 5.0, 6.0])))
        3.5
    """
    from scipy.stats import trim_mean

    return trim_mean(values, 0.25, axis=axis)


def seed_aggregate(
    values: np.ndarray, *, confidence: float = 0.95, resamples: int = 2000
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Interquartile mean over seeds (``values``: ``[seeds, points]``) at each point,
    with a percentile-bootstrap confidence interval over the seeds (scipy's
    ``bootstrap``, a fixed random state: the same data give the same band).

    Returns:
        ``(iqm, low, high)``, each of shape ``[points]``.

    Raises:
        ValueError: fewer than 2 seeds (a single run has no spread to bound).
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2 or values.shape[0] < 2:
        raise ValueError(
            f"seed_aggregate needs values of shape [seeds, points] with at least 2 seeds, "
            f"got shape {values.shape}."
        )
    low, high = bootstrap_interval(values, interquartile_mean, confidence, resamples)
    return interquartile_mean(values), low, high


def bootstrap_interval(data, statistic, confidence: float, resamples: int):
    """The percentile-bootstrap interval of ``statistic`` over ``data``'s first axis
    (scipy's ``bootstrap``, a fixed random state: the same data give the same band)."""
    from scipy.stats import bootstrap

    interval = bootstrap(
        (data,), statistic, axis=0, vectorized=True, confidence_level=confidence,
        n_resamples=resamples, method="percentile", random_state=0,
    ).confidence_interval  # fmt: skip
    return interval.low, interval.high


def performance_profile(
    scores: np.ndarray, taus: np.ndarray, *, confidence: float = 0.95, resamples: int = 2000
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The share of runs scoring above each ``τ`` of ``taus`` (a performance profile, as
    Agarwal et al. 2021 recommend over a table of means: it shows the whole spread of the
    runs), with a percentile-bootstrap interval over the runs (scipy's ``bootstrap``, a
    fixed random state). The ``rliable`` package computes the same; it needs ``arch``,
    whose releases it accepts (< 8) do not import with pandas 3, so rl_pg uses scipy.

    Returns:
        ``(share, low, high)``, each of shape ``[len(taus)]``.

    Raises:
        ValueError: ``scores`` is not one score per run for at least 2 runs.

    Examples:
        >>> import numpy as np
        >>> from rl_pg.training.aggregates import performance_profile
        >>> share, low, high = performance_profile(np.array([1.0, 2.0, 3.0, 4.0]),
        ...                                        np.array([0.0, 2.5, 5.0]))
        >>> share.tolist(), bool((low <= share).all() and (share <= high).all())
        ([1.0, 0.5, 0.0], True)
    """
    return share_of_runs(
        scores, taus, np.greater, confidence, resamples, "performance_profile needs one score"
    )


def share_of_runs(values, points, compare, confidence: float, resamples: int, needs: str):
    """The share of runs whose value ``compare``s each of ``points``, with a
    percentile-bootstrap interval over the runs: ``(share, low, high)``, each
    ``[len(points)]``. ``needs`` opens the error for fewer than 2 runs."""
    values = np.asarray(values, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    if values.ndim != 1 or len(values) < 2:
        raise ValueError(f"{needs} per run for at least 2 runs, got shape {values.shape}.")

    def share(runs: np.ndarray, axis: int = -1) -> np.ndarray:
        runs = np.moveaxis(runs, axis, -1)  # [..., runs]
        return np.moveaxis(compare(runs[..., None], points).mean(axis=-2), -1, 0)

    low, high = bootstrap_interval(values, share, confidence, resamples)
    return share(values), low, high


def solved_share(
    reached: np.ndarray, frames: np.ndarray, *, confidence: float = 0.95, resamples: int = 2000
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The share of runs that reached their threshold by each of ``frames`` (``reached``:
    each run's frames to the threshold, ``inf`` for one that never did), with a
    percentile-bootstrap interval over the runs: the aggregate of runs that stop when
    solved, whose evaluation curves end at different frames.

    Examples:
        >>> import numpy as np
        >>> from rl_pg.training.aggregates import solved_share
        >>> share, low, high = solved_share(np.array([10.0, 20.0, 40.0, np.inf]),
        ...                                 np.array([0.0, 20.0, 100.0]))
        >>> share.tolist(), bool((low <= share).all() and (share <= high).all())
        ([0.0, 0.5, 0.75], True)
    """
    return share_of_runs(
        reached, frames, np.less_equal, confidence, resamples,
        "solved_share needs the frames to the threshold",
    )  # fmt: skip
