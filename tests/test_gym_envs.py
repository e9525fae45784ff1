"""``rl_pg.envs.gym_env``: one gymnasium environment, or several stepped as one batch."""

from __future__ import annotations

import importlib.util

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import check_env_specs

from rl_pg.envs import InfoFlags, gym_env
from rl_pg.evaluation import evaluate
from rl_pg.models import mlp_actor


@pytest.mark.parametrize("num_envs", [None, 1, 5])
def test_specs(num_envs):
    env = gym_env("CartPole-v1", num_envs=num_envs)
    check_env_specs(env)
    assert env.batch_size == (() if num_envs is None else (num_envs,))


def test_batched_env_replays_independent_gymnasium_envs():
    """Each batch entry is the gymnasium env seeded seed + i, reset when it finishes."""
    n, steps, seed = 4, 300, 7
    env = gym_env("CartPole-v1", num_envs=n)
    env.set_seed(seed)
    refs = [gym.make("CartPole-v1") for _ in range(n)]
    for i, ref in enumerate(refs):
        ref.reset(seed=seed + i)  # what set_seed does; env.reset() below resets again
    ref_obs = [ref.reset()[0] for ref in refs]
    rng = np.random.default_rng(0)
    td = env.reset()
    ends = 0
    for _ in range(steps):
        np.testing.assert_allclose(td["observation"].numpy(), np.stack(ref_obs), rtol=0, atol=0)
        actions = rng.integers(0, 2, n)
        td["action"] = torch.as_tensor(actions)
        td, td_next_root = env.step_and_maybe_reset(td)
        for i, ref in enumerate(refs):
            obs, reward, terminated, truncated, _ = ref.step(int(actions[i]))
            np.testing.assert_allclose(td["next", "observation"][i].numpy(), obs, atol=0)
            assert td["next", "reward"][i].item() == reward
            assert td["next", "terminated"][i].item() == terminated
            assert td["next", "truncated"][i].item() == truncated
            if terminated or truncated:
                obs, _ = ref.reset()
                ends += 1
            ref_obs[i] = obs
        td = td_next_root
    assert ends > n  # the comparison went through many resets


def test_collector_and_greedy_evaluation_on_a_batched_env():
    env = gym_env("CartPole-v1", num_envs=3)
    actor = mlp_actor(env, hidden=(8,))
    collector = Collector(env, actor, frames_per_batch=3 * 40, total_frames=3 * 80)
    batches = list(collector)
    collector.shutdown()
    assert [b.shape for b in batches] == [torch.Size([3, 40])] * 2
    # Evaluation resets finished members itself (stepping past the end is refused), and
    # each member plays its share of the episodes back to back: 7 over 5 members is
    # 2, 2, 1, 1, 1. The same greedy episodes, played one by one on gymnasium's own
    # CartPoles seeded as the members are, give the same returns.
    with torch.no_grad():  # a policy that does not balance: episodes of varied lengths
        for p in actor.parameters():
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    batched = gym_env("CartPole-v1", num_envs=5)
    batched.set_seed(123)
    result = evaluate(actor, batched, episodes=7)
    returns = []
    for member, share in enumerate([2, 2, 1, 1, 1]):
        reference = gym.make("CartPole-v1")
        reference.reset(seed=123 + member)  # set_seed resets the members, seeded,
        obs, _ = reference.reset()  # and the evaluation's rollout resets them again
        for _ in range(share):
            total, done = 0.0, False
            while not done:
                logits = actor.module[0].module(torch.as_tensor(obs, dtype=torch.float32))
                obs, reward, terminated, truncated, _ = reference.step(int(logits.argmax()))
                total, done = total + reward, terminated or truncated
            returns.append(total)
            obs, _ = reference.reset()
    assert len(set(returns)) > 1  # not one length for all: the shares are told apart
    assert result["mean_return"] == pytest.approx(np.mean(returns))
    assert result["std_return"] == pytest.approx(np.std(returns))


def test_render_needs_a_single_environment():
    with pytest.raises(ValueError, match="single environment"):
        gym_env("CartPole-v1", num_envs=2, render=True)


@pytest.mark.skipif(importlib.util.find_spec("ale_py") is None, reason="ale-py is not installed")
def test_single_and_batched_games_keep_gymnasium_frameskip():
    # TorchRL's GymEnv replaces gymnasium's `frameskip` by its own `frame_skip` (1 by
    # default); a single env must skip like gymnasium and like the batched games.
    import ale_py

    gym.register_envs(ale_py)
    kwargs = {"frameskip": 4, "repeat_action_probability": 0.0}
    raw = gym.make("ALE/Pong-v5", **kwargs)
    single = gym_env("ALE/Pong-v5", **kwargs)
    batched = gym_env("ALE/Pong-v5", num_envs=2, **kwargs)
    expected, _ = raw.reset(seed=3)
    single.set_seed(3)
    batched.set_seed(3)
    one, both = single.reset(), batched.reset()
    assert np.array_equal(one["pixels"].numpy(), expected)
    assert np.array_equal(both["observation"][0].numpy(), expected)
    for step in range(40):
        action = (1, 2, 3)[step % 3]
        expected, *_ = raw.step(action)
        one = single.step(one.set("action", torch.tensor(action)))["next"]
        both = batched.step(both.set("action", torch.tensor([action, action])))["next"]
        assert np.array_equal(one["pixels"].numpy(), expected), step
        assert np.array_equal(both["observation"][0].numpy(), expected), step


@pytest.mark.parametrize(("num_envs", "error"), [(0, ValueError), (2.5, TypeError)])
def test_gym_env_refuses_a_bad_number_of_environments(num_envs, error):
    with pytest.raises(error, match="num_envs must be an integer"):
        gym_env("CartPole-v1", num_envs=num_envs)


def test_info_flags_refuses_a_single_string():
    with pytest.raises(TypeError, match=r"keys must be a sequence of names"):
        InfoFlags("crashed")
