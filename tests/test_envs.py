"""The torch-native bandit and gridworld."""

from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import check_env_specs

from rl_pg.envs import BanditEnv, GridWorldEnv

UP, DOWN, LEFT, RIGHT = range(4)


def _play(env, actions):
    td = env.reset()
    rewards, dones = [], []
    for action in actions:
        td["action"] = torch.as_tensor(action)
        td = env.step(td)
        rewards.append(td["next", "reward"].item())
        dones.append(td["next", "done"].item())
        td = td["next"]
    return rewards, dones, td


class TestBanditEnv:
    @pytest.mark.parametrize("batch_size", [(), 3, (2, 2)])
    def test_specs(self, batch_size):
        check_env_specs(BanditEnv(num_arms=6, batch_size=batch_size))

    def test_arm_rewards(self):
        env = BanditEnv(num_arms=100)
        assert env.arm_rewards[0] == 1.0
        assert (env.arm_rewards[1:50] == 0.9).all() and (env.arm_rewards[50:] == 0).all()

    def test_every_step_ends_the_episode(self):
        rollout = BanditEnv(batch_size=4).rollout(3, break_when_any_done=False)
        assert rollout["next", "done"].all() and rollout["next", "terminated"].all()

    @pytest.mark.parametrize(
        ("num_arms", "error"), [(1, ValueError), (2.5, TypeError), (True, TypeError)]
    )
    def test_bad_num_arms(self, num_arms, error):
        with pytest.raises(error, match="num_arms must be an integer"):
            BanditEnv(num_arms=num_arms)


class TestGridWorldEnv:
    @pytest.mark.parametrize("batch_size", [(), 5, (2, 3)])
    def test_specs(self, batch_size):
        check_env_specs(GridWorldEnv(batch_size=batch_size))

    def test_shortest_path_earns_the_optimal_return(self):
        env = GridWorldEnv()
        # (3,0) -> up to (1,0) -> right along row 1 is blocked by the pit at (1,2):
        rewards, dones, _ = _play(env, [UP, UP, UP, RIGHT, RIGHT, RIGHT])
        assert dones == [False] * 5 + [True]
        assert sum(rewards) == pytest.approx(env.optimal_return) == pytest.approx(0.5)

    def test_pit_is_terminal(self):
        rewards, dones, td = _play(GridWorldEnv(), [UP, UP, RIGHT, RIGHT])
        assert rewards[-1] == -1.0 and dones[-1] and td["terminated"].item()

    def test_wall_keeps_the_agent_in_place(self):
        _, _, td = _play(GridWorldEnv(), [DOWN, LEFT])
        assert td["cell"].item() == 12

    def test_truncation(self):
        _, dones, td = _play(GridWorldEnv(max_steps=3), [LEFT, LEFT, LEFT])
        assert dones == [False, False, True]
        assert td["truncated"].item() and not td["terminated"].item()

    def test_collector_resets_finished_copies_only(self):
        env = GridWorldEnv(batch_size=16, max_steps=10)
        collector = Collector(env, policy=None, frames_per_batch=16 * 30, total_frames=16 * 30)
        (batch,) = list(collector)
        collector.shutdown()
        # After a done, that copy starts again from the start cell, the others go on.
        done = batch["next", "done"].squeeze(-1)
        after = batch["cell"][:, 1:][done[:, :-1]]
        assert (after == env.start).all()
        assert batch["step_count"].max() <= 9

    @pytest.mark.parametrize(
        ("kwargs", "message"),
        [
            ({"size": 1}, "size must be an integer >= 2"),
            ({"goal": (4, 0)}, r"goal=\(4, 0\) is not a cell of a 4x4 grid"),
            ({"pit": (3, 0)}, "start, goal and pit must differ"),
            ({"max_steps": 0}, "max_steps must be an integer >= 1"),
            ({"step_reward": float("nan")}, "step_reward must be a finite number"),
            ({"start": (0,)}, r"start must be a \(row, column\) pair"),
            ({"batch_size": 0}, r"batch_size\[0\] must be an integer >= 1"),
        ],
    )
    def test_bad_layouts(self, kwargs, message):
        with pytest.raises(ValueError, match=message):
            GridWorldEnv(**kwargs)

    @pytest.mark.parametrize("kwargs", [{"start": (0.5, 0)}, {"size": 4.0}, {"batch_size": (2.5,)}])
    def test_layouts_of_the_wrong_kind(self, kwargs):
        with pytest.raises(TypeError, match="must be an integer"):
            GridWorldEnv(**kwargs)

    def test_optimal_return_goes_around_the_pit(self):
        env = GridWorldEnv(size=3, start=(0, 0), goal=(0, 2), pit=(0, 1))
        assert env.optimal_return == pytest.approx(1.0 - 0.1 * 3)  # 4 moves around it
