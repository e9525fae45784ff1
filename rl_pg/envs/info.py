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

    dtype = torch.float32

    def __init__(self, keys: Sequence[str], *, default: Any = 0.0) -> None:
        self.keys = list(check_names("keys", keys))
        self.default = default
        self._info_spec = Composite({key: self._entry_spec() for key in self.keys}, shape=[])

    def _entry_spec(self):
        return Unbounded(shape=(1,), dtype=self.dtype)

    def __call__(self, info_dict: dict[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        for key in self.keys:
            value = info_dict.get(key, self.default)
            tensordict.set(key, torch.tensor([value], dtype=self.dtype))
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._info_spec


class InfoFlags(InfoValues):
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

    dtype = torch.bool

    def __init__(self, keys: Sequence[str]) -> None:
        super().__init__(keys, default=False)

    def _entry_spec(self):
        return Categorical(2, shape=(1,), dtype=self.dtype)
