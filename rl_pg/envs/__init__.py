"""Batched, torch-native environments for the tutorials' small problems."""

from rl_pg.envs.bandit import BanditEnv
from rl_pg.envs.gridworld import GridWorldEnv

__all__ = ["BanditEnv", "GridWorldEnv"]
