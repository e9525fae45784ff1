"""rl_pg.training.optimisation: what one update does and logs about the policy."""

from __future__ import annotations

import copy
from dataclasses import replace

import pytest
import torch

from rl_pg.action_stats import means_beyond_bounds
from rl_pg.envs import GridWorldEnv, gym_env
from rl_pg.models import mlp_actor, mlp_actor_critic
from rl_pg.training import TrainConfig
from rl_pg.training.optimisation import make_loss, make_optimizer, update


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


@pytest.mark.parametrize("scope", ["joint", "per_network"])
def test_clip_scope_sets_whose_gradient_norm_is_bounded(scope, tmp_path):
    # SGD at rate 1 moves each weight by its clipped gradient: the step is the gradient.
    env = gym_env("CartPole-v1")
    actor, critic = mlp_actor_critic(env)
    rewards = TrainConfig(run_dir=tmp_path, lr=1.0, optimizer="sgd", gamma=0.99)
    batch = env.rollout(50, actor, break_when_any_done=False)
    batch["next", "reward"] = batch["next", "reward"] * 100  # a critic error far above 1
    cfg = replace(rewards, max_grad_norm=0.5, clip_scope=scope)
    clipped = _step(cfg, make_loss(cfg, *copy.deepcopy((actor, critic))), batch)
    unclipped = _step(replace(rewards, max_grad_norm=None), make_loss(cfg, actor, critic), batch)
    norm = {
        k: torch.linalg.vector_norm(torch.cat([g.flatten() for g in v]))
        for k, v in unclipped.items()
    }
    assert norm["critic"] > 2 * norm["actor"] > 2  # the case the scope is for
    for net in ("actor", "critic"):
        step = torch.linalg.vector_norm(torch.cat([g.flatten() for g in clipped[net]]))
        if scope == "per_network":  # each bounded by itself
            torch.testing.assert_close(step, torch.tensor(0.5))
        else:  # one factor for both, set by their joint norm
            joint = torch.linalg.vector_norm(torch.stack(list(norm.values())))
            torch.testing.assert_close(step, 0.5 * norm[net] / joint)


def _step(cfg, loss, batch) -> dict[str, list[torch.Tensor]]:
    """The change of each network's weights in one update."""
    nets = {"actor": loss.actor_network, "critic": loss.critic_network}
    before = {k: [p.detach().clone() for p in net.parameters()] for k, net in nets.items()}
    update(cfg, loss, make_optimizer(cfg, loss), batch, lr=cfg.lr)
    return {
        k: [b - p.detach() for b, p in zip(before[k], net.parameters(), strict=True)]
        for k, net in nets.items()
    }


def test_scale_lr_factor_steps_the_gaussian_scale_apart_at_every_rate(tmp_path):
    # SGD moves each weight by lr times its gradient: the scale's step is factor x larger.
    env = gym_env("Pendulum-v1")
    actor, critic = mlp_actor_critic(env, state_independent_scale=True)
    with torch.no_grad():
        batch = env.rollout(50, actor, break_when_any_done=False)
    cfg = TrainConfig(run_dir=tmp_path, lr=0.01, optimizer="sgd", gamma=0.99)
    steps = {}
    for factor in (1.0, 10.0):
        cfg = replace(cfg, scale_lr_factor=factor)
        loss = make_loss(cfg, *copy.deepcopy((actor, critic)))
        optimizer = make_optimizer(cfg, loss)
        scale = next(p for n, p in loss.actor_network.named_parameters() if "scale" in n)
        before = scale.detach().clone()
        update(cfg, loss, optimizer, batch, lr=0.5 * cfg.lr)  # a scheduled rate
        steps[factor] = scale.detach() - before
        assert [g["lr"] for g in optimizer.param_groups] == (
            [0.005] if factor == 1 else [0.005, 0.05]
        )
    assert steps[1.0].abs().min() > 0
    torch.testing.assert_close(steps[10.0], 10 * steps[1.0])


def test_scale_lr_factor_refuses_a_policy_without_a_learned_scale(tmp_path):
    env = gym_env("Pendulum-v1")
    cfg = TrainConfig(run_dir=tmp_path, scale_lr_factor=10.0)
    loss = make_loss(cfg, *mlp_actor_critic(env))  # the scale is an output of the network
    with pytest.raises(ValueError, match=r"--scale-lr-factor 10\.0 .* has none"):
        make_optimizer(cfg, loss)
    with pytest.raises(ValueError, match="--optimizer natural has no learning rate"):
        TrainConfig(run_dir=tmp_path, scale_lr_factor=10.0, optimizer="natural").validate()
