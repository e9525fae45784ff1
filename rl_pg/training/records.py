"""What the files a run writes may hold, field by field: readers check values, not only
keys, and name the file and the field that is wrong.

A schema maps each field to a kind: ``"count"`` (a whole number ≥ 0), ``"number"``
(any real number), ``"text"``, ``"flag"`` (true or false), a tuple of the values allowed,
or ``"list of numbers"``. A kind ending in ``"?"`` also allows ``null``; a field whose
name ends in ``"?"`` may be absent.

Examples:
    >>> from rl_pg.training.records import check_values
    >>> check_values({"frames": 10, "mode": "greedy"}, {"frames": "count", "mode": ("greedy",
    ...              "sampled")}, "summary.json")
    {'frames': 10, 'mode': 'greedy'}
    >>> check_values({"frames": "ten"}, {"frames": "count"}, "runs/x/summary.json")
    Traceback (most recent call last):
    ...
    ValueError: runs/x/summary.json: "frames" should be a whole number ≥ 0, got 'ten'.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["EVALUATION_RECORD", "RUN_SUMMARY", "check_values", "optional", "read_json"]

RUN_SUMMARY = {
    "recipe": "text",
    "seed": "count",
    "frames": "count",
    "train_wall_s": "number",
    "best_at_frames": "count?",
    "updates?": "count",
    "best_eval_mean_return?": "number?",
    "select_by?": "text",
    "select_mode?": ("max", "min"),
    "eval_value?": "number?",
    "best_eval_value?": "number?",
    "solved_at_frames?": "count?",
    "threshold?": "number?",
    "interrupted?": "flag",
}
"""A run's ``summary.json``, as ``rl-pg report`` reads it."""

EVALUATION_RECORD = {
    "checkpoint": "text",
    "frames": "count?",
    "mode": ("greedy", "sampled"),
    "seed": "count",
    "mean_return": "number",
    "std_return?": "number",
    "episodes?": "count",
    "on?": "text",
    "crashed_rate?": "number?",
}
"""A line of a run's ``evaluations.jsonl`` (what ``rl-pg evaluate`` appends)."""

_SAID = {
    "count": "a whole number ≥ 0",
    "number": "a number",
    "text": "text",
    "flag": "true or false",
    "list of numbers": "a list of numbers",
    "object": "a mapping of names to values",
}


def check_values(record: Any, schema: Mapping[str, Any], where: str) -> dict[str, Any]:
    """``record`` itself when every field of ``schema`` holds a value of its kind.

    Args:
        record: what was read (a dict, or a ValueError says it is not one).
        schema (mapping): field name (ending in ``?`` if it may be absent) to kind.
        where (str): the file (and line) named in the message.

    Raises:
        ValueError: ``record`` is not a dict, a field is missing, or holds a value not
            of its kind; the message names ``where``, the field and the value.
    """
    if not isinstance(record, dict):
        raise ValueError(f"{where}: should hold a JSON object, got {_short(record)}.")
    for key, kind in schema.items():
        name = key.removesuffix("?")
        if name not in record:
            if key.endswith("?"):
                continue
            raise ValueError(f'{where}: "{name}" is missing.')
        value = record[name]
        if isinstance(kind, str) and kind.endswith("?"):
            if value is None:
                continue
            kind = kind[:-1]
        if not _is(value, kind):
            said = _SAID.get(kind) if isinstance(kind, str) else " or ".join(map(repr, kind))
            raise ValueError(f'{where}: "{name}" should be {said}, got {_short(value)}.')
    return record


def read_json(path: str | Path, *, what: str, fix: str, schema: Mapping[str, Any] | None = None):
    """The JSON content of the file ``path`` (checked against ``schema`` if given).

    Raises:
        ValueError: the file is missing, unreadable, not JSON or not of the schema, in
            one line: ``"PATH is not WHAT (why); FIX."``.
    """
    try:
        value = json.loads(Path(path).read_text(encoding="utf-8"))
        if schema is not None:
            check_values(value, schema, str(path))
    except (OSError, UnicodeDecodeError, ValueError) as err:
        why = str(err).removeprefix(f"{path}: ").rstrip(".")
        raise ValueError(f"{path} is not {what} ({why}); {fix}.") from None
    return value


def optional(schema: Mapping[str, Any]) -> dict[str, Any]:
    """``schema`` with every field allowed to be absent (what is there still holds its
    kind)."""
    return {key if key.endswith("?") else f"{key}?": kind for key, kind in schema.items()}


def _is(value: Any, kind: Any) -> bool:
    if isinstance(kind, tuple):
        return value in kind
    if kind == "text":
        return isinstance(value, str)
    if kind == "flag":
        return isinstance(value, bool)
    if kind == "object":
        return isinstance(value, dict)
    if kind == "list of numbers":
        return isinstance(value, list) and all(_is(v, "number") for v in value)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    if kind == "count":
        return isinstance(value, int) and value >= 0
    return True  # "number": NaN and infinities are numbers a run may have logged


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
