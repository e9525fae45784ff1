"""What ``rl-pg report`` reads of a run directory, and the JSON stores of runs it
writes (``--store``) and reads back (``--stored``): each run's summary, its best
and final checkpoints' ``rl-pg evaluate`` results, its config and a curve.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.app.evaluate import EVALUATIONS
from rl_pg.checkpoint import write_atomically
from rl_pg.training.curves import (
    read_curve,
)
from rl_pg.training.metric import Metric
from rl_pg.training.records import (
    EVALUATION_RECORD,
    RUN_SUMMARY,
    check_values,
    optional,
    read_json,
)
from rl_pg.training.run_dir import CONFIG, SUMMARY
from rl_pg.training.seeds import fresh_seed

__all__ = [
    "MODES",
    "STORED_POINTS",
    "holds",
    "is_store",
    "read_report",
    "read_stored",
    "run_names",
    "smoothed",
    "store_report",
    "stored_runs",
]

STORED_POINTS = 200  # a stored curve's most points: longer ones are stored smoothed


def read_report(run_dir: Path) -> dict[str, Any]:
    """A run's summary, with its best checkpoint's latest greedy and sampled
    ``rl-pg evaluate`` results (``"greedy"``, ``"sampled"``; ``None`` when there are
    none of that checkpoint), those on its default fresh episodes first, the final
    checkpoint's (``"last"``) and the training's frames per second."""
    path = Path(run_dir) / SUMMARY
    if not path.is_file():
        raise ValueError(
            f"{run_dir} has no {SUMMARY}: not a run directory, or its first run is still "
            "going (a run writes its summary when it ends or is interrupted)."
        )
    try:
        report = check_values(json.loads(path.read_text()), RUN_SUMMARY, str(path))
    except ValueError as err:  # not JSON, or a field missing or wrong
        why = str(err).removeprefix(f"{path}: ")
        raise ValueError(
            f"{path} is not a run summary ({why}); rl-pg resume {run_dir} writes it again "
            f"when the run ends or is stopped."
        ) from None
    report["greedy"] = report["sampled"] = None
    report["last"] = {"greedy": None, "sampled": None}
    # the training's speed over all its sessions (train_wall_s leaves evaluations out)
    seconds = report["train_wall_s"]
    report["frames_per_s"] = report["frames"] / seconds if seconds else None
    evaluations = Path(run_dir) / EVALUATIONS
    if evaluations.is_file():
        # best.pt moves on when a resumed run evaluates better: only results of the
        # checkpoint that is best now, on the recipe's test set (not `--on` another one),
        # describe it; of those, the latest on rl-pg evaluate's own episodes (a result on
        # episodes chosen with --seed is only taken where there is none). The same for
        # the last checkpoint, at the frames the run ended on.
        fresh = fresh_seed(report["seed"])
        for number, line in enumerate(evaluations.read_text().splitlines(), start=1):
            where = f"{evaluations}, line {number}"
            try:
                record = check_values(json.loads(line), EVALUATION_RECORD, where)
            except ValueError as err:
                if line.strip():  # a write killed half-way, or an edit: say so, skip it
                    why = str(err).removeprefix(f"{where}: ")
                    print(
                        f"rl-pg report: {where}, is not an evaluation record ({why}); skipped.",
                        file=sys.stderr,
                    )
                continue
            if "on" in record:
                continue
            if record["checkpoint"] == "best" and record["frames"] == report["best_at_frames"]:
                results = report
            elif record["checkpoint"] == "last" and record["frames"] == report["frames"]:
                results = report["last"]
            else:
                continue
            kept = results[record["mode"]]
            if kept is None or record["seed"] == fresh or kept["seed"] != fresh:
                results[record["mode"]] = record
    return report


def is_store(path: str | Path) -> bool:
    """Whether ``path`` is a table store ``--store`` wrote (JSON with its ``"runs"``)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(data, dict) and isinstance(data.get("runs"), list)


def store_report(runs: list[Path], path: Path, *, metric: str = "eval/mean_return") -> None:
    """Writes the runs' rows (as ``read_report`` reads them), names, configs and
    ``metric`` curves to the JSON file ``path`` (atomically). A curve of more than
    ``STORED_POINTS`` points (a training metric, logged every few updates) is stored
    smoothed: see ``smoothed``."""
    names = run_names(runs)
    stored = []
    for name, run in zip(names, runs, strict=True):
        frames, values, window = smoothed(*read_curve(run, metric))
        fix = "it is written as the run starts: restore it from a copy"
        config = read_json(Path(run) / CONFIG, what="a run's config", schema={}, fix=fix)
        curve = {"metric": metric, "window": window, "frames": frames.tolist(),
                 "values": values.tolist()}  # fmt: skip
        stored.append({"name": name, "report": read_report(run), "config": config, "curve": curve})
    write_atomically(Path(path), json.dumps({"runs": stored}, indent=1) + "\n")


