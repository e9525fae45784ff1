"""Trained agents as files: a run's deployed policy, exported without its training state,
and the agents shipped with rl_pg, to watch or evaluate without training.

rl-pg export runs/cartpole-seed0 --out cartpole.pt   # the run's best agent, as one file
rl-pg play cartpole.pt --gif cartpole.gif            # an agent file plays like a run
rl-pg play lunarlander --pretrained                  # the agent shipped for a recipe
rl-pg evaluate metadrive --pretrained --episodes 10

An agent file is a checkpoint (same format and checksum) that keeps only what rebuilds
and runs the models: the recipe, its config, the weights (the policy average's, for a
run trained with ``--policy-ema``: the ones its evaluations played) and where it came
from (the run, its frames, its last greedy and sampled ``rl-pg evaluate`` results, the
sessions that trained it). No optimiser state, random states or collector state: it
cannot be resumed, only deployed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tyro

from rl_pg.checkpoint import save_checkpoint
from rl_pg.training import read_run
from rl_pg.training.checkpoints import POLICY_AVERAGE, callback_states

__all__ = ["SHIPPED", "ExportArgs", "export_agent", "main", "shipped_agent"]

SHIPPED = Path(__file__).resolve().parent / "agents"
"""The folder of the agents shipped with rl_pg, one ``<recipe>.pt`` each."""


def shipped_agent(recipe: str) -> Path:
    """The agent file shipped for ``recipe``.

    Raises:
        ValueError: no agent is shipped for it (the message lists those that are).
    """
    path = SHIPPED / f"{recipe}.pt"
    if not path.is_file():
        names = sorted(p.stem for p in SHIPPED.glob("*.pt"))
        raise ValueError(
            f"No agent is shipped for {recipe!r}; --pretrained plays one of {names}. "
            f"Train one (rl-pg train {recipe}), or play an agent file: rl-pg play FILE.pt."
        )
    return path


def export_agent(run: str | Path, out: str | Path, *, which: str = "best") -> dict[str, Any]:
    """Writes the deployed agent of ``run`` (a run directory or a checkpoint file) to
    ``out`` as an agent file (see the module's description); returns what it wrote.

    Raises:
        CheckpointError: ``run`` has no such checkpoint, or it is damaged.
        ValueError: ``out`` is a directory.
    """
    if Path(out).is_dir():
        raise ValueError(f"--out {out} is a directory: name the agent file, e.g. {out}/agent.pt.")
    saved = read_run(run, which=which)
    weights = {
        key: value
        for key, value in saved["loss"].items()
        if key.startswith(("actor_network.", "critic_network."))
    }
    average = callback_states(saved).get(POLICY_AVERAGE)
    if average is not None:  # deploy what the evaluations played: the average
        actor = {k: v for k, v in average["weights"].items() if k.startswith("module.")}
        weights = {k: v for k, v in weights.items() if not k.startswith("actor_network.")}
        weights |= {"actor_network." + k.removeprefix("module."): v for k, v in actor.items()}
    state = saved.get("state", {})
    agent = {
        "recipe": saved["recipe"],
        "recipe_module": saved.get("recipe_module"),
        "config": saved["config"],
        "loss": weights,
        "state": {k: state.get(k) for k in ("frames", "updates", "best_mean_return")},
        "agent": {
            "exported_from": Path(run).resolve().name,  # the run directory's (or file's) name
            "checkpoint": which if Path(run).is_dir() else Path(run).name,
            # the results rl-pg evaluate recorded are the best checkpoint's
            **(_history(Path(run)) if Path(run).is_dir() and which == "best" else {}),
        },
    }
    save_checkpoint(agent, out)
    return agent


def _history(run: Path) -> dict[str, Any]:
    """The run's last greedy and sampled ``rl-pg evaluate`` results of its best
    checkpoint, as ``rl-pg report`` reads them, and the sessions that trained it."""
    from rl_pg.recipes.report import read_report

    try:
        report = read_report(run)
    except ValueError:  # no summary yet: a run still in its first session
        return {}
    return {
        "greedy": report.get("greedy"),
        "sampled": report.get("sampled"),
        "sessions": report.get("sessions"),
    }


@dataclass
class ExportArgs:
    """Write a run's deployed agent to one file, without its training state."""

    run: tyro.conf.Positional[Path]
    """Run directory (or checkpoint file) written by a recipe."""
    out: Path
    """The agent file to write (.pt). Play it with rl-pg play FILE, evaluate it with
    rl-pg evaluate FILE."""
    checkpoint: Literal["best", "last"] = "best"
    """Export the best checkpoint (what rl-pg play deploys), or the last."""


def main(args: ExportArgs) -> Path:
    """Exports the agent; prints what was written."""
    agent = export_agent(args.run, args.out, which=args.checkpoint)
    size = Path(args.out).stat().st_size
    print(
        f"{args.out}: the {agent['recipe']} agent of {args.run} ({args.checkpoint} checkpoint, "
        f"{agent['state']['frames']:,} frames), {size / 1024:.0f} KiB"
    )
    return Path(args.out)
