"""REINFORCE on CartPole-v1 until greedy play is solved (mean >= 475 over 20 episodes).

By default 32 CartPoles are stepped as one batch in this process (gymnasium's
SyncVectorEnv behind rl_pg's VectorGymEnv) and each update uses 8 steps of each, with
reward-to-go bootstrapped from a learned V(s) at the segment's end and V(s) as the
baseline: the fastest set-up on a CPU (see benchmarks/). The textbook variant, whole
episodes from one environment::

    rl-pg train cartpole --batch-mode episodes --num-envs 1
    rl-pg train cartpole --help
"""

from __future__ import annotations

from dataclasses import dataclass

from torchrl.envs import EnvBase

from rl_pg._checks import require_extra
from rl_pg.envs import gym_env
from rl_pg.models import mlp_actor_critic
from rl_pg.training import Count, TrainConfig
from rl_pg.training.recipe import Recipe
from rl_pg.training.settings import BatchedEnvironments, EnvPoolBackend


@dataclass
class Config(
    TrainConfig,
    BatchedEnvironments,
    EnvPoolBackend,
    num_envs=32,
    total_frames=300_000,
    batch_mode="segments",
    segment_length=8,
    episodes_per_batch=4,
    lr=5e-3,
    max_grad_norm=1.0,
    normalize_advantage=True,
    eval_interval=5_000,
    threshold=475.0,
):
    """REINFORCE with reward-to-go and a learned value baseline on CartPole-v1."""

    env_id: str = "CartPole-v1"
    """Gymnasium environment id: a CartPole's (v0 or v1). Another id trains with rl-pg
    train gym --env-id ID, under its own name and threshold."""
    hidden: Count = 64
    """Width of the two hidden layers of the actor and of the critic."""

    def validate(self) -> None:
        super().validate()
        if not self.env_id.startswith("CartPole-"):
            raise ValueError(
                f"rl-pg train cartpole trains CartPole (its threshold of 475 and its "
                f"defaults are CartPole's), not {self.env_id}: train it with rl-pg train "
                f"gym --env-id {self.env_id}, under its own name and threshold."
            )


def make_env(cfg: Config, *, render: bool = False) -> EnvBase:
    # One CartPole is unbatched; EnvPool steps a batch even of one (--backend is never
    # dropped). A watched episode is always gymnasium's, drawn with pygame.
    if render:
        require_extra("pygame", "classic", "Drawing CartPole's frames")
    if render or (cfg.num_envs == 1 and cfg.backend == "gymnasium"):
        return gym_env(cfg.env_id, render=render)
    if cfg.backend == "envpool":  # two halves that step in turn with --overlap
        return gym_env(cfg.env_id, num_envs=cfg.num_envs, backend="envpool", groups=1 + cfg.overlap)
    return gym_env(cfg.env_id, num_envs=cfg.num_envs)


def make_eval_env(cfg: Config) -> EnvBase:
    """The evaluation episodes, played side by side."""
    return gym_env(cfg.env_id, num_envs=cfg.eval_episodes if cfg.eval_episodes > 1 else None)


def make_models(env: EnvBase, cfg: Config):
    return mlp_actor_critic(env, hidden=(cfg.hidden, cfg.hidden))


RECIPE = Recipe(
    name="cartpole",
    config=Config,
    make_env=make_env,
    make_models=make_models,
    make_eval_env=make_eval_env,
)
