"""Deploy a trained agent: load a run directory (or checkpoint), play, record.

python recipes/play.py runs/cartpole-seed0 --episodes 5 --gif cartpole.gif
python recipes/play.py runs/highway-seed0 --sample          # sample, not greedy
"""

from __future__ import annotations

import dataclasses
import importlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro

from rl_pg.evaluation import check_recording, play
from rl_pg.training import Count, Positive, Range, check_fields, load_models, read_run
from rl_pg.training.interrupt import exit_quietly_on_interrupt

sys.path.insert(0, str(Path(__file__).resolve().parent))


@dataclass
class Args:
    """Play a trained agent's episodes and print their returns."""

    run: tyro.conf.Positional[Path]
    """Run directory (or checkpoint file) written by a recipe."""
    episodes: Count = 5
    """Episodes to play."""
    checkpoint: Literal["best", "last"] = "best"
    """Deploy the best evaluated checkpoint, or the last one."""
    sample: bool = False
    """Sample actions from the policy instead of acting greedily."""
    gif: Path | None = None
    """Record the episodes to this .gif (or .mp4, with rl_pg[video]) file."""
    fps: Positive = 30.0
    """Frames per second of the recording."""
    seed: Annotated[int, Range(low=0, high=2**32 - 1)] = 0
    """Seed of the environment and of the sampled actions."""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.gif is not None:  # before the checkpoint is loaded and episodes played
            self.gif = check_recording(self.gif)


def main(args: Args) -> list[float]:
    saved = read_run(args.run, which=args.checkpoint)
    recipe = _recipe(saved["recipe"], args.run)
    fields = {f.name for f in dataclasses.fields(recipe.Config)}
    cfg = recipe.Config(**{k: v for k, v in saved["config"].items() if k in fields})
    if "num_envs" in fields:  # play one environment, whatever the run trained on
        cfg = dataclasses.replace(cfg, num_envs=1)
    env = recipe.make_env(cfg, render=args.gif is not None)
    actor, critic = recipe.make_models(env, cfg)
    load_models(saved, actor, critic)
    torch.manual_seed(args.seed)
    env.set_seed(args.seed)
    returns = play(
        actor,
        env,
        episodes=args.episodes,
        deterministic=not args.sample,
        record=args.gif,
        fps=args.fps,
    )
    for episode, value in enumerate(returns):
        print(f"episode {episode}: return {value:.2f}")
    print(f"mean return {sum(returns) / len(returns):.2f} over {len(returns)} episodes")
    if args.gif is not None:
        print(f"recorded {args.gif}")
    return returns


def _recipe(name: str, run: Path):
    """The recipe module that trained a run; runs of other code cannot be rebuilt here."""
    path = Path(__file__).resolve().parent / f"{name}.py"
    if name == Path(__file__).stem or not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.py") if p.stem != "play")
        raise ValueError(
            f"{run} was trained by {name!r}, which is not one of the recipes play.py can "
            f"rebuild ({', '.join(known)}). Its weights load from Python: "
            f"saved = rl_pg.training.read_run(run_dir, which='best'); build the same actor "
            f"and critic; rl_pg.training.load_models(saved, actor, critic)."
        )
    return importlib.import_module(name)


if __name__ == "__main__":
    with exit_quietly_on_interrupt():
        main(tyro.cli(Args))
