"""``rl-pg``: train a recipe, resume a run, evaluate or play a trained agent, list the recipes.

    rl-pg list
    rl-pg train cartpole --seed 1          # rl-pg train cartpole --help: every flag
    rl-pg resume runs/cartpole-seed1-...   # continue with the run's stored config
    rl-pg evaluate runs/cartpole-seed1-... --sample
    rl-pg play runs/cartpole-seed1-... --gif cartpole.gif
    rl-pg tune cartpole --trials 20 --params lr gamma --total-frames 100000
    rl-pg report runs/cartpole-seed* --plot seeds.png
    rl-pg lab variance cartpole --seeds 0 1 2

``python -m rl_pg.app`` is the same command; in a checkout, ``python
recipes/<name>.py`` runs ``rl-pg train <name>`` and ``python recipes/play.py``
runs ``rl-pg play``.
"""

from __future__ import annotations

import importlib
import multiprocessing
import os
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from rl_pg._process import frozen_heap
from rl_pg.app.flags import flag, parse_args, parse_config
from rl_pg.checkpoint import CheckpointError
from rl_pg.recipes import NAMES, load, recipe_of
from rl_pg.training.checkpoints import LATEST, read_run, resolve_latest
from rl_pg.training.config import DeviceUnavailable
from rl_pg.training.console import format_comparison, format_summary
from rl_pg.training.interrupt import exit_quietly_on_interrupt
from rl_pg.training.run_dir import RunDirBusy, RunDirUnusable

__all__ = ["main", "run", "run_checkout_script"]

USAGE = """usage: rl-pg {list,train,resume,evaluate,play,export,tune,report,lab} ...

  rl-pg list                       the recipes and what they train
  rl-pg train RECIPE [FLAGS]       train a recipe (rl-pg train RECIPE --help: its flags)
  rl-pg resume RUN_DIR [FLAGS]     continue a run with its stored config; FLAGS may
                                   change what is safe to change (budget, workers, ...)
  rl-pg evaluate RUN_DIR [FLAGS]   evaluate a run's best agent on fresh episodes (--help)
  rl-pg play RUN_DIR [FLAGS]       play, and record, a run's best agent (--help: flags)
  rl-pg play RECIPE --pretrained   the same with the agent shipped for a recipe
  rl-pg export RUN_DIR --out FILE  a run's best agent as one file, to share and play
  rl-pg tune RECIPE [FLAGS]        search a recipe's hyperparameters with Optuna (--help)
  rl-pg report RUN_DIR... [FLAGS]  runs side by side: a table, and curves with --plot
  rl-pg lab variance RECIPE [FLAGS]
                                   train seeds measuring the gradient noise of every
                                   return estimator; a figure and a table (--help)
"""


# The commands that take a recipe (or a run) first: their usage, for `--help` or a
# missing first argument (the recipe's own flags come with `rl-pg COMMAND RECIPE --help`).
COMMAND_USAGE = {
    "train": """usage: rl-pg train RECIPE [FLAGS]

Train a recipe: its run goes to --run-dir (default runs/RECIPE-seedS-TIME, with
runs/latest naming it). `rl-pg train RECIPE --help` lists the recipe's flags.
""",
    "resume": """usage: rl-pg resume RUN_DIR [FLAGS]

Continue a run from its last checkpoint with the configuration it stored; FLAGS may
change only what is safe to change (the budget, the workers, logging).
""",
    "tune": """usage: rl-pg tune RECIPE [FLAGS]

Search a recipe's hyperparameters with Optuna (needs rl_pg[tune]); each trial is a run
of its own. `rl-pg tune RECIPE --help` lists the search's flags and the recipe's.
""",
    "lab": """usage: rl-pg lab variance RECIPE [FLAGS]

The lab's experiments. variance: train a recipe's seeds measuring the gradient noise
of every return estimator on the same batches, then draw it and tabulate it.
`rl-pg lab variance RECIPE --help` lists the lab's flags and the recipe's.
""",
}
COMMAND_USAGE["lab variance"] = COMMAND_USAGE["lab"]


def _command_usage(command: str, rest: list[str]) -> str | None:
    """The usage to print when ``rl-pg COMMAND REST`` asks for help or lacks its
    recipe (None: the command runs)."""
    if command == "lab":
        command, rest = ("lab variance", rest[1:]) if rest[:1] == ["variance"] else ("lab", rest)
    if command not in COMMAND_USAGE:
        return None
    if rest and rest[0] not in ("-h", "--help"):
        return None
    recipes = "" if command == "resume" else f"Recipes: {', '.join(NAMES)}.\n"
    return COMMAND_USAGE[command] + recipes


