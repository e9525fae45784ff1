"""From flags to settings and back: a config class's ``--help`` grouped by concern with
each field's first sentence, ``--resume`` starting from a run's stored config, and the
flag that sets a field to a value (what ``rl-pg tune`` and ``rl-pg report`` print).
"""

from __future__ import annotations

import ast
import copy
import dataclasses
import inspect
import itertools
import re
import sys
import textwrap
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, TypeVar

import tyro

from rl_pg.checkpoint import CheckpointError
from rl_pg.training.checkpoints import read_run
from rl_pg.training.config import TrainConfig

__all__ = ["field_docs", "first_sentence", "flag", "parse_args", "parse_config"]

SENTENCE_END = re.compile(r"(?<=[.!?])(?<!e\.g\.)(?<!i\.e\.)\s+(?=[A-Z(`'\"])")
"""Where a sentence ends: after . ! or ?, before a capital, a bracket or a quote."""

Config = TypeVar("Config", bound=TrainConfig)


def parse_config(
    config_class: type[Config],
    args: Sequence[str] | None = None,
    *,
    prog: str | None = None,
    stored: dict | None = None,
) -> Config:
    """``tyro.cli(config_class)``, except that ``--resume --run-dir DIR`` starts from the
    configuration stored in DIR's checkpoint: only the flags given on the command line
    change it (and the loop refuses changes that are not safe on resume).

    Args:
        config_class (type): a ``TrainConfig`` dataclass.
        args (sequence of str, optional): the command line. Defaults to ``sys.argv[1:]``.

    Keyword Args:
        prog (str, optional): the program's name in ``--help``.
        stored (dict, optional): the resumed run's stored configuration, where the
            caller has read its checkpoint already (default: read from DIR).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor_critic
        >>> from rl_pg.training import TrainConfig, train
        >>> from rl_pg.app.flags import parse_config
        >>> run = Path(tempfile.mkdtemp()) / "run"
        >>> cfg = parse_config(TrainConfig, ["--run-dir", str(run), "--lr", "0.02",
        ...                                  "--total-updates", "1", "--no-progress"])
        >>> _ = train(cfg, recipe="demo", make_env=GridWorldEnv, make_models=mlp_actor_critic)
        >>> resumed = parse_config(TrainConfig, ["--resume", "--run-dir", str(run),
        ...                                      "--total-updates", "2"])
        >>> resumed.lr, resumed.total_updates, resumed.progress
        (0.02, 2, False)
    """
    args = list(sys.argv[1:] if args is None else args)
    run_dir = _resumed_run_dir(args)
    defaults = None
    if run_dir is not None:
        if stored is None:
            try:
                stored = read_run(run_dir)["config"]
            except CheckpointError:  # train() reports the missing or corrupted checkpoint
                stored = None
        if stored is not None:
            resumed = config_class.from_stored(stored, resume=True, run_dir=Path(run_dir))
            defaults = {f.name: getattr(resumed, f.name) for f in dataclasses.fields(resumed)}
    return tyro.cli(_grouped(config_class, defaults), args=args, prog=prog).config


def parse_args(args_class: type, args: Sequence[str], *, prog: str, **kwargs):
    """``tyro.cli(args_class, args=args, prog=prog, **kwargs)`` whose ``--help`` gives
    each flag its docstring's first sentence, on one line (the rest is for the docs)."""
    docs = field_docs(args_class)
    hints = typing.get_type_hints(args_class, include_extras=True)
    fields = [f for f in dataclasses.fields(args_class) if f.init]
    short = dataclasses.make_dataclass(
        args_class.__name__,
        [
            (
                f.name,
                Annotated[hints[f.name], tyro.conf.arg(help=first_sentence(docs.get(f.name, "")))],
                dataclasses.field(default=f.default, default_factory=f.default_factory),
            )
            for f in fields
        ],
    )
    paragraphs = re.split(r"\n\s*\n", args_class.__doc__ or "")
    short.__doc__ = "\n\n".join(" ".join(p.split()) for p in paragraphs)  # unwrapped
    parsed = tyro.cli(short, args=list(args), prog=prog, **kwargs)
    value, rest = parsed if kwargs.get("return_unknown_args") else (parsed, None)
    value = args_class(**{f.name: getattr(value, f.name) for f in fields})
    return (value, rest) if kwargs.get("return_unknown_args") else value


