"""Figures of stored runs: every seed with their interquartile mean, settings side by
side (``rl-pg report --stored FILE... --plot``), and performance profiles of the
best checkpoints held both ways (``--profile``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rl_pg.app.settings import by_setting
from rl_pg.app.stores import read_stored, stored_runs
from rl_pg.training.curves import (
    plot_profiles,
    plot_seeds,
    plot_settings,
    plot_solved,
    plot_solved_settings,
)
from rl_pg.training.metric import Metric

__all__ = ["plot_profile", "plot_stored"]


def plot_stored(
    paths: Path | list[Path], figure: Path, *, ylim: tuple[float, float] | None = None
) -> Path:
    """Draws the seeds of stored reports into ``figure``: each run's curve, and their
    interquartile mean with a 95 % bootstrap band (see
    [`plot_seeds`][rl_pg.training.curves.plot_seeds]); for runs that stopped when
    solved (their curves end where each passed), the share of them solved by each
    frame (see [`plot_solved`][rl_pg.training.curves.plot_solved]). Several files are
    several settings on one figure, one colour each, named by the file's stem.

    Raises:
        ValueError: a file that is not a stored report, or two files of one stem (the
            figure could not tell them apart).
    """
    paths = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    stems = [path.stem for path in paths]
    if len(set(stems)) != len(stems):
        raise ValueError(f"--plot names each file's runs by its stem; these repeat one: {paths}.")
    settings = {}
    for stem, runs in zip(_setting_names(stems), map(stored_runs, paths), strict=True):
        groups = by_setting(runs)  # runs of one file that differ in more than the seed
        if len(groups) == 1:
            settings[stem] = runs
        else:
            settings.update({f"{stem}: {label}": group for label, group in groups.items()})
    for name, group in settings.items():
        if len(group) < 2:
            raise ValueError(
                f"--plot draws the seeds of each setting with their spread, and the setting "
                f"{name!r} has {len(group)} run: store two or more seeds of it (a file "
                f"whose runs differ in more than the seed holds one setting per difference)."
            )
    stems = list(settings)
    paths = stems  # one figure per setting from here
    runs = [run for group in settings.values() for run in group]
    title = ", ".join(sorted({run["report"]["recipe"] for run in runs}))
    if all(run["config"].get("stop_when_solved") for run in runs):
        reached = {
            stem: {run["name"]: run["report"].get("solved_at_frames") for run in group}
            for stem, group in settings.items()
        }  # fmt: skip
        budget = max(run["report"]["frames"] for run in runs)  # where the last one stopped
        if len(paths) == 1:
            return plot_solved(reached[stems[0]], Path(figure), budget=budget, title=title)
        return plot_solved_settings(reached, Path(figure), budget=budget, title=title)
    metrics = {run["curve"]["metric"] for run in runs}
    thresholds = {run["report"].get("threshold") for run in runs}
    metric = metrics.pop() if len(metrics) == 1 else "the stored metric"
    windows = {run["curve"].get("window", 1) for run in runs}
    if windows != {1}:  # stored smoothed: say over how many logged values
        title += f" (curves: means of {'/'.join(map(str, sorted(windows)))} logged values)"
    shared = thresholds.pop() if len(thresholds) == 1 else None
    curves = {
        stem: {
            run["name"]: (np.array(run["curve"]["frames"]), np.array(run["curve"]["values"]))
            for run in group
        }
        for stem, group in settings.items()
    }
    judged = {Metric.of_summary(run["report"]).logged for run in runs}  # what thresholds judge
    draw = dict(
        ylabel=metric, title=title, ylim=ylim,
        threshold=shared if judged == {metric} else None,
    )  # fmt: skip
    if len(paths) == 1:
        return plot_seeds(curves[stems[0]], Path(figure), **draw)
    return plot_settings(curves, Path(figure), **draw)


def _setting_names(stems: list[str]) -> list[str]:
    """Files' stems without the words all of them start with (``gridworld-no-baseline``,
    ``gridworld-reward-to-go`` -> ``no-baseline``, ``reward-to-go``).

    Examples:
        >>> from rl_pg.app.figures import _setting_names
        >>> _setting_names(["bandit-ema", "bandit-no-baseline"]), _setting_names(["seeds"])
        (['ema', 'no-baseline'], ['seeds'])
    """
    words = [stem.split("-") for stem in stems]
    shared = 0
    while len(stems) > 1 and all(
        len(w) > shared + 1 and w[shared] == words[0][shared] for w in words
    ):
        shared += 1
    return ["-".join(w[shared:]) for w in words]


def plot_profile(paths: list[Path], figure: Path) -> Path:
    """Draws the performance profile of each stored file's runs into ``figure``: a run's
    score is its best checkpoint's lower mean return of the greedy and the sampled
    evaluations (what it holds both ways). Each file is one setting, named by its stem.

    Raises:
        ValueError: a file that is not a stored report, or a run in it without both
            evaluations (the message names the file and the run).
    """
    scores, thresholds, recipes = {}, set(), set()
    for path in paths:
        reports, names = read_stored(path)
        for report, name in zip(reports, names, strict=True):
            if report["greedy"] is None or report["sampled"] is None:
                raise ValueError(
                    f"{path}: run {name} has no greedy and sampled evaluation of its best "
                    f"checkpoint (rl-pg evaluate RUN --episodes 100, and with --sample), so "
                    f"it has no score to profile; evaluate it, then --store again."
                )
        scores[Path(path).stem] = np.array(
            [min(r["greedy"]["mean_return"], r["sampled"]["mean_return"]) for r in reports]
        )
        thresholds |= {r.get("threshold") for r in reports}
        recipes |= {r["recipe"] for r in reports}
    return plot_profiles(
        scores,
        Path(figure),
        xlabel="τ: the best checkpoint's mean return, the lower of greedy and sampled",
        title=", ".join(sorted(recipes)),
        threshold=thresholds.pop() if len(thresholds) == 1 else None,
    )
