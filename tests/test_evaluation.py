"""Evaluation over whole episodes."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor

from rl_pg.envs import BanditEnv, GridWorldEnv
from rl_pg.evaluation import evaluate, first_episodes


def _fixed_actor(n_obs, logits):
    linear = torch.nn.Linear(n_obs, len(logits))
    with torch.no_grad():
        linear.weight.zero_()
        linear.bias.copy_(torch.tensor(logits))
    return ProbabilisticActor(
        TensorDictModule(linear, ["observation"], ["logits"]),
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
    )


class TestFirstEpisodes:
    def test_flags_and_unfinished_rows(self):
        rollout = TensorDict(
            {
                "next": {
                    "reward": torch.ones(2, 3, 1),
                    "done": torch.tensor([[0, 1, 0], [0, 0, 0]], dtype=torch.bool)[..., None],
                    "crashed": torch.tensor([[0, 1, 0], [0, 0, 1]], dtype=torch.bool)[..., None],
                }
            },
            batch_size=[2, 3],
        )
        out = first_episodes(rollout, flags=["crashed", "absent"])
        assert out["return"].tolist() == [2.0, 3.0]
        assert out["finished"].tolist() == [True, False]
        assert out["crashed"].tolist() == [True, True]
        assert "absent" not in out


class TestEvaluate:
    def test_greedy_takes_the_mode(self):
        actor = _fixed_actor(1, [0.0, 1.0, 0.5, 0.0])  # argmax is arm 1, paying 0.9
        out = evaluate(actor, BanditEnv(num_arms=4, batch_size=5), episodes=12)
        assert out["mean_return"] == pytest.approx(0.9, abs=1e-6)
        assert out["std_return"] == pytest.approx(0, abs=1e-6)

    def test_sampling(self):
        torch.manual_seed(0)
        actor = _fixed_actor(1, [0.0, 0.0, 0.0, 0.0])
        out = evaluate(actor, BanditEnv(num_arms=4), episodes=400, deterministic=False)
        assert out["mean_return"] == pytest.approx(0.475, abs=0.1)  # (1 + 0.9) / 4

    def test_single_env_counts_whole_episodes(self):
        actor = _fixed_actor(16, [0.0, 0.0, 1.0, 0.0])  # always left: truncated at 7
        out = evaluate(actor, GridWorldEnv(max_steps=7), episodes=3)
        assert out["mean_length"] == 7 and out["mean_return"] == pytest.approx(-0.7)

    def test_at_least_one_episode(self):
        with pytest.raises(ValueError, match="episodes must be an integer >= 1"):
            evaluate(_fixed_actor(1, [0.0, 0.0]), BanditEnv(num_arms=2), episodes=0)

    @pytest.mark.parametrize(
        ("kwargs", "error", "match"),
        [
            ({"max_steps": 0}, ValueError, "max_steps must be an integer >= 1"),
            ({"episodes": 2.0}, TypeError, "episodes must be an integer"),
            ({"deterministic": "no"}, TypeError, "deterministic must be True or False"),
            ({"flags": "crashed"}, TypeError, "flags must be a sequence of names"),
        ],
    )
    def test_bad_arguments(self, kwargs, error, match):
        with pytest.raises(error, match=match):
            evaluate(
                _fixed_actor(1, [0.0, 0.0]), BanditEnv(num_arms=2), **{"episodes": 1, **kwargs}
            )


def test_values_are_read_at_the_end_of_each_first_episode():
    # env 0 ends at step 1 then starts again; env 1 never ends within the rollout.
    done = torch.tensor([[0, 1, 0, 0], [0, 0, 0, 0]], dtype=torch.bool)[..., None]
    progress = torch.tensor([[0.1, 0.4, 0.0, 0.2], [0.1, 0.2, 0.3, 0.5]])[..., None]
    rollout = TensorDict(
        {"next": {"reward": torch.zeros(2, 4, 1), "done": done, "route_completion": progress}},
        batch_size=[2, 4],
    )
    out = first_episodes(rollout, values=["route_completion", "absent"])
    assert torch.allclose(out["route_completion"], torch.tensor([0.4, 0.5]))
    assert "absent" not in out


def test_evaluate_averages_values_and_takes_policies_without_parameters():
    from torchrl.envs.utils import RandomPolicy

    env = GridWorldEnv(batch_size=4)
    result = evaluate(RandomPolicy(env.action_spec), env, episodes=4, values=["reward"])
    assert -1.0 <= result["mean_reward"] <= 1.0  # each episode's last reward: goal, pit or step
    with pytest.raises(ValueError, match="one number per step; 'observation' has 16"):
        evaluate(RandomPolicy(env.action_spec), env, episodes=4, values=["observation"])
    with pytest.raises(TypeError, match="values"):
        evaluate(RandomPolicy(env.action_spec), env, episodes=4, values=[3])
