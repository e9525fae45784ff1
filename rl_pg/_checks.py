"""Argument checks shared by every public entry point.

Each check returns the value in its canonical Python type (a numpy ``float32`` or a
one-element tensor becomes a ``float``) or raises an error that names the argument,
says what was expected and what was received. ``TypeError`` is raised for a value of
the wrong kind, ``ValueError`` for one of the right kind out of its range.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch

__all__ = ["check_bool", "check_int", "check_real", "check_tensor"]


def _received(value: Any) -> str:
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)} and dtype {value.dtype}"
    return f"{value!r} ({type(value).__name__})"


def _scalar(value: Any) -> Any:
    """A one-element tensor or numpy array as a Python number; anything else as is."""
    if isinstance(value, torch.Tensor) and value.numel() == 1 and not value.dtype.is_complex:
        return value.item()
    if hasattr(value, "item") and getattr(value, "size", None) == 1:  # numpy
        return value.item()
    return value


def check_real(
    name: str,
    value: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    optional: bool = False,
    hint: str = "",
) -> float | None:
    """A finite real number in ``[low, high]`` (ends open where asked) as a ``float``.

    Examples:
        >>> import numpy as np
        >>> from rl_pg._checks import check_real
        >>> check_real("gamma", np.float32(0.5), low=0, high=1)
        0.5
        >>> check_real("lr", -1.0, low=0, low_open=True)
        Traceback (most recent call last):
        ...
        ValueError: lr must be a finite number > 0, got -1.0 (float).
    """
    if value is None and optional:
        return None
    number = _scalar(value)
    if isinstance(number, bool) or not isinstance(number, numbers.Real):
        raise TypeError(
            f"{name} must be a real number{' or None' if optional else ''}, got "
            f"{_received(value)}.{_hint(hint)}"
        )
    number = float(number)
    bounds = []
    if low is not None:
        bounds.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        bounds.append(f"{'<' if high_open else '<='} {high:g}")
    in_range = math.isfinite(number)
    if low is not None:
        in_range &= number > low if low_open else number >= low
    if high is not None:
        in_range &= number < high if high_open else number <= high
    if not in_range:
        expected = "a finite number" + (f" {' and '.join(bounds)}" if bounds else "")
        raise ValueError(f"{name} must be {expected}, got {_received(value)}.{_hint(hint)}")
    return number


def check_int(
    name: str, value: Any, *, low: int | None = None, optional: bool = False, hint: str = ""
) -> int | None:
    """An integer ``>= low`` (numpy integers included, floats refused) as an ``int``.

    Examples:
        >>> from rl_pg._checks import check_int
        >>> check_int("episodes", 0, low=1)
        Traceback (most recent call last):
        ...
        ValueError: episodes must be an integer >= 1, got 0 (int).
    """
    if value is None and optional:
        return None
    number = _scalar(value)
    if isinstance(number, bool) or not isinstance(number, numbers.Integral):
        raise TypeError(
            f"{name} must be an integer{' or None' if optional else ''}, got "
            f"{_received(value)}.{_hint(hint)}"
        )
    if low is not None and number < low:
        raise ValueError(
            f"{name} must be an integer >= {low}, got {_received(value)}.{_hint(hint)}"
        )
    return int(number)


def check_bool(name: str, value: Any) -> bool:
    """``True`` or ``False`` (numpy booleans included; ``0``, ``1`` and strings refused).

    Examples:
        >>> from rl_pg._checks import check_bool
        >>> check_bool("one_hot", "yes")
        Traceback (most recent call last):
        ...
        TypeError: one_hot must be True or False, got 'yes' (str).
    """
    if isinstance(value, bool):
        return value
    if type(value).__name__ == "bool_":  # numpy.bool_
        return bool(value)
    raise TypeError(f"{name} must be True or False, got {_received(value)}.")


def check_tensor(name: str, value: Any, *, hint: str = "") -> torch.Tensor:
    """Refuses anything that is not a ``torch.Tensor``.

    Examples:
        >>> from rl_pg._checks import check_tensor
        >>> check_tensor("reward", [1.0, 2.0])
        Traceback (most recent call last):
        ...
        TypeError: reward must be a torch.Tensor, got [1.0, 2.0] (list).
    """
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {_received(value)}.{_hint(hint)}")
    return value


def _hint(hint: str) -> str:
    return f" {hint}" if hint else ""
