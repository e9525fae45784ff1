"""The settings of a training run: one dataclass, checked when it is made.

Every field declares its kind and bounds in its type (``Count``, ``Positive``,
``NonNegative``, ``Range``). A recipe's config subclasses ``TrainConfig``, declares the
fields it adds, and changes the defaults of inherited fields in its class statement,
without re-declaring them (their type, bounds and help text stay the base's)::

    @dataclass
    class Config(TrainConfig, lr=5e-3, total_frames=300_000):
        hidden: Count = 64
        '''Width of the hidden layers.'''
"""

from __future__ import annotations

import dataclasses
import inspect
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch

from rl_pg._checks import Range, check_fields
from rl_pg.training.learning import LossSettings, OptimiserSettings, ReturnSettings
from rl_pg.training.settings import (
    BatchedEnvironments,
    CheckpointSettings,
    CollectionSettings,
    Count,
    EnvPoolBackend,
    EvaluationSettings,
    LoggingSettings,
    NonNegative,
    Positive,
    RunSettings,
)

__all__ = [
    "GROUPS",
    "RESUMABLE_FIELDS",
    "Count",
    "DeviceUnavailable",
    "NonNegative",
    "Positive",
    "Range",
    "TrainConfig",
]


class DeviceUnavailable(ValueError):
    """The device asked for is not one torch can use here (``--device cuda`` on a build
    or machine without CUDA)."""


GROUPS = (RunSettings, CollectionSettings, ReturnSettings, LossSettings, OptimiserSettings,
          EvaluationSettings, CheckpointSettings, LoggingSettings)  # fmt: skip
"""The groups of a run's settings, in the order ``--help`` shows them."""

RESUMABLE_FIELDS = frozenset().union(*(group.resumable for group in GROUPS))
"""Config fields that may change when a run is resumed; any other change is refused."""


