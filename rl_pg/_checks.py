"""Argument checks shared by every public entry point.

Each check returns the value in its canonical Python type (a numpy ``float32`` or a
one-element tensor becomes a ``float``) or raises an error that names the argument,
says what was expected and what was received. ``TypeError`` is raised for a value of
the wrong kind, ``ValueError`` for one of the right kind out of its range.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import inspect
import math
import numbers
import types
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "Range",
    "check_batch_size",
    "check_bool",
    "check_field",
    "check_fields",
    "check_int",
    "check_key",
    "check_names",
    "check_real",
    "check_tensor",
]


def require_extra(module: str, extra: str, needed_for: str) -> None:
    """Raises ``ModuleNotFoundError`` naming the extra to install when ``module`` is
    missing: one line a user can act on, instead of a traceback from deep inside the
    package that needed it (which often names another fix).

    Examples:
        >>> from rl_pg._checks import require_extra
        >>> require_extra("no_such_module_here", "box2d", "LunarLander")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ModuleNotFoundError: LunarLander needs the box2d extra: pip install -c ...
    """
    if importlib.util.find_spec(module) is None:
        raise ModuleNotFoundError(
            f"{needed_for} needs the {extra} extra: "
            f'pip install -c constraints.txt "rl_pg[{extra}]".'
        )


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
    number = float(_number_of_kind(name, value, numbers.Real, "a real number", optional, hint))
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
    number = _number_of_kind(name, value, numbers.Integral, "an integer", optional, hint)
    if low is not None and number < low:
        raise ValueError(
            f"{name} must be an integer >= {low}, got {_received(value)}.{_hint(hint)}"
        )
    return int(number)


def _number_of_kind(name, value, kind, what: str, optional: bool, hint: str):
    """``value`` as a Python or numpy number of ``kind``; booleans are not numbers here."""
    number = _scalar(value)
    if isinstance(number, bool) or not isinstance(number, kind):
        raise TypeError(
            f"{name} must be {what}{' or None' if optional else ''}, got "
            f"{_received(value)}.{_hint(hint)}"
        )
    return number


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
    if type(value).__module__ == "numpy" and type(value).__name__ in ("bool", "bool_"):
        return bool(value)
    raise TypeError(f"{name} must be True or False, got {_received(value)}.")


def check_choice(name: str, value: Any, choices: tuple) -> Any:
    """``value`` if it is one of ``choices``.

    Examples:
        >>> from rl_pg._checks import check_choice
        >>> check_choice("unit", "step", ("episode", "group"))
        Traceback (most recent call last):
        ...
        ValueError: unit must be one of ('episode', 'group'), got 'step'.
    """
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}.")
    return value


def check_names(name: str, value: Any) -> tuple[str, ...]:
    """A sequence of strings (entry or info names); a lone string is refused, not split.

    Examples:
        >>> from rl_pg._checks import check_names
        >>> check_names("flags", "crashed")
        Traceback (most recent call last):
        ...
        TypeError: flags must be a sequence of names such as ['crashed'], got 'crashed'.
    """
    if isinstance(value, str) or not hasattr(value, "__iter__"):
        raise TypeError(f"{name} must be a sequence of names such as ['crashed'], got {value!r}.")
    names = tuple(value)
    if not all(isinstance(item, str) for item in names):
        raise TypeError(f"{name} must be a sequence of names such as ['crashed'], got {value!r}.")
    return names


def check_key(name: str, value: Any) -> str | tuple[str, ...]:
    """A TensorDict key: a string or a non-empty tuple of strings.

    Examples:
        >>> from rl_pg._checks import check_key
        >>> check_key("in_key", ("next", "pixels"))
        ('next', 'pixels')
    """
    if isinstance(value, str) or (
        isinstance(value, tuple) and value and all(isinstance(k, str) for k in value)
    ):
        return value
    raise TypeError(f"{name} must be a string or a tuple of strings, got {value!r}.")


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


@dataclasses.dataclass(frozen=True)
class Range:
    """Bounds of a number field, declared with its type: ``Annotated[int, Range(low=1)]``.

    [`check_fields`][rl_pg._checks.check_fields] enforces them; a subclass that
    re-declares the field with a plain type keeps its base's bounds.
    """

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False


def check_fields(obj: Any) -> None:
    """Checks every field of a dataclass instance against its annotation.

    ``bool``, ``int``, ``float``, ``str``, ``Path``, ``Literal[...]`` and their
    ``| None`` forms are checked, with the bounds of any [`Range`][rl_pg._checks.Range]
    in an ``Annotated`` type. Numbers are stored back in canonical form (a numpy
    ``float32`` becomes a ``float``, a string path a ``Path``). Errors name the field
    and its command-line flag.

    Examples:
        >>> from dataclasses import make_dataclass
        >>> from typing import Annotated
        >>> from rl_pg._checks import Range, check_fields
        >>> Config = make_dataclass("Config", [("hidden", Annotated[int, Range(low=1)], 64)])
        >>> check_fields(Config(hidden=0))
        Traceback (most recent call last):
        ...
        ValueError: hidden (--hidden) must be an integer >= 1, got 0 (int).
    """
    annotations = _field_annotations(type(obj))
    for field in dataclasses.fields(obj):
        base, bounds = annotations[field.name]
        name = f"{field.name} (--{field.name.replace('_', '-')})"
        setattr(obj, field.name, _check_value(name, getattr(obj, field.name), base, bounds))


def check_field(
    cls: type, field: str, value: Any, name: str | None = None, *, optional: bool = False
) -> Any:
    """``value`` checked as dataclass ``cls`` checks its field ``field`` (its type and
    bounds), for code that takes the same setting as an argument: the bound is declared
    once, on the field. None passes only with ``optional`` (where the field's type
    allows it). Returns the value in canonical form; errors name ``name`` (default: the
    field).

    Examples:
        >>> from dataclasses import make_dataclass
        >>> from typing import Annotated
        >>> from rl_pg._checks import Range, check_field
        >>> Config = make_dataclass("Config", [("rate", Annotated[float, Range(low=0)], 1.0)])
        >>> check_field(Config, "rate", -1.0, name="rate")
        Traceback (most recent call last):
        ...
        ValueError: rate must be a finite number >= 0, got -1.0 (float).
    """
    base, bounds = _field_annotations(cls)[field]
    name = field if name is None else name
    if value is None and not optional:
        raise TypeError(f"{name} must not be None.")
    return _check_value(name, value, base, bounds)


@functools.cache  # a class's hints, once: evaluating them is most of a config's making
def _field_annotations(cls: type) -> dict[str, tuple[Any, tuple[Range, ...]]]:
    """``name -> (type of the most derived declaration, bounds from every declaration)``."""
    out: dict[str, tuple[Any, list[Range]]] = {}
    for klass in cls.__mro__:
        if not dataclasses.is_dataclass(klass):
            continue
        hints = typing.get_type_hints(klass, include_extras=True)
        for name in inspect.get_annotations(klass):
            base, bounds = _split(hints[name])
            if name in out:
                out[name][1].extend(bounds)
            else:
                out[name] = (base, bounds)
    return {name: (base, tuple(bounds)) for name, (base, bounds) in out.items()}


def _split(hint: Any) -> tuple[Any, list[Range]]:
    """``Annotated[float, Range(...)] | None`` -> ``(float | None, [Range(...)])``."""
    if typing.get_origin(hint) is typing.Annotated:
        base, *metadata = typing.get_args(hint)
        return base, [m for m in metadata if isinstance(m, Range)]
    if _is_union(hint):
        parts = [_split(arg) for arg in typing.get_args(hint)]
        return typing.Union[tuple(base for base, _ in parts)], [  # noqa: UP007
            bound for _, bounds in parts for bound in bounds
        ]
    return hint, []


def _check_value(name: str, value: Any, base: Any, bounds: Sequence[Range]) -> Any:
    options = typing.get_args(base) if _is_union(base) else (base,)
    optional = type(None) in options
    kinds = [kind for kind in options if kind is not type(None)]
    if value is None:
        if optional:
            return None
        raise TypeError(f"{name} must not be None.")
    if len(kinds) != 1:
        return value  # a union this checker does not interpret
    kind = kinds[0]
    if typing.get_origin(kind) is typing.Literal:
        choices = typing.get_args(kind)
        if value not in choices:
            raise ValueError(f"{name} must be one of {choices}, got {value!r}.")
        return value
    if kind is bool:
        return check_bool(name, value)
    low = max((b for b in bounds if b.low is not None), key=lambda b: b.low, default=None)
    high = min((b for b in bounds if b.high is not None), key=lambda b: b.high, default=None)
    if kind is int:
        number = check_int(
            name, value, low=None if low is None else int(low.low) + int(low.low_open)
        )
        if high is not None and (number > high.high or (high.high_open and number == high.high)):
            limit = int(high.high) - int(high.high_open)
            raise ValueError(f"{name} must be an integer <= {limit}, got {number}.")
        return number
    if kind is float:
        return check_real(
            name,
            value,
            low=None if low is None else low.low,
            high=None if high is None else high.high,
            low_open=low is not None and low.low_open,
            high_open=high is not None and high.high_open,
        )
    if kind is str and not isinstance(value, str):
        raise TypeError(f"{name} must be a string, got {_received(value)}.")
    if kind is Path:
        if not isinstance(value, (str, Path)):
            raise TypeError(f"{name} must be a path, got {_received(value)}.")
        return Path(value)
    return value


def _is_union(tp: Any) -> bool:
    return typing.get_origin(tp) in (typing.Union, types.UnionType)


def check_batch_size(batch_size: Any) -> tuple[int, ...]:
    """An environment batch size: an integer >= 1 or a sequence of them (``()``: no batch).

    Examples:
        >>> from rl_pg._checks import check_batch_size
        >>> check_batch_size(8), check_batch_size((2, 3)), check_batch_size(())
        ((8,), (2, 3), ())
    """
    sizes = [batch_size] if not hasattr(batch_size, "__iter__") else list(batch_size)
    return tuple(check_int(f"batch_size[{i}]", size, low=1) for i, size in enumerate(sizes))
