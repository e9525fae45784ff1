"""rl_pg.training.optimisation: what one update logs about the policy."""

from __future__ import annotations

import pytest
import torch

from rl_pg.envs import GridWorldEnv, gym_env
from rl_pg.models import mlp_actor
from rl_pg.training.optimisation import means_beyond_bounds


@pytest.mark.parametrize("bounded", ["normal", "beta", "tanh_normal"])
def test_means_beyond_bounds_is_measured_for_a_clipped_gaussian_only(bounded):
    env = gym_env("Pendulum-v1")  # torque in [-2, 2]
    actor = mlp_actor(env, bounded=bounded)
    batch = env.rollout(6, actor)
    if bounded != "normal":  # a Beta's mean is inside; a TanhNormal's loc is pre-squash
        assert means_beyond_bounds(actor, batch) is None
        return
    batch["loc"] = torch.tensor([[2.5], [-2.01], [1.9], [0.0], [-1.0], [2.0]])
    assert means_beyond_bounds(actor, batch) == pytest.approx(2 / 6)  # 2.0 is inside
    batch["loc"] = torch.full((6, 1), 7.0)  # a driver stuck at full throttle
    assert means_beyond_bounds(actor, batch) == 1.0


def test_means_beyond_bounds_takes_the_worst_dimension_and_skips_discrete_policies():
    env = gym_env("LunarLander-v3", continuous=True)  # [main, lateral] in [-1, 1]^2
    actor = mlp_actor(env, bounded="normal")
    batch = env.rollout(4, actor)
    batch["loc"] = torch.tensor([[0.0, 3.0], [0.0, 3.0], [0.0, 3.0], [1.5, 0.0]])
    assert means_beyond_bounds(actor, batch) == 0.75  # lateral: 3 of 4; main: 1 of 4
    grid = GridWorldEnv()
    assert means_beyond_bounds(mlp_actor(grid), grid.rollout(3)) is None


def test_means_beyond_bounds_of_batched_environments_in_segments_and_flat():
    env = gym_env("Pendulum-v1", num_envs=3)  # bounds of shape [3, 1]
    actor = mlp_actor(env, bounded="normal")
    batch = env.rollout(4, actor)  # [3 environments, 4 steps]
    assert batch["loc"].shape == (3, 4, 1) and env.action_spec.space.low.shape == (3, 1)
    loc = torch.zeros(3, 4, 1)
    loc[0, :2] = 2.5  # 2 of 12 steps beyond
    batch["loc"] = loc
    assert means_beyond_bounds(actor, batch) == pytest.approx(2 / 12)
    assert means_beyond_bounds(actor, batch.reshape(-1)) == pytest.approx(2 / 12)
