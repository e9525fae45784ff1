"""rl_pg.training.curves: the seeds' aggregate (interquartile mean, bootstrap band) and
the figures drawn from it."""

from __future__ import annotations

import numpy as np
import pytest

from rl_pg.training.aggregates import interquartile_mean, seed_aggregate
from rl_pg.training.curves import plot_seeds


def test_interquartile_mean_is_the_mean_of_the_middle_half():
    rng = np.random.default_rng(0)
    values = rng.normal(size=(12, 5))
    middle = np.sort(values, axis=0)[3:9]  # 12 seeds: drop the 3 lowest and 3 highest
    np.testing.assert_allclose(interquartile_mean(values), middle.mean(0))
    # one failed seed moves the mean, not the interquartile mean
    spoiled = values.copy()
    spoiled[0] = -1e6
    assert abs(interquartile_mean(spoiled) - interquartile_mean(values)).max() < 1.0
    assert abs(spoiled.mean(0) - values.mean(0)).min() > 1e4


def test_the_bootstrap_band_covers_the_truth_and_narrows_with_seeds():
    rng = np.random.default_rng(1)
    covered, widths = 0, {}
    for seeds in (5, 40):
        for _ in range(40):
            values = rng.normal(loc=3.0, size=(seeds, 1))
            iqm, low, high = seed_aggregate(values, resamples=500)
            assert low[0] <= iqm[0] <= high[0]
            covered += seeds == 40 and low[0] <= 3.0 <= high[0]
            widths.setdefault(seeds, []).append(high[0] - low[0])
    # a 95 % band misses the true centre of a symmetric law about 1 time in 20
    assert covered >= 32
    assert np.mean(widths[40]) < 0.5 * np.mean(widths[5])
    # the same data, the same band
    values = rng.normal(size=(6, 3))
    for a, b in zip(seed_aggregate(values), seed_aggregate(values), strict=True):
        np.testing.assert_array_equal(a, b)


def test_one_seed_or_unaligned_seeds_are_refused(tmp_path):
    with pytest.raises(ValueError, match="at least 2 seeds"):
        seed_aggregate(np.ones((1, 4)))
    frames = np.arange(3.0)
    with pytest.raises(ValueError, match="same frames"):
        plot_seeds(
            {"a": (frames, frames), "b": (frames + 1, frames)}, tmp_path / "x.png",
            ylabel="y", title="t",
        )  # fmt: skip
    figure = plot_seeds(
        {"a": (frames, frames), "b": (frames, 2 * frames)}, tmp_path / "x.png",
        ylabel="y", title="t", threshold=1.0, ylim=(0, 5),
    )  # fmt: skip
    assert figure.read_bytes()[:4] == b"\x89PNG"


def test_seeds_evaluated_a_batch_apart_are_aggregated_at_their_median_frames(tmp_path):
    """Whole-episode runs evaluate at the first batch past each interval: a few frames
    apart is the same evaluation; half an interval apart is not."""
    values = np.array([1.0, 2.0, 3.0])
    curves = {"a": (np.array([5_056, 10_048, 15_040]), values),
              "b": (np.array([5_120, 10_112, 15_104]), values + 1)}  # fmt: skip
    assert plot_seeds(curves, tmp_path / "ok.png", ylabel="r", title="t").is_file()
    curves["b"] = (np.array([7_600, 12_600, 17_600]), values)
    with pytest.raises(ValueError, match="within half an interval"):
        plot_seeds(curves, tmp_path / "no.png", ylabel="r", title="t")
