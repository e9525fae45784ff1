"""Deploy a trained agent: load a run directory (or checkpoint), play, record.

rl-pg play runs/cartpole-seed0 --episodes 5 --gif cartpole.gif
rl-pg play runs/highway-seed0 --sample          # sample, not greedy
rl-pg play runs/highway-seed0 --checkpoint last # the last weights, not the best
rl-pg play lunarlander --pretrained             # the agent shipped with rl_pg
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import torch

from rl_pg.app.sources import AgentSource, agent_path
from rl_pg.recipes import recipe_of
from rl_pg.recording import check_recording, play
from rl_pg.training import Count, Positive, Range, check_fields, load_models, read_run
from rl_pg.training.threads import torch_threads

__all__ = ["Args", "main"]


@dataclass
class Args(AgentSource):
    """Play a trained agent's episodes and print their returns."""

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
    """Plays ``args.episodes`` episodes of the run's agent; returns their returns."""
    run = agent_path(args.run, pretrained=args.pretrained, hub=args.hub)
    saved = read_run(run, which=args.checkpoint)
    recipe = recipe_of(saved, run)
    cfg = recipe.config.from_stored(saved["config"], num_envs=1)  # one environment, to watch
    with torch_threads(cfg.threads):
        make_env = recipe.make_play_env or recipe.make_env
        env = make_env(cfg, render=args.gif is not None)
        try:
            if args.gif is not None and "pixels" not in env.observation_spec.keys():
                raise ValueError(
                    f"The {recipe.name} recipe draws no frames (its make_env(cfg, "
                    f"render=True) gives no 'pixels'), so --gif has nothing to record: "
                    f"play it without --gif."
                )
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
        finally:
            env.close()  # some simulators (MetaDrive) allow one open environment per process
    for episode, value in enumerate(returns):
        print(f"episode {episode}: return {value:.2f}")
    print(f"mean return {sum(returns) / len(returns):.2f} over {len(returns)} episodes")
    if args.gif is not None:
        print(f"recorded {args.gif}")
    return returns
