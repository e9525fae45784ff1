"""Evaluate a trained agent as its training evaluated it, on fresh episodes.

rl-pg evaluate runs/lunarlander-seed0                 # best checkpoint, 100 greedy episodes
rl-pg evaluate runs/lunarlander-seed0 --sample        # by sampling
rl-pg evaluate runs/metadrive-seed0 --checkpoint last --episodes 20
rl-pg evaluate runs/metadrive-seed0 --action-stats    # how the policy acts, too
rl-pg evaluate runs/metadrive-seed0 --on training     # on scenarios it trained on
rl-pg evaluate runs/md-ema --trained-weights           # a --policy-ema run's own weights

The recipe's test environment (its evaluation environment, on fresh seeds, unless the
recipe keeps scenarios apart for scoring, as MetaDrive's does), with its metrics (flag
rates such as crashes, values such as route completion), rebuilt from the run directory
alone. Each result is also appended to the run's ``evaluations.jsonl``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from rl_pg.app.sources import AgentSource, agent_path
from rl_pg.recipes import recipe_of
from rl_pg.training import Count, Range, read_run

__all__ = ["EVALUATIONS", "Args", "main"]

EVALUATIONS = "evaluations.jsonl"
"""The file of a run directory that collects its ``rl-pg evaluate`` results."""


@dataclass
class Args(AgentSource):
    """Evaluate a trained agent on the recipe's test environment."""

    episodes: Count = 100
    """Episodes to evaluate on."""
    checkpoint: Literal["best", "last"] = "best"
    """Of a run directory, the best checkpoint or the last. A checkpoint file is
    evaluated as it is."""
    sample: bool = False
    """Sample actions from the policy instead of acting greedily."""
    seed: Annotated[int, Range(low=0, high=2**32 - 1)] | None = None
    """Seed of the episodes and of sampled actions (None: fresh episodes). None picks a
    seed that no evaluation during training used."""
    action_stats: bool = False
    """Also report how a discrete policy acted. The share of steps of each action, how
    often the action changes from one step to the next, how often it is the policy's
    most probable one, and the policy's mean entropy."""
    on: str | None = None
    """Play another set of environments than the test set. MetaDrive: ``training`` or
    ``selection`` scenarios, to compare with the held-out ones."""
    trained_weights: bool = False
    """With --policy-ema runs: play the trained weights, not their average. The average
    is what the run evaluated, kept as best.pt and deploys; this compares the two."""


def main(args: Args) -> dict[str, Any]:
    """Evaluates the run's agent; prints and returns the result."""
    run = agent_path(args.run, pretrained=args.pretrained, hub=args.hub)
    saved = read_run(run, which=args.checkpoint)
    recipe = recipe_of(saved, run)
    result = recipe.evaluate_checkpoint(
        saved, episodes=args.episodes, sample=args.sample, seed=args.seed,
        action_stats=args.action_stats, on=args.on, trained_weights=args.trained_weights,
    )  # fmt: skip
    # A checkpoint file is itself the checkpoint: --checkpoint picks within a run directory.
    record = {"checkpoint": args.checkpoint if run.is_dir() else run.name, **result}
    print(_describe(record))
    if run.is_dir():
        append_record(run / EVALUATIONS, record)
    return record


def append_record(path: Path, record: dict[str, Any]) -> None:
    """Appends ``record`` to the JSON-lines file ``path`` as one line of its own: after a
    torn last line (a write killed half-way), it starts on a fresh line, so the torn
    line alone is lost (readers skip it, naming it) and this record is kept."""
    with open(path, "a+b") as file:
        file.seek(0, os.SEEK_END)
        if file.tell() > 0:
            file.seek(-1, os.SEEK_END)
            if file.read(1) != b"\n":
                file.write(b"\n")
        file.write((json.dumps(record) + "\n").encode())


def _describe(record: dict[str, Any]) -> str:
    frames = "" if record["frames"] is None else f" at {record['frames']:,} frames"
    on = f", on {record['on']}" if "on" in record else ""
    on += f", {record['weights']} weights" if "weights" in record else ""
    head = (
        f"{_name(record['checkpoint'])}{frames}, {record['mode']}, "
        f"{record['episodes']} episodes (seed {record['seed']}{on}): "
        f"return {record['mean_return']:.2f} ± {record['std_return']:.2f}, "
        f"length {record['mean_length']:.1f}"
    )
    extra = [
        f"{key} {value:.0%}" if key.endswith("_rate") else f"{key} {value:.3f}"
        for key, value in record.items()
        if key.endswith("_rate") or (key.startswith("mean_") and key not in _BASE)
    ]
    text = head + "".join(f", {item}" for item in extra) + f" ({record['seconds']:.0f} s)"
    if "action_shares" in record:
        shares = " ".join(f"{i}:{share:.1%}" for i, share in enumerate(record["action_shares"]))
        text += f"\n  actions played (index: share of steps): {shares}"
    return text


def _name(checkpoint: str) -> str:
    return f"{checkpoint} checkpoint" if checkpoint in ("best", "last") else checkpoint


_BASE = {"mean_return", "mean_length"}
