"""A pytest plugin for ``torchrl_compat.py``: TorchRL's tests get ``rl_pg.ReinforceLoss``
wherever they import ``torchrl.objectives``' ``ReinforceLoss``.

The class is swapped when pytest loads the plugin, before any test module is imported;
after collection the plugin checks that every collected module that names
``ReinforceLoss`` holds rl_pg's, and stops the run otherwise (a count of TorchRL's own
class passing must never be reported as rl_pg's).
"""

from __future__ import annotations

import sys

import pytest
import torchrl.objectives
import torchrl.objectives.reinforce

import rl_pg

torchrl.objectives.reinforce.ReinforceLoss = rl_pg.ReinforceLoss
torchrl.objectives.ReinforceLoss = rl_pg.ReinforceLoss


def pytest_collection_modifyitems(items) -> None:
    modules = {item.module.__name__ for item in items if getattr(item, "module", None)}
    wrong = [
        name for name in sorted(modules)
        if getattr(sys.modules[name], "ReinforceLoss", rl_pg.ReinforceLoss)
        is not rl_pg.ReinforceLoss
    ]  # fmt: skip
    if wrong or not modules:
        raise pytest.UsageError(
            f"rl_pg.ReinforceLoss was not substituted in {wrong or 'any collected module'}."
        )