def _grouped(config_class: type[Config], defaults: dict[str, Any] | None) -> type:
    """``config_class`` as tyro should show it: one dataclass per group of
    ``TrainConfig.groups`` (the recipe's own fields first, as a group of their own),
    with the flags unprefixed and each field's docstring on one line, so that the help
    wraps it whole. Parsing builds the config itself (``.config``), inside tyro, which
    reports a value the config refuses as it reports a malformed flag."""
    docs = field_docs(config_class)
    hints = typing.get_type_hints(config_class, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(config_class)}
    grouped = {name: names for name, (_, names) in config_class.groups.items()}
    placed = {name for names in grouped.values() for name in names}
    own = tuple(name for name in fields if name not in placed)
    groups = {"recipe": ("The recipe's own settings.", own)} if own else {}
    groups.update(config_class.groups)

    def spec(name: str) -> tuple[str, Any, dataclasses.Field]:
        kind = Annotated[hints[name], tyro.conf.arg(help=first_sentence(docs.get(name, "")))]
        if defaults is not None:
            value = defaults[name]
        elif fields[name].default is not dataclasses.MISSING:
            value = fields[name].default
        elif fields[name].default_factory is not dataclasses.MISSING:
            return name, kind, dataclasses.field(default_factory=fields[name].default_factory)
        else:
            return name, kind, dataclasses.field()
        return name, kind, dataclasses.field(default_factory=lambda v=value: copy.deepcopy(v))

    members = []
    for group, (about, names) in groups.items():
        names = [name for name in names if name in fields]
        if not names:
            continue
        section = dataclasses.make_dataclass(group, [spec(name) for name in names])
        kind = Annotated[section, tyro.conf.OmitArgPrefixes, tyro.conf.arg(help=about)]
        members.append((group, kind, dataclasses.field(default_factory=section)))

    def build(self) -> None:
        values = {
            name: getattr(getattr(self, group), name)
            for group, *_ in members
            for name in (f.name for f in dataclasses.fields(getattr(self, group)))
        }
        self.config = config_class(**values)

    cli = dataclasses.make_dataclass(
        config_class.__name__, members, namespace={"__post_init__": build}
    )
    cli.__doc__ = (
        f"{config_class.__doc__ or ''}\n\nEach flag's first sentence; the docs' recipe pages "
        "(Flags) give each in full."
    )
    return cli


def first_sentence(text: str) -> str:
    """The first sentence of a field's docstring: what ``--help`` shows of it.

    Examples:
        >>> from rl_pg.app.flags import first_sentence
        >>> first_sentence("Learning rate. Decays with lr_schedule, e.g. 'linear'.")
        'Learning rate.'
        >>> first_sentence("Where models live ('auto': CUDA when available). More.")
        "Where models live ('auto': CUDA when available)."
        >>> first_sentence("Steps (e.g. 5 per update) to take.")
        'Steps (e.g. 5 per update) to take.'
    """
    return SENTENCE_END.split(text, maxsplit=1)[0]


def field_docs(cls: type) -> dict[str, str]:
    """The docstrings written under a dataclass's fields, each on one line
    (subclasses' override their bases')."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
        except (OSError, TypeError, IndentationError):  # no source: defined interactively
            continue
        for node, after in itertools.pairwise(body):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)
            ):
                docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def _resumed_run_dir(args: list[str]) -> str | None:
    if "--resume" not in args:
        return None
    for i, arg in enumerate(args):
        if arg == "--run-dir" and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith("--run-dir="):
            return arg.split("=", 1)[1]
    return None


def flag(name: str, value) -> str:
    """The flag that sets field ``name`` to ``value``, as ``rl-pg train`` takes it.

    Examples:
        >>> from rl_pg.app.flags import flag
        >>> flag("kl_lr_range", [0.1, 3.0]), flag("lr", 0.001), flag("progress", False)
        ('--kl-lr-range 0.1 3.0', '--lr 0.001', '--no-progress')
    """
    name = name.replace("_", "-")
    if isinstance(value, bool):
        return f"--{name}" if value else f"--no-{name}"
    values = value if isinstance(value, (list, tuple)) else [value]  # a pair: LOW HIGH
    # Every digit (repr): a run is repeatable from its seed only with the exact values.
    return f"--{name} " + " ".join(repr(v) if isinstance(v, float) else str(v) for v in values)
