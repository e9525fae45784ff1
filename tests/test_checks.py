"""The argument checks behind every public entry point (rl_pg._checks)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import pytest
import torch

from rl_pg._checks import (
    Range,
    check_batch_size,
    check_bool,
    check_fields,
    check_int,
    check_real,
)


@dataclass
class _Base:
    rate: Annotated[float, Range(0, 1, low_open=True)] = 0.5
    width: Annotated[int, Range(low=1)] | None = None
    mode: Literal["a", "b"] = "a"
    path: Path | None = None
    flag: bool = False

    def __post_init__(self):
        check_fields(self)


@dataclass
class _Derived(_Base):
    rate: float = 0.25  # re-declared with a plain type: the base's bounds still hold
    extra: Annotated[int, Range(low=2, high=9)] = 3


class TestCheckFields:
    def test_bounds_survive_a_plain_redeclaration(self):
        with pytest.raises(ValueError, match=r"rate \(--rate\) must be a finite number > 0"):
            _Derived(rate=0.0)

    def test_optional_annotated_fields(self):
        assert _Base(width=None).width is None
        with pytest.raises(ValueError, match=r"width \(--width\) must be an integer >= 1"):
            _Base(width=0)

    def test_upper_bound_of_an_integer(self):
        with pytest.raises(ValueError, match=r"extra \(--extra\) must be an integer <= 9"):
            _Derived(extra=10)

    def test_choices(self):
        with pytest.raises(ValueError, match=r"mode \(--mode\) must be one of \('a', 'b'\)"):
            _Base(mode="c")

    def test_values_are_made_canonical(self):
        config = _Derived(rate=np.float32(0.5), extra=np.int64(4), path="runs/x")
        assert (type(config.rate), type(config.extra), config.path) == (
            float,
            int,
            Path("runs/x"),
        )

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"flag": 1}, "flag .* must be True or False"),
            ({"path": 3}, "path .* must be a path"),
            ({"rate": None}, "rate .* must not be None"),
            ({"width": 2.0}, "width .* must be an integer"),
        ],
    )
    def test_wrong_kinds(self, kwargs, match):
        with pytest.raises(TypeError, match=match):
            _Base(**kwargs)


class TestScalarChecks:
    @pytest.mark.parametrize("value", [0.5, np.float32(0.5), torch.tensor(0.5), np.array(0.5)])
    def test_real_numbers_of_any_library(self, value):
        assert check_real("x", value) == 0.5

    @pytest.mark.parametrize("value", [True, "1", None, torch.ones(2), 1j])
    def test_not_a_real_number(self, value):
        with pytest.raises(TypeError, match="x must be a real number"):
            check_real("x", value)

    @pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
    def test_non_finite_numbers(self, value):
        with pytest.raises(ValueError, match="x must be a finite number"):
            check_real("x", value)

    def test_open_and_closed_ends(self):
        assert check_real("x", 1.0, low=0, high=1) == 1.0
        with pytest.raises(ValueError, match="< 1"):
            check_real("x", 1.0, low=0, high=1, high_open=True)

    @pytest.mark.parametrize("value", [1.0, True, "3"])
    def test_not_an_integer(self, value):
        with pytest.raises(TypeError, match="n must be an integer"):
            check_int("n", value)

    def test_numpy_booleans(self):
        assert check_bool("b", np.bool_(True)) is True

    @pytest.mark.parametrize("size", [0, (2, 0), -1, (1.5,)])
    def test_bad_batch_sizes(self, size):
        with pytest.raises((ValueError, TypeError), match=r"batch_size\[\d\] must be an integer"):
            check_batch_size(size)
