"""REINFORCE on MetaDrive, the driving tutorials' own simulator (docs/recipes/metadrive.md).

Trains on the tutorials' ``MetaDrive-validation-v0`` (scenarios 0 - 999; a
259-dimensional observation in [0, 1]; 9 joint [steering, throttle] actions). Greedy
evaluations during training, each in a process of its own, play 100 selection scenarios
and keep the best checkpoint; ``rl-pg evaluate`` scores it on 100 held-out scenarios,
apart from both. MetaDrive runs offline and headless (its asset download is skipped)::

    pip install -c constraints.txt "rl_pg[metadrive]"    # Python < 3.12
    rl-pg train metadrive --run-dir runs/metadrive
    rl-pg evaluate runs/metadrive                        # the best checkpoint, held out
    rl-pg evaluate runs/metadrive --on training          # ... on training scenarios
    rl-pg train metadrive --references                   # random and full-throttle drivers
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, ClassVar, Literal

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import EnvBase
from torchrl.envs.utils import RandomPolicy

from rl_pg.checkpoint import write_atomically
from rl_pg.envs import metadrive as md
from rl_pg.episode_workers import EpisodeWorkers
from rl_pg.evaluation import evaluate
from rl_pg.models import mlp_actor_critic
from rl_pg.training import Count, NonNegative, TrainConfig
from rl_pg.training.config import config_dict
from rl_pg.training.provenance import session_record
from rl_pg.training.recipe import Recipe
from rl_pg.training.seeds import evaluation_seed


@dataclass
class Config(
    TrainConfig,
    total_frames=2_000_000,
    # The tutorial's 200 whole episodes per update are 20k-200k steps here: ten to a
    # hundred updates in the whole budget. Segments of 256 steps per worker, bootstrapped
    # from V with GAE, give about 4 000. See the docs page for the runs that chose these.
    batch_mode="segments",
    segment_length=256,
    returns="gae",
    gae_lambda=0.95,
    gamma=0.99,
    critic_steps=5,
    # The tutorial's 0.1 kept the policy near uniform here (see the docs page).
    entropy_coeff=0.01,
    lr=1e-3,
    # Decayed to 0: at a constant 1e-3 the greedy policy moved by up to 0.15 route
    # completion between evaluations to the end (see the docs page).
    lr_schedule="linear",
    normalize_advantage=True,
    workers=2,  # one MetaDrive engine per process: collection on both cores
    checkpoint_interval=100,
    # 16 candidates for the best checkpoint; each evaluation plays whole episodes inside
    # the workers' processes.
    eval_interval=125_000,
    eval_episodes=100,  # every selection scenario once
    # The targets are success and route completion on held-out scenarios, not the
    # return (which pays for distance driven whether or not the car arrives): best.pt
    # is the checkpoint that reached its destination most often on the selection ones.
    select_by="arrive_dest_rate",
    threshold=None,
    stop_when_solved=False,
):
    """REINFORCE on MetaDrive: 9 discrete driving actions, standardised observations,
    GAE over 256-step segments, evaluated on held-out scenarios."""

    # Runs stored before --failure-penalty existed trained with MetaDrive's 5; before
    # --select-by, best.pt was their best mean return.
    absent_means: ClassVar[dict[str, Any]] = {"failure_penalty": 5.0, "select_by": "mean_return"}

    env_id: Literal[
        "MetaDrive-validation-v0", "MetaDrive-10env-v0", "MetaDrive-100envs-v0",
        "MetaDrive-1000envs-v0",
    ] = "MetaDrive-validation-v0"  # fmt: skip
    """Training scenarios. The best checkpoint is picked on scenarios 10100-10199 and
    scored on the held-out 10000-10099."""
    actions: Literal["tutorial", "swapped", "continuous"] = "tutorial"
    """A table of 9 actions, or 'continuous'. 'tutorial': the table as the tutorial fed
    it to MetaDrive (steering +-1, throttle +-0.6); 'swapped': steering +-0.6, throttle
    +-1; 'continuous': MetaDrive's own [steering, throttle] in [-1, 1]^2, from the
    policy that --bounded names."""
    bounded: Literal["normal", "beta", "tanh_normal"] | None = None
    """With --actions continuous: the policy's distribution. None: 'beta'. 'beta': a
    Beta on the bounds (Pendulum's; here it drives far better than the Gaussian, whose
    throttle mean leaves the bounds: see the MetaDrive page); 'normal': a Gaussian whose
    mean the network outputs, one learned scale per dimension in every state, its
    samples clipped by the environment (LunarLanderContinuous's); 'tanh_normal': a
    Gaussian squashed into them."""
    horizon: Count = md.DEFAULT_HORIZON
    """Time limit of an episode, in steps of 0.1 s."""
    hidden: Count = 128
    """Width of the hidden layers (Linear(259, 128)-ReLU-Linear(128, 9))."""
    layers: Count = 1
    """Number of hidden layers of the actor and of the critic."""
    lateral_reward: bool = False
    """Train on MetaDrive's lane-keeping reward. Its ``use_lateral_reward``: progress
    pays in proportion to how near the car keeps to its lane's centre. Only the training
    reward changes (its returns, and `rl-pg play` without `--gif`, are the shaped ones);
    every evaluation scores MetaDrive's default reward."""
    failure_penalty: NonNegative = 50.0
    """Penalty for leaving the road or crashing, in training. MetaDrive's
    ``out_of_road_penalty``, ``crash_vehicle_penalty`` and ``crash_object_penalty``;
    MetaDrive's own is 5, which at gamma 0.99 weighs little beside the driving a failure
    forfeits. Only the training reward changes, as with `--lateral-reward`; every
    evaluation scores MetaDrive's default reward."""
    normalize_observations: bool = True
    """Standardise each observation feature with running statistics. The features that
    steer, heading and lane position, vary by about 0.04."""
    references: bool = False
    """Instead of training, score a random and a full-throttle driver. Both play the
    held-out scenarios."""

    @classmethod
    def as_run(cls, stored: dict[str, Any]) -> dict[str, Any]:
        """Runs stored before ``bounded`` defaulted to None kept ``"normal"`` whatever
        their actions; for the 9-action tables that value meant nothing, and is dropped."""
        run = super().as_run(stored)
        if run.get("actions") != "continuous" and run.get("bounded") == "normal":
            run["bounded"] = None
        return run

    @property
    def distribution(self) -> Literal["normal", "beta", "tanh_normal"]:
        """The continuous policy's distribution: ``bounded``, or a Beta when unset."""
        return self.bounded or "beta"

    def validate(self) -> None:
        super().validate()
        selection = md.SCENARIO_SETS[md.SELECTION][1]
        if self.eval_episodes > selection:
            raise ValueError(
                f"--eval-episodes {self.eval_episodes}: evaluations play the {selection} "
                f"selection scenarios in order, each once; more would count some twice. "
                f"Ask for at most {selection}."
            )
        if self.bounded is not None and self.actions != "continuous":
            raise ValueError(
                f"--bounded {self.bounded} chooses the distribution of continuous actions, "
                f"but --actions is {self.actions!r}: add --actions continuous, or drop "
                f"--bounded."
            )


def _table(cfg: Config) -> str | None:
    """The action table the environment applies (None: MetaDrive's continuous actions)."""
    return None if cfg.actions == "continuous" else cfg.actions


# MetaDrive's terminal penalties that `--failure-penalty` sets (arriving pays +10).
REFERENCES = "references.json"  # what `--references` writes into its run directory
_FAILURE_PENALTIES = ("out_of_road_penalty", "crash_vehicle_penalty", "crash_object_penalty")


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    """The training scenarios, with the training reward; with ``render``, the held-out
    ones in order, seen from above."""
    if render:  # deployment: held-out scenarios in order
        return md.metadrive_env(
            md.HELD_OUT, actions=_table(cfg), order="sequential", horizon=cfg.horizon, render=True
        )
    config = dict.fromkeys(_FAILURE_PENALTIES, cfg.failure_penalty)
    config["use_lateral_reward"] = cfg.lateral_reward
    return md.metadrive_env(cfg.env_id, actions=_table(cfg), horizon=cfg.horizon, config=config)


def make_eval_env(cfg: Config) -> EpisodeWorkers:
    """The selection scenarios in order, split among ``cfg.workers`` processes."""
    return _in_order(md.SELECTION, cfg)


def make_test_env(cfg: Config) -> EpisodeWorkers:
    """The held-out scenarios in order, split among ``cfg.workers`` processes."""
    return _in_order(md.HELD_OUT, cfg)


def make_training_test_env(cfg: Config) -> EpisodeWorkers:
    """The training scenarios in order, split among ``cfg.workers`` processes, as the
    other sets (100 episodes play 100 training scenarios, consecutive within each
    worker's part, from where the evaluation's seed starts them)."""
    return _in_order(cfg.env_id, cfg)


def _in_order(env_id: str, cfg: Config, *, table: bool = True) -> EpisodeWorkers:
    """Each worker plays its consecutive part of the set in order, in a process of its
    own (one engine per process), or with ``--ray`` in a Ray actor of the cluster the
    training collects on: an evaluation of as many episodes as the set has scenarios
    plays each once. ``table=False``: MetaDrive's own actions, not the recipe's."""
    actions, horizon, workers = _table(cfg) if table else None, cfg.horizon, cfg.workers
    md.require_metadrive()  # here, rather than as a worker's traceback
    parts = md.split_scenarios(env_id, workers)
    return EpisodeWorkers(
        [
            partial(md.metadrive_env, env_id, actions=actions, order="sequential",
                    horizon=horizon, scenarios=part)
            for part in parts
        ],
        distinct_episodes=sum(len(part) for part in parts),
        backend="ray" if cfg.ray else "process",
    )  # fmt: skip


def make_models(env: EnvBase, cfg: Config):
    hidden = (cfg.hidden,) * cfg.layers
    return mlp_actor_critic(
        env,
        hidden=hidden,
        activation=nn.ReLU,
        normalize=cfg.normalize_observations,
        **({"bounded": cfg.distribution} if cfg.actions == "continuous" else {}),
        state_independent_scale=cfg.actions == "continuous" and cfg.distribution != "beta",
    )


def references(cfg: Config) -> dict:
    """Scores a random and an always-full-throttle driver as ``rl-pg evaluate`` scores
    trained agents: on the held-out scenarios. Writes them, with the config and where
    they ran, to ``references.json`` in ``--run-dir`` (``runs/metadrive-references``)."""
    drivers = (
        # uniformly among the 9 actions of the table, as an untrained policy starts
        ("random", True, lambda env: RandomPolicy(env.action_spec)),
        # MetaDrive's own [steering, throttle] = [0, 1], whatever the table
        ("full throttle", False, lambda env: _constant([0.0, 1.0])),
    )
    results = {}
    for name, table, make_policy in drivers:
        env = _in_order(md.HELD_OUT, cfg, table=table)
        try:
            torch.manual_seed(cfg.seed)
            env.set_seed(evaluation_seed(cfg.seed))  # the scenarios training evaluations play
            start = time.perf_counter()
            result = evaluate(
                make_policy(env), env, episodes=cfg.eval_episodes, flags=RECIPE.eval_flags,
                values=RECIPE.eval_values,
            )  # fmt: skip
            result["seconds"] = time.perf_counter() - start
        finally:
            env.close()
        results[name] = result
        print(f"{name}: " + ", ".join(f"{key} {value:.3f}" for key, value in result.items()))
    path = Path(cfg.run_dir or "runs/metadrive-references") / REFERENCES
    path.parent.mkdir(parents=True, exist_ok=True)
    stored = {"config": config_dict(cfg), "session": session_record(0), "drivers": results}
    write_atomically(path, json.dumps(stored, indent=1) + "\n")
    print(f"written to {path}")
    return results


class _Constant(nn.Module):
    """The same action in every state (a module, so it can be sent to a process)."""

    def __init__(self, action: list[float]) -> None:
        super().__init__()
        self.register_buffer("action", torch.tensor(action))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.action.expand(*observation.shape[:-1], -1)


def _constant(action: list[float]) -> TensorDictModule:
    return TensorDictModule(_Constant(action), ["observation"], ["action"])


RECIPE = Recipe(
    name="metadrive",
    config=Config,
    make_env=make_env,
    make_models=make_models,
    make_eval_env=make_eval_env,
    make_test_env=make_test_env,
    test_sets={"training": make_training_test_env, "selection": make_eval_env},
    eval_flags=md.METADRIVE_FLAGS,
    eval_values=md.METADRIVE_VALUES,
    commands={"references": references},
)