def smoothed(
    frames: np.ndarray, values: np.ndarray, points: int | None = None
) -> tuple[np.ndarray, np.ndarray, int]:
    """A curve of at most ``points`` points (default ``STORED_POINTS``): the means of
    consecutive windows of ``window`` logged values, each at its window's last frame
    (a last, shorter window keeps the curve's end), and ``window`` (1: as logged).

    Examples:
        >>> import numpy as np
        >>> from rl_pg.app.stores import smoothed
        >>> smoothed(np.arange(1.0, 6.0), np.array([0.0, 1.0, 0.0, 1.0, 1.0]), points=2)
        (array([3., 5.]), array([0.33333333, 1.        ]), 3)
    """
    points = STORED_POINTS if points is None else points
    window = max(1, -(-len(values) // points))  # the smallest that fits
    if window == 1:
        return frames, values, 1
    starts = np.arange(0, len(values), window)
    means = np.add.reduceat(values, starts) / np.diff(np.append(starts, len(values)))
    ends = np.minimum(starts + window, len(values)) - 1
    return frames[ends], means, window


def read_stored(path: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """The rows and names ``store_report`` wrote to ``path``.

    Raises:
        ValueError: ``path`` is missing, or is not a file ``--store`` wrote (the
            message names the file).
    """
    runs = stored_runs(path)
    return [run["report"] for run in runs], [run["name"] for run in runs]


def stored_runs(path: Path) -> list[dict[str, Any]]:
    """The runs a file written by ``--store`` holds (each with its name, report, config
    and curve), every value checked, or a ValueError naming the file and the field."""
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError as err:
        raise ValueError(
            f"{path} does not exist: write it with rl-pg report RUN... --store."
        ) from err
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(
            f"{path} is not a stored report ({type(err).__name__}: {err}); write it with "
            f"rl-pg report RUN... --store {path}."
        ) from err
    try:
        if not isinstance(data, dict) or not isinstance(data.get("runs"), list):
            raise ValueError(f'{path}: should hold {{"runs": [...]}}.')
        for number, run in enumerate(data["runs"]):
            where = f"{path}, run {number}"
            check_values(run, STORED_RUN, where)
            check_values(run["report"], optional(RUN_SUMMARY), f"{where}, report")
            for mode in ("greedy", "sampled"):
                if run["report"].get(mode) is not None:
                    check_values(
                        run["report"][mode], optional(EVALUATION_RECORD), f"{where}, {mode}"
                    )
            curve = check_values(run["curve"], STORED_CURVE, f"{where}, curve")
            if "frames" in curve and len(curve["frames"]) != len(curve["values"]):
                raise ValueError(
                    f"{where}, curve: {len(curve['frames'])} frames for "
                    f"{len(curve['values'])} values."
                )
    except ValueError as err:
        raise ValueError(
            f"{err} It is not a stored report as rl-pg report writes one: write it again "
            f"with rl-pg report RUN... --store {path}."
        ) from None
    return data["runs"]


# What each reading of a store needs is there; whatever is there holds its kind.
STORED_RUN = {"name": "text", "report": "object", "config?": "object", "curve": "object"}

STORED_CURVE = {"metric?": "text", "frames?": "list of numbers", "values": "list of numbers",
                "window?": "count"}  # fmt: skip


def holds(report: dict[str, Any]) -> bool | None:
    """Whether a run's best checkpoint reaches its threshold both greedily and by
    sampling (the worse of the two on the metric the run selected by); None without a
    threshold or without both evaluations."""
    if report.get("threshold") is None or not report.get("greedy") or not report.get("sampled"):
        return None
    metric = Metric.of_summary(report)
    values = [report[mode].get(metric.key) for mode in ("greedy", "sampled")]
    if None in values:  # evaluated before the recipe reported its metric
        return None
    return metric.reaches(metric.worst(values), report["threshold"])


MODES = ("greedy", "sampled")


def run_names(runs: list[Path]) -> list[str]:
    """The shortest distinct names: the folders' own names, or whole paths if two share one."""
    names = [run.resolve().name for run in runs]
    return names if len(set(names)) == len(names) else [str(run) for run in runs]
