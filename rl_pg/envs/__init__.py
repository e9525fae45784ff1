"""Batched, torch-native environments for the small problems, and gymnasium helpers."""

from rl_pg.envs.bandit import BanditEnv
from rl_pg.envs.envpool import EnvPoolEnv
from rl_pg.envs.gridworld import GridWorldEnv
from rl_pg.envs.gym import DRIVING_ACTIONS, driving_env, gym_env
from rl_pg.envs.info import InfoFlags
from rl_pg.envs.vector import VectorGymEnv

__all__ = [
    "DRIVING_ACTIONS",
    "BanditEnv",
    "EnvPoolEnv",
    "GridWorldEnv",
    "InfoFlags",
    "VectorGymEnv",
    "driving_env",
    "gym_env",
]