@dataclass
class TrainConfig(*reversed(GROUPS)):  # the fields in the groups' order
    """Settings of the training loop shared by every recipe: every group of
    [`rl_pg.training.settings`][rl_pg.training.settings] at once."""

    groups: ClassVar[dict[str, tuple[str, tuple[str, ...]]]] = {
        group.group: (
            group.__doc__.split("\n")[0],
            tuple(field.name for field in dataclasses.fields(group)),
        )
        for group in GROUPS
    }
    """The fields by concern, as ``--help`` shows them: group -> (what it holds, fields).
    A recipe's own fields form a group of their own."""
    acts_only_with: ClassVar[dict[str, tuple[str, Any]]] = {
        name: rule for group in GROUPS for name, rule in group.acts_only_with.items()
    }
    """Fields that act only when another field takes one of some values (``"not
    None"``: any value but None): field -> (that field, those values), each group's
    rules. A run's value of such a field is no setting of the run when the other field
    says it is unused (``inert``)."""
    absent_means: ClassVar[dict[str, Any]] = {}
    """Fields whose default changed after they were added, each with the value a stored
    config that lacks the field ran with (it was written before the field existed). A
    stored config that lacks any other field ran as that field's default does."""

    def __init_subclass__(cls, **defaults: Any) -> None:
        """``class Config(TrainConfig, lr=5e-3)``: new defaults for inherited fields."""
        super().__init_subclass__()
        own = inspect.get_annotations(cls)
        for mixin in (BatchedEnvironments, EnvPoolBackend):
            (name,) = (field.name for field in dataclasses.fields(mixin))
            if name in own and not issubclass(cls, mixin):
                raise TypeError(
                    f"{cls.__name__} declares {name}, which the loop's checks read from "
                    f"rl_pg.training.settings.{mixin.__name__}: add that class to "
                    f"{cls.__name__}'s bases instead and set the default in the class "
                    f"statement ({name}=...)."
                )
        if not defaults:
            return
        inherited = {}
        for base in reversed(cls.__mro__[1:]):
            if dataclasses.is_dataclass(base):
                inherited.update(typing.get_type_hints(base, include_extras=True))
        unknown = sorted(set(defaults) - set(inherited))
        if unknown:
            raise TypeError(
                f"{cls.__name__} sets defaults of {', '.join(unknown)}, which "
                f"{cls.__mro__[1].__name__} does not have: declare new fields in the class body."
            )
        own = dict(inspect.get_annotations(cls))
        clash = sorted(set(defaults) & set(own))
        if clash:
            raise TypeError(
                f"{cls.__name__} both declares and overrides {', '.join(clash)}: do one."
            )
        # Re-declared with the base's type: @dataclass then keeps the field in place.
        annotations = {name: inherited[name] for name in defaults}
        cls.__annotations__ = {**annotations, **own}
        for name, value in defaults.items():
            setattr(cls, name, value)

    def __post_init__(self) -> None:
        if self.scale_lr_factor is None:  # a recipe that chooses by policy did so first
            self.scale_lr_factor = 1.0
        self.validate()

    @classmethod
    def from_stored(cls, stored: dict[str, Any], **changes: Any) -> TrainConfig:
        """This config from a run's stored one (``config.json``, a checkpoint's
        ``"config"``) with ``changes``; fields this class lacks are ignored, fields the
        stored config lacks take the values the run had (``as_run``)."""
        fields = {field.name: field for field in dataclasses.fields(cls)}
        values = {k: v for k, v in {**cls.as_run(stored), **changes}.items() if k in fields}
        for name, value in values.items():  # JSON gave back a list for a tuple
            if isinstance(value, list) and isinstance(fields[name].default, tuple):
                values[name] = tuple(value)
        return cls(**values)

    @classmethod
    def inert(cls, name: str, config: dict[str, Any]) -> bool:
        """Whether field ``name`` does nothing in ``config`` (a stored config, as
        ``as_run`` completes it), by ``acts_only_with``.

        Examples:
            >>> from rl_pg.training import TrainConfig
            >>> TrainConfig.inert("target_kl", {"lr_control": "none"})
            True
            >>> TrainConfig.inert("target_kl", {"lr_control": "kl"})
            False
        """
        if name not in cls.acts_only_with:
            return False
        other, values = cls.acts_only_with[name]
        value = config.get(other)
        return value is None if values == "not None" else value not in values

    @classmethod
    def as_run(cls, stored: dict[str, Any]) -> dict[str, Any]:
        """A stored config with the fields it lacks (newer than the run) at the values
        the run had: their defaults, or ``absent_means`` where a default has changed
        since. Values as ``config_dict`` writes them (paths as strings)."""
        defaults = {
            field.name: _plain(field.default)
            for field in dataclasses.fields(cls)
            if field.default is not dataclasses.MISSING
        }
        return {key: _plain(value) for key, value in {**defaults, **cls.absent_means,
                                                      **stored}.items()}  # fmt: skip

    def torch_device(self) -> torch.device:
        """``device`` as a ``torch.device`` ('auto' resolved).

        Raises:
            DeviceUnavailable: ``device='cuda'`` where torch sees no CUDA device.
            ValueError: a CUDA device with worker processes.
        """
        device = self.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device == "cuda" and (self.workers > 1 or self.ray):
            raise ValueError(
                f"--device {self.device} trains on CUDA with local collection only: drop "
                f"--workers / --ray, or use --device cpu with them."
            )
        if device == "cuda" and not torch.cuda.is_available():
            raise DeviceUnavailable(
                "device (--device) is 'cuda' but torch sees no CUDA device (torch "
                f"{torch.__version__}, built for CUDA {torch.version.cuda}); use --device cpu, "
                "or install a CUDA build of torch (README: Bring your own torch)."
            )
        return torch.device(device)

    def validate(self) -> None:
        """Checks every field (also those a recipe adds) against its type and bounds.

        Runs when the config is made, so that the command line refuses a bad flag
        before anything starts, and again in [`train`][rl_pg.training.loop.train].

        Raises:
            ValueError: a value out of its range or choices; the message names the
                field and its flag.
            TypeError: a value of the wrong kind (from Python code).
        """
        check_fields(self)
        for group in GROUPS:
            group.check(self)
        num_envs = self.num_envs if isinstance(self, BatchedEnvironments) else None
        if self.overlap and (num_envs or 1) < 2:
            raise ValueError(
                f"--overlap steps two halves of the environments in turn: use --num-envs 2 "
                f"or more (got {num_envs or 1})."
            )
        if self.overlap and not (isinstance(self, EnvPoolBackend) and self.backend == "envpool"):
            raise ValueError(
                "--overlap needs environments that step without holding Python: use "
                "--backend envpool with it"
                + ("." if isinstance(self, EnvPoolBackend) else
                   " (this recipe has no EnvPool backend).")
            )  # fmt: skip
        if self.critic_steps > 1 and self.baseline != "critic":
            raise ValueError(
                f"--critic-steps {self.critic_steps} fits a critic, but --baseline is "
                f"{self.baseline!r}: use --baseline critic, or leave --critic-steps at 1."
            )
        self._check_groups_of_episodes(num_envs)

    def _check_groups_of_episodes(self, num_envs: int | None) -> None:
        """The group baselines against the collection and the environments."""
        if not self.grouped:
            return
        if self.batch_mode != "episodes" or not self.local:
            raise ValueError(
                f"--baseline {self.baseline} plays episodes in groups from one seed: use "
                f"--batch-mode episodes with one local collector (got --batch-mode "
                f"{self.batch_mode}, --workers {self.workers}{', --ray' if self.ray else ''})."
            )
        width = self.group_width
        if self.episodes_per_batch % width:
            raise ValueError(
                f"--baseline {self.baseline} plays groups of {width} episodes (--group-size "
                f"{self.group_size}{' and the greedy one' if width > self.group_size else ''}): "
                f"set --episodes-per-batch to a multiple of {width} (got "
                f"{self.episodes_per_batch})."
            )
        if num_envs is not None and self.episodes_per_batch % num_envs:
            raise ValueError(
                f"--baseline {self.baseline} plays each batch in rounds of one episode per "
                f"environment: set --episodes-per-batch to a multiple of --num-envs (got "
                f"{self.episodes_per_batch} and {num_envs}; as many environments as "
                f"episodes is one round)."
            )
        if self.baseline == "greedy" and num_envs is not None and num_envs % width:
            raise ValueError(
                f"--baseline greedy plays the last environment of every {width} greedily: "
                f"set --num-envs to a multiple of {width} (--group-size {self.group_size} "
                f"and the greedy one; got {num_envs})."
            )


def config_dict(cfg: Any) -> dict[str, Any]:
    """The config (a ``TrainConfig``, or any dataclass) as plain JSON-able values (paths
    as strings, pairs as lists), as a run's config.json holds them: a stored config and
    a new one compare entry by entry."""
    return {key: _plain(value) for key, value in dataclasses.asdict(cfg).items()}


def _plain(value: Any) -> Any:
    """``value`` as JSON gives it back: a path as a string, a tuple as a list."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple | list):
        return [_plain(item) for item in value]
    return value