def run(argv: Sequence[str] | None = None) -> None:
    """The ``rl-pg`` command as a process of its own: [`main`][rl_pg.app.cli.main]
    with the imports' objects kept out of the garbage collector's walks, and none left
    for the interpreter's teardown (see ``rl_pg._process.frozen_heap``). The console
    script, ``python -m rl_pg.app`` and a checkout's ``recipes/*.py`` start here."""
    _fork_workers_from_a_preloaded_server()
    with frozen_heap():
        main(argv)


# What a worker process (a collector's, an evaluation's) imports to build its
# environment and policy: torch, tensordict and TorchRL with them.
WORKER_IMPORTS = ["rl_pg.recipes", "rl_pg.training", "rl_pg.evaluation"]


def _fork_workers_from_a_preloaded_server() -> None:
    """Worker processes start by a fork of one server process that imported
    ``WORKER_IMPORTS`` once, instead of each starting a fresh interpreter that imports
    them again (5-6 s of CPU each here). Unlike a fork of this process, the server runs
    no thread and holds no environment, so the workers start as clean as spawned ones
    (Python 3.14 makes it the default on Linux). Only for this command's own process:
    TorchRL sets "spawn" when it is imported, which code that imports rl_pg keeps."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        multiprocessing.set_start_method("forkserver", force=True)
        multiprocessing.set_forkserver_preload(WORKER_IMPORTS)


def main(argv: Sequence[str] | None = None) -> None:
    """The ``rl-pg`` command (``argv`` defaults to ``sys.argv[1:]``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    command, rest = (args[0], args[1:]) if args else ("", [])
    with exit_quietly_on_interrupt(), _user_errors():
        usage = _command_usage(command, rest)
        if usage is not None:  # help asked for, or the recipe (or run) missing
            asked = bool(rest) and rest[-1] in ("-h", "--help")
            print(usage, end="", file=sys.stdout if asked else sys.stderr)
            sys.exit(0 if asked else 2)
        if command == "list":
            _list()
        elif command == "train" and rest and not rest[0].startswith("-"):
            _train(rest[0], rest[1:])
        elif command == "resume" and rest and not rest[0].startswith("-"):
            _resume(resolve_latest(rest[0]), rest[1:])
        elif command in ("evaluate", "play", "export"):
            _subcommand(command, rest)
        elif command == "report":
            latest = [str(resolve_latest(a)) if Path(a).name == LATEST else a for a in rest]
            _subcommand(command, latest)
        elif command == "tune" and rest and not rest[0].startswith("-"):
            _tune(rest[0], rest[1:])
        elif command == "lab" and rest[:1] == ["variance"] and len(rest) > 1:
            _lab_variance(rest[1], rest[2:])
        elif command in ("-h", "--help"):
            print(USAGE, end="")
        else:
            print(USAGE, end="", file=sys.stderr)
            sys.exit(2)


def run_checkout_script(path: str) -> None:
    """What ``python recipes/<name>.py`` runs in a checkout: ``rl-pg train <name>``
    (``rl-pg play`` for ``play.py``)."""
    # Python puts a script's folder first on the import path, where recipes/metadrive.py
    # would shadow the metadrive package: these scripts import nothing from there.
    folder = str(Path(path).resolve().parent)
    sys.path[:] = [p for p in sys.path if str(Path(p or ".").resolve()) != folder]
    name = Path(path).stem
    run(["play", *sys.argv[1:]] if name == "play" else ["train", name, *sys.argv[1:]])


@contextmanager
def _user_errors() -> Iterator[None]:
    """Errors in what the user asked for (a busy, foreign or unusable run directory, a
    missing package or device, a tracking server that does not answer): the message
    alone, and exit status 1."""
    try:
        yield
    except (CheckpointError, RunDirBusy, RunDirUnusable, DeviceUnavailable, ImportError,
            ConnectionError) as err:  # fmt: skip
        sys.exit(f"rl-pg: {err}")


def _list() -> None:
    width = max(map(len, NAMES))
    for name in NAMES:
        print(f"{name:<{width}}  {load(name).description}")


def _train(name: str, args: list[str]) -> None:
    try:
        recipe = load(name)
    except ValueError as err:
        sys.exit(f"rl-pg train: {err}")
    cfg = parse_config(recipe.config, args, prog=f"rl-pg train {name}")
    _report(recipe.run(cfg))


def _tune(name: str, args: list[str]) -> None:
    from rl_pg.training.tuning import TuneArgs, tune

    recipe, tuning, base, study_dir = _command_over_runs("tune", name, args, TuneArgs, "tune")

    def search():
        return tune(
            recipe, base, params=tuning.params, trials=tuning.trials, seeds=tuning.tune_seeds,
            objective=tuning.objective, held_out_episodes=tuning.held_out_episodes,
            seed_score=tuning.seed_score, study_dir=study_dir, pruner=tuning.pruner,
        )  # fmt: skip

    # --jobs N: N-1 more searches on the same study, each a process of its own (the
    # study's locks let searches share it); this one reports the result once all ended.
    own = [a for i, a in enumerate(args) if a != "--jobs" and not a.startswith("--jobs=")
           and (i == 0 or args[i - 1] != "--jobs")]  # fmt: skip
    command = [sys.executable, "-m", "rl_pg.app", "tune", name, *own, "--jobs", "1"]
    jobs = [
        subprocess.Popen(command, env={**os.environ, _TUNE_JOB: "1"})
        for _ in range(tuning.jobs - 1)
    ]
    try:
        result = search()
    except ValueError as err:
        sys.exit(f"rl-pg tune: {err}")
    finally:
        failed = [job.args for job in jobs if job.wait() != 0]
    if failed:
        sys.exit(f"rl-pg tune: {len(failed)} of the {tuning.jobs} searches failed (their "
                 f"messages are above); the study keeps every trial that completed.")  # fmt: skip
    if os.environ.get(_TUNE_JOB):
        return  # one search of several: the command that started it reports
    if jobs:
        result = search()  # every search's trials counted: none left to run
    flags = " ".join(flag(k, v) for k, v in result["best_settings"].items())
    print(
        f"{result['trials']} trials in {study_dir} ({result['pruned']} pruned); best: trial "
        f"{result['best_trial']}, "
        f"score {result['best_score']:.2f} ({result['objective']} evaluation, "
        f"{result['seed_score']} over seeds {result['seeds']}). Its flags: {flags}"
    )
    if result["reference_score"] is not None:
        print(f"The settings as given (trial 0) scored {result['reference_score']:.2f}.")


_TUNE_JOB = "RL_PG_TUNE_JOB"  # set in the extra searches of rl-pg tune --jobs N


def _lab_variance(name: str, args: list[str]) -> None:
    from rl_pg.app.lab import LabArgs, variance_lab

    recipe, lab, base, root = _command_over_runs(
        "lab variance", name, args, LabArgs, "lab-variance"
    )
    try:
        variance_lab(recipe, base, seeds=lab.seeds, every=lab.every, root=root)
    except (ValueError, FileNotFoundError) as err:  # bad flags, or runs measured nothing
        sys.exit(f"rl-pg lab variance: {err}")
    print((root / "variance.md").read_text(), end="")
    print(f"Figure: {root / 'variance.png'}; every seed's run in {root}/seed<S>.")


def _command_over_runs(command: str, name: str, args: list[str], own_args, folder: str):
    """What a command that trains a recipe's runs reads: the recipe, the command's own
    flags (``own_args``), the recipe's config from every other flag, and the directory
    its runs go to (``--run-dir``, default ``runs/<folder>-<recipe>``)."""
    try:
        recipe = load(name)
    except ValueError as err:
        sys.exit(f"rl-pg {command}: {err}")
    prog = f"rl-pg {command} {name}"
    own, rest = parse_args(own_args, args, prog=prog, return_unknown_args=True)
    base = parse_config(recipe.config, rest, prog=prog)
    root = Path(base.run_dir if base.run_dir is not None else f"runs/{folder}-{name}")
    return recipe, own, base, root


def _resume(run_dir: Path, args: list[str]) -> None:
    # Read here to rebuild the run; train() reads it again once it holds the directory,
    # in case another process wrote it in between.
    saved = read_run(run_dir)
    try:
        recipe = recipe_of(saved, run_dir)
    except ValueError as err:
        sys.exit(f"rl-pg resume: {err}")
    args = ["--resume", "--run-dir", str(run_dir), *args]
    cfg = parse_config(recipe.config, args, prog=f"rl-pg resume {run_dir}", stored=saved["config"])
    _report(recipe.run(cfg))


# What each subcommand's user can mend (a run that cannot be rebuilt, a missing extra,
# not a run directory, no such metric): said in one line.
_SUBCOMMANDS = {
    "play": ("Args", (ValueError, ImportError)),
    "export": ("ExportArgs", (ValueError,)),
    "evaluate": ("Args", (ValueError, ImportError)),
    "report": ("Args", (ValueError, FileNotFoundError)),
}


def _subcommand(command: str, args: list[str]) -> None:
    """``rl-pg COMMAND ARGS``: ``rl_pg.app.COMMAND.main`` on its parsed flags."""
    args_class, mendable = _SUBCOMMANDS[command]
    module = importlib.import_module(f"rl_pg.app.{command}")
    try:
        module.main(parse_args(getattr(module, args_class), args, prog=f"rl-pg {command}"))
    except mendable as err:
        sys.exit(f"rl-pg {command}: {err}")


def _report(result: dict) -> None:
    """A run's summary, or a comparison's; a recipe command printed its own result."""
    if "frames" in result:
        print(format_summary(result))
    elif result and all(isinstance(runs, list) for runs in result.values()):
        print(format_comparison(result))
