"""What a run shows while it trains, and the summary it ends with.

On a terminal: a progress bar. Anywhere else (``nohup``, batch jobs, CI logs, a pipe):
a compact line every ``every_s`` seconds and after every evaluation, so that a log
shows progress long before the run ends.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any, TextIO

from tqdm import tqdm

from rl_pg.training.metric import Metric

__all__ = ["Console", "format_comparison", "format_summary"]


class Console:
    """Progress of a run, on ``stream`` (standard error by default).

    Keyword Args:
        total_frames (int): the run's frame budget.
        initial_frames (int): frames already done (a resumed run).
        total_updates (int, optional): the run's update budget, when it has one. The
            progress then counts to the frames at which the first of the two limits
            ends the run (projected from the frames per update so far) and shows the
            updates too.
        enabled (bool): show anything at all (``--progress``).
        stream (TextIO, optional): where to write. Defaults to ``sys.stderr``.
        every_s (float): seconds between two lines when not on a terminal.
            Defaults to ``10``.
    """

    def __init__(
        self,
        *,
        total_frames: int,
        initial_frames: int,
        enabled: bool,
        total_updates: int | None = None,
        stream: TextIO | None = None,
        every_s: float = 10.0,
    ) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.every_s = every_s
        on_terminal = enabled and _is_terminal(self.stream)
        self.bar = (
            tqdm(total=total_frames, initial=initial_frames, unit="frames", file=self.stream)
            if on_terminal
            else None
        )
        self.lines = enabled and not on_terminal
        self.total_frames = total_frames
        self.total_updates = total_updates
        self._last = (time.monotonic(), initial_frames)
        self._train_return = math.nan

    def update(
        self,
        frames: int,
        spent: int,
        metrics: dict[str, float] | None,
        last_eval: dict[str, float],
        *,
        evaluated: bool = False,
        updates: int | None = None,
    ) -> None:
        """Reports the frames done (and the ``updates``); ``metrics`` when the update
        was logged."""
        if metrics is not None and math.isfinite(metrics.get("train/episode_return", math.nan)):
            self._train_return = metrics["train/episode_return"]  # else: no episode ended
        eval_mean = last_eval.get("eval/mean_return", math.nan)
        end, of_updates = self.total_frames, ""
        if self.total_updates is not None and updates:
            end = min(end, frames + round((self.total_updates - updates) * frames / updates))
            of_updates = f" | update {updates:,}/{self.total_updates:,}"
        if self.bar is not None:
            if self.bar.total != end:
                self.bar.total = end
            self.bar.set_postfix(
                train=f"{self._train_return:.2f}", eval=f"{eval_mean:.2f}", refresh=False
            )
            self.bar.update(spent)
        elif self.lines:
            now = time.monotonic()
            if evaluated or now - self._last[0] >= self.every_s:
                fps = (frames - self._last[1]) / max(now - self._last[0], 1e-9)
                self._last = (now, frames)
                losses = "" if metrics is None else _losses(metrics)
                print(
                    f"frames {frames:,}/{end:,}{of_updates} | {fps:,.0f} frames/s | train "
                    f"return {self._train_return:.2f}{losses} | eval {eval_mean:.2f}",
                    file=self.stream,
                    flush=True,
                )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def format_summary(summary: dict[str, Any]) -> str:
    """A run's summary as a few readable lines.

    Examples:
        >>> from rl_pg.training.console import format_summary
        >>> print(format_summary({
        ...     "recipe": "cartpole", "run_dir": "runs/x", "seed": 0, "frames": 20224,
        ...     "updates": 79, "train_wall_s": 1.2, "eval_mean_return": 500.0,
        ...     "eval_std_return": 0.0, "threshold": 475.0, "solved_at_frames": 20224,
        ...     "best_eval_mean_return": 500.0, "best_at_frames": 20224,
        ...     "interrupted": False,
        ... }))
        cartpole, seed 0: 20,224 frames, 79 updates, 1.2 s of training
          evaluation: 500.00 ± 0.00 (best 500.00 at 20,224 frames)
          solved: reached 475 at 20,224 frames
          run directory: runs/x
    """
    lines = [
        f"{summary['recipe']}, seed {summary['seed']}: {summary['frames']:,} frames, "
        f"{summary['updates']:,} updates, {summary['train_wall_s']:.1f} s of training"
        + (" (interrupted)" if summary.get("interrupted") else "")
    ]
    metric = Metric.of_summary(summary)
    if summary.get("eval_mean_return") is not None:
        line = f"  evaluation: {summary['eval_mean_return']:.2f} ± {summary['eval_std_return']:.2f}"
        if summary.get("best_eval_mean_return") is not None and metric.key == "mean_return":
            line += (
                f" (best {summary['best_eval_mean_return']:.2f} at "
                f"{summary['best_at_frames']:,} frames)"
            )
        lines.append(line)
    if metric.key != "mean_return" and summary.get("best_eval_value") is not None:
        lines.append(
            f"  best checkpoint by {metric.key}: {metric.text(summary['best_eval_value'])} at "
            f"{summary['best_at_frames']:,} frames (return {summary['best_eval_mean_return']:.2f})"
        )
    rates = {k: v for k, v in summary.items() if k.endswith("_rate")}
    if rates:
        lines.append("  " + ", ".join(f"{k}: {v:.0%}" for k, v in rates.items()))
    if summary.get("threshold") is not None:
        solved = summary.get("solved_at_frames")
        lines.append(
            f"  solved: reached {summary['threshold']:.4g} at {solved:,} frames"
            if solved is not None
            else f"  solved: not yet (threshold {summary['threshold']:.4g})"
        )
    if summary.get("best_confirmed") is not None:
        lines.append(
            f"  best confirmed (worse of greedy and sampled): {summary['best_confirmed']:.2f}"
        )
    sessions = summary.get("sessions", [])
    if len(sessions) > 1:
        resumed = len(sessions) - 1
        times = "once" if resumed == 1 else f"{resumed} times"
        lines.append(f"  sessions: {len(sessions)} (stopped and resumed {times})")
    extra = {
        k: v
        for k, v in summary.items()
        if k not in _SUMMARY_FIELDS and k not in rates and v is not None
    }
    lines.extend(f"  {k.replace('_', ' ')}: {_number(v)}" for k, v in extra.items())
    lines.append(f"  run directory: {summary['run_dir']}")
    return "\n".join(lines)


def format_comparison(results: dict[str, list[dict[str, Any]]]) -> str:
    """Several variants' runs (``{variant: [summary per seed]}``), one line per variant.

    Examples:
        >>> from rl_pg.training.console import format_comparison
        >>> print(format_comparison({"no baseline": [
        ...     {"run_dir": "runs/c/no baseline/seed0", "eval_mean_return": 0.9,
        ...      "solved_at_frames": None},
        ...     {"run_dir": "runs/c/no baseline/seed1", "eval_mean_return": 1.0,
        ...      "solved_at_frames": 3000}]}))
        no baseline: 1/2 seeds solved, last evaluation 0.90 1.00 (runs/c/no baseline)
    """
    lines = []
    for variant, runs in results.items():
        solved = sum(run.get("solved_at_frames") is not None for run in runs)
        evals = " ".join(_number(run.get("eval_mean_return")) for run in runs)
        folder = Path(runs[0]["run_dir"]).parent if runs else ""
        lines.append(
            f"{variant}: {solved}/{len(runs)} seeds solved, last evaluation {evals} ({folder})"
        )
    return "\n".join(lines)


_SUMMARY_FIELDS = frozenset(
    {
        "recipe",
        "run_dir",
        "seed",
        "frames",
        "updates",
        "train_wall_s",
        "eval_mean_return",
        "eval_std_return",
        "threshold",
        "solved_at_frames",
        "best_eval_mean_return",
        "best_at_frames",
        "best_confirmed",
        "select_by",
        "select_mode",
        "eval_value",
        "best_eval_value",
        "sessions",
        "interrupted",
    }
)


def _number(value: Any) -> str:
    return f"{value:.2f}" if isinstance(value, float) else str(value)


def _losses(metrics: dict[str, float]) -> str:
    parts = [
        f"{k.removeprefix('loss/')} {v:.3g}" for k, v in metrics.items() if k.startswith("loss/")
    ]
    return f" | loss {' '.join(parts)}" if parts else ""


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False
