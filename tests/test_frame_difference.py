"""FrameDifference on real ALE Pong frames, alone and on a batch of games."""

from __future__ import annotations

import gymnasium
import pytest
import torch
from torchrl.envs import TransformedEnv, check_env_specs

from rl_pg.envs import gym_env
from rl_pg.frame_difference import FrameDifference

ale_py = pytest.importorskip("ale_py")
gymnasium.register_envs(ale_py)
ALE = {"frameskip": 4, "repeat_action_probability": 0.0}


def test_observation_is_the_difference_of_processed_frames():
    env = TransformedEnv(gym_env("ALE/Pong-v5", **ALE), FrameDifference(keep_pixels=True))
    check_env_specs(env)
    env.set_seed(0)
    rollout = env.rollout(60, break_when_any_done=False)
    frames = FrameDifference.process(rollout["next", "pixels"]).flatten(-2)
    first = FrameDifference.process(rollout["pixels"][0]).flatten(-2)
    assert rollout["observation"][0].abs().sum() == 0  # zeros right after the reset
    torch.testing.assert_close(rollout["next", "observation"][0], frames[0] - first)
    torch.testing.assert_close(rollout["next", "observation"][1:], frames[1:] - frames[:-1])
    assert rollout["next", "observation"].abs().sum() > 0  # the ball and paddles move


def test_batched_games_reset_one_member_only():
    env = TransformedEnv(
        gym_env("ALE/Pong-v5", num_envs=2, **ALE), FrameDifference(in_key="observation")
    )
    assert env.observation_spec["observation"].shape == (2, 6400)
    env.set_seed(0)
    td = env.rollout(30, break_when_any_done=False)[..., -1]
    td = td["next"].clone()
    before = td.clone()
    td["_reset"] = torch.tensor([[True], [False]])
    after = env.reset(td)
    assert after["observation"][0].abs().sum() == 0  # the reset game starts afresh
    torch.testing.assert_close(after["observation"][1], before["observation"][1])
    torch.testing.assert_close(after["previous_frame"][1], before["previous_frame"][1])


def test_bad_frames_and_options():
    with pytest.raises(ValueError, match=r"\[\*B, 210, 160, 3\]"):
        FrameDifference.process(torch.zeros(84, 84, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="keep_pixels=True needs an out_key"):
        FrameDifference(in_key="observation", keep_pixels=True)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"in_key": 3}, "in_key must be a string"),
        ({"prev_key": ()}, "prev_key must be a string"),
        ({"keep_pixels": "yes"}, "keep_pixels must be True or False"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(TypeError, match=match):
        FrameDifference(**kwargs)
