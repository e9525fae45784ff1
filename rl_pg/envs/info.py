"""Entries of a gymnasium ``info`` dict (crashes, successes, progress) as TorchRL entries."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs.gym_like import BaseInfoDictReader

from rl_pg._checks import check_names

__all__ = ["InfoFlags", "InfoValues"]


class InfoFlags(BaseInfoDictReader):
    """Reads ``info[key]`` as a ``[1]`` boolean entry, ``False`` when the key is absent.

    TorchRL's default reader expects numpy arrays; simulators such as highway-env and
    MetaDrive report plain Python booleans.

    Args:
        keys (sequence of str): the info keys to read.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rl_pg.envs.info import InfoFlags
        >>> reader = InfoFlags(["crashed"])
        >>> reader({"crashed": True, "speed": 20.0}, TensorDict())["crashed"]
        tensor([True])
    """

    def __init__(self, keys: Sequence[str]) -> None:
        self.keys = list(check_names("keys", keys))
        self._info_spec = Composite(
            {key: Categorical(2, shape=(1,), dtype=torch.bool) for key in self.keys}, shape=[]
        )

    def __call__(self, info_dict: dict[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        for key in self.keys:
            tensordict.set(key, torch.tensor([bool(info_dict.get(key, False))]))
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._info_spec


class InfoValues(BaseInfoDictReader):
    """Reads ``info[key]`` as a ``[1]`` float32 entry, ``default`` when the key is absent.

    For quantities a simulator reports at every step, such as MetaDrive's
    ``route_completion`` (the share of the route driven so far).

    Args:
        keys (sequence of str): the info keys to read.

    Keyword Args:
        default (float): the value when a key is absent. Defaults to ``0.0``.

    Examples:
        >>> from tensordict import TensorDict
        >>> from rl_pg.envs.info import InfoValues
        >>> InfoValues(["route_completion"])({"route_completion": 0.5}, TensorDict())[
        ...     "route_completion"
        ... ]
        tensor([0.5000])
    """

    def __init__(self, keys: Sequence[str], *, default: float = 0.0) -> None:
        self.keys = list(check_names("keys", keys))
        self.default = float(default)
        self._info_spec = Composite(
            {key: Unbounded(shape=(1,), dtype=torch.float32) for key in self.keys}, shape=[]
        )

    def __call__(self, info_dict: dict[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        for key in self.keys:
            value = float(info_dict.get(key, self.default))
            tensordict.set(key, torch.tensor([value], dtype=torch.float32))
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._info_spec
