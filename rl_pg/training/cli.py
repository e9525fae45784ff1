"""Command lines of the recipes: flags to a config, and resuming without retyping them."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TypeVar

import tyro

from rl_pg.checkpoint import CheckpointError
from rl_pg.training.checkpoints import read_run
from rl_pg.training.config import TrainConfig

__all__ = ["parse_config"]

Config = TypeVar("Config", bound=TrainConfig)


def parse_config(
    config_class: type[Config], args: Sequence[str] | None = None, *, prog: str | None = None
) -> Config:
    """``tyro.cli(config_class)``, except that ``--resume --run-dir DIR`` starts from the
    configuration stored in DIR's checkpoint: only the flags given on the command line
    change it (and the loop refuses changes that are not safe on resume).

    Args:
        config_class (type): a ``TrainConfig`` dataclass.
        args (sequence of str, optional): the command line. Defaults to ``sys.argv[1:]``.

    Keyword Args:
        prog (str, optional): the program's name in ``--help``.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor_critic
        >>> from rl_pg.training import TrainConfig, train
        >>> from rl_pg.training.cli import parse_config
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
    if run_dir is None:
        return tyro.cli(config_class, args=args, prog=prog)
    try:
        stored = read_run(run_dir)["config"]
    except CheckpointError:  # train() reports the missing or corrupted checkpoint
        return tyro.cli(config_class, args=args, prog=prog)
    default = config_class.from_stored(stored, resume=True, run_dir=Path(run_dir))
    return tyro.cli(config_class, args=args, default=default, prog=prog)


def _resumed_run_dir(args: list[str]) -> str | None:
    if "--resume" not in args:
        return None
    for i, arg in enumerate(args):
        if arg == "--run-dir" and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith("--run-dir="):
            return arg.split("=", 1)[1]
    return None
