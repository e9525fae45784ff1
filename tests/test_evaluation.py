"""Evaluation over whole episodes."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import Binary, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor

from rl_pg.envs import BanditEnv, GridWorldEnv
from rl_pg.episode_workers import EpisodeWorkers
from rl_pg.evaluation import EpisodeRequest, evaluate, first_episodes


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
        env = BanditEnv(num_arms=4)
        out = evaluate(actor, env, episodes=400, deterministic=False)
        rewards = env.arm_rewards.double()  # uniform over the arms: 1, 0.9, 0, 0
        mean, sd = rewards.mean().item(), rewards.std(unbiased=False).item()
        assert mean == pytest.approx(0.475)
        assert abs(out["mean_return"] - mean) < 4 * sd / 400**0.5  # 4 standard errors

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
    torch.manual_seed(0)
    result = evaluate(RandomPolicy(env.action_spec), env, episodes=8, values=["reward"])
    # Every step but an episode's last earns step_reward (-0.1), so the last rewards the
    # value reads average to the mean return less (mean length - 1) steps of it.
    last = result["mean_return"] - (result["mean_length"] - 1) * -0.1
    assert result["mean_reward"] == pytest.approx(last, abs=1e-5)
    assert result["mean_reward"] != pytest.approx(-0.1)  # some episodes ended in goal or pit
    with pytest.raises(ValueError, match="one number per step; 'observation' has 16"):
        evaluate(RandomPolicy(env.action_spec), env, episodes=4, values=["observation"])
    with pytest.raises(TypeError, match="values"):
        evaluate(RandomPolicy(env.action_spec), env, episodes=4, values=[3])


class _Scenarios(EnvBase):
    """Walks through scenarios ``first, first + 1, ...``, one per reset; scenario ``k``
    lasts ``1 + k % 4`` steps, pays ``k`` per step and is "odd" when ``k`` is."""

    def __init__(self, first: int):
        super().__init__()
        self.next_scenario, self.scenario, self.t = first, -1, 0
        flag = Binary(1, shape=(1,), dtype=torch.bool)
        self.observation_spec = Composite(observation=Unbounded(shape=(1,)), odd=flag)
        self.action_spec = Categorical(2, shape=())
        self.reward_spec = Unbounded(shape=(1,))
        self.full_done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone())

    def _reset(self, tensordict):
        self.scenario, self.t = self.next_scenario, 0
        self.next_scenario += 1
        return TensorDict(
            {"observation": torch.zeros(1), "done": torch.zeros(1, dtype=torch.bool),
             "terminated": torch.zeros(1, dtype=torch.bool),
             "truncated": torch.zeros(1, dtype=torch.bool),
             "odd": torch.zeros(1, dtype=torch.bool)},
        )  # fmt: skip

    def _step(self, tensordict):
        self.t += 1
        k = self.scenario
        done = torch.tensor([self.t == 1 + k % 4])
        return TensorDict(
            {"observation": torch.full((1,), float(self.t)), "reward": torch.full((1,), float(k)),
             "done": done, "terminated": done, "truncated": torch.zeros(1, dtype=torch.bool),
             "odd": done & (k % 2 == 1)},
        )  # fmt: skip

    def _set_seed(self, seed):
        return seed


def _raise():
    raise ValueError("no such scenario set")


@pytest.mark.parametrize(
    ("batched", "max_steps", "lengths"),  # scenarios 0, 1, 2 and 10, 11
    [
        ("serial", 100, [1, 2, 3, 3, 4]),
        ("serial", 2, [1, 2, 2, 2, 2]),
        ("processes", 100, [1, 2, 3, 3, 4]),
        # processes cutting episodes at max_steps: in the next test
    ],
)
def test_a_batched_env_plays_each_environments_share_in_order_skipping_nothing(
    batched, max_steps, lengths
):
    from functools import partial

    from torchrl.envs import SerialEnv
    from torchrl.envs.utils import RandomPolicy

    makers = [partial(_Scenarios, 0), partial(_Scenarios, 10)]
    env = SerialEnv(2, makers) if batched == "serial" else EpisodeWorkers(makers)
    scenarios = [0, 1, 2, 10, 11]  # env 0 plays 3 of the 5 episodes, env 1 plays 2
    try:
        out = evaluate(RandomPolicy(env.action_spec), env, episodes=5, max_steps=max_steps,
                       flags=["odd"])  # fmt: skip
    finally:
        env.close()
    assert out["mean_length"] == pytest.approx(sum(lengths) / 5)
    returns = [k * n for k, n in zip(scenarios, lengths, strict=True)]
    assert out["mean_return"] == pytest.approx(sum(returns) / 5)
    assert out["odd_rate"] == pytest.approx(0.4 if max_steps == 100 else 0.2)  # 11 is cut


def test_episode_workers_keep_their_environments_and_report_a_worker_s_failure():
    from functools import partial

    env = EpisodeWorkers([partial(_Scenarios, 0), partial(_Scenarios, 10)])
    policy = _fixed_actor(1, [0.0, 1.0])
    try:
        first = evaluate(policy, env, episodes=2)  # scenarios 0 and 10
        # 1 and 11 (4 steps, cut at 2): the same processes go on
        second = evaluate(policy, env, episodes=2, max_steps=2)
    finally:
        env.close()
    assert (first["mean_return"], second["mean_return"]) == ((0 + 10 * 3) / 2, (1 * 2 + 11 * 2) / 2)
    assert second["mean_length"] == 2
    assert env.is_closed
    broken = EpisodeWorkers([partial(_Scenarios, 0), _raise])
    with pytest.raises(RuntimeError, match=r"worker 1 failed:(.|\n)*no such scenario set"):
        evaluate(policy, broken, episodes=2)
    assert broken.is_closed
    with pytest.raises(TypeError, match="make_envs must be"):
        EpisodeWorkers([])


def test_episode_workers_on_ray_actors_play_each_share_in_order_and_report_a_failure(local_ray):
    """As worker processes do (the test above), on a local Ray instance as a training's
    --ray starts one; a failure in an actor names it, and closes the actors."""
    import sys
    from functools import partial

    from torchrl.envs.utils import RandomPolicy

    ray = local_ray

    def fail(td):
        raise ValueError("no such scenario set")

    # The actors cannot import this test module: its environments travel by value.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        env = EpisodeWorkers([partial(_Scenarios, 0), partial(_Scenarios, 10)], backend="ray")
        out = evaluate(RandomPolicy(env.action_spec), env, episodes=5, flags=["odd"])
        lengths, scenarios = [1, 2, 3, 3, 4], [0, 1, 2, 10, 11]  # as the processes play them
        assert out["mean_length"] == pytest.approx(sum(lengths) / 5)
        returns = [k * n for k, n in zip(scenarios, lengths, strict=True)]
        assert out["mean_return"] == pytest.approx(sum(returns) / 5)
        assert out["odd_rate"] == pytest.approx(0.4)
        assert env.nodes == [ray.get_runtime_context().get_node_id()] * 2  # one node here
        with pytest.raises(RuntimeError, match=r"a Ray actor\) failed:(.|\n)*no such scenario"):
            evaluate(TensorDictModule(fail, ["observation"], ["action"]), env, episodes=2)
        assert env.is_closed and ray.is_initialized()  # Ray stays: these did not start it
        alone = EpisodeWorkers([partial(_Scenarios, 3)], backend="ray")  # a single actor
        out = evaluate(RandomPolicy(alone.action_spec), alone, episodes=2)
        assert out["mean_return"] == pytest.approx((3 * 4 + 4 * 1) / 2)  # scenarios 3, 4
        alone.close()
    finally:
        ray.cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    with pytest.raises(ValueError, match="backend must be 'process' or 'ray'"):
        EpisodeWorkers([partial(_Scenarios, 0)], backend="threads")


def test_episode_workers_spawn_unless_a_start_method_is_set(monkeypatch):
    # The suite's workers fork from a forkserver (conftest.py); a user who set no start
    # method gets spawned processes, which import everything afresh.
    import multiprocessing
    from functools import partial

    # As multiprocessing's own with no method set: None if asked so, else it fixes its
    # platform default (fork on Linux) and returns that.
    monkeypatch.setattr(
        multiprocessing, "get_start_method", lambda allow_none=False: None if allow_none else "fork"
    )
    env = EpisodeWorkers([partial(_Scenarios, 10)])
    try:
        result = evaluate(_fixed_actor(1, [0.0, 1.0]), env, episodes=1)  # scenario 10
        assert type(env._workers[0][0]).__name__ == "SpawnProcess"
    finally:
        env.close()
    assert result["mean_return"] == 10 * 3


def _first_step_policy():
    """Greedily plays action 0 at an episode's first step (observation 0) and 1 after
    (``_Scenarios`` observes the steps taken): logits ``[0.5 - t, t]``."""
    linear = torch.nn.Linear(1, 2)
    with torch.no_grad():
        linear.weight.copy_(torch.tensor([[-1.0], [1.0]]))
        linear.bias.copy_(torch.tensor([0.5, 0.0]))
    return ProbabilisticActor(
        TensorDictModule(linear, ["observation"], ["logits"]),
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
    )


@pytest.mark.parametrize("batched", ["single", "serial", "processes"])
def test_action_stats_count_each_episode_apart(batched):
    from functools import partial

    from torchrl.envs import SerialEnv

    makers = [partial(_Scenarios, 0), partial(_Scenarios, 10)]
    if batched == "single":
        env, lengths = _Scenarios(0), [1, 2, 3]  # scenarios 0, 1, 2
    else:
        env = SerialEnv(2, makers) if batched == "serial" else EpisodeWorkers(makers)
        lengths = [1, 2, 3, 3, 4]  # scenarios 0, 1, 2 and 10, 11
    try:
        out = evaluate(_first_step_policy(), env, episodes=len(lengths), action_stats=True)
    finally:
        env.close()
    # A plain count: each episode plays 0 once, then 1; it switches once if it lasts 2+.
    steps = sum(lengths)
    assert out["action_shares"] == pytest.approx([len(lengths) / steps, 1 - len(lengths) / steps])
    switches = sum(n >= 2 for n in lengths)  # none across episodes: each starts with 0 again
    assert out["action_switch_rate"] == pytest.approx(switches / (steps - len(lengths)))
    assert out["greedy_action_rate"] == 1.0
    t = torch.tensor([float(i) for n in lengths for i in range(n)])
    logits = torch.stack([0.5 - t, t], -1)
    expected = torch.distributions.Categorical(logits=logits).entropy().mean()
    assert out["mean_entropy"] == pytest.approx(expected.item(), rel=1e-5)


def test_action_stats_of_a_sampling_policy_and_of_a_policy_without_logits():
    from torchrl.envs.utils import RandomPolicy

    torch.manual_seed(0)
    env = GridWorldEnv(batch_size=4, max_steps=50)
    out = evaluate(_fixed_actor(16, [2.0, 0.0, 0.0, 0.0]), env, episodes=8,
                   deterministic=False, action_stats=True)  # fmt: skip
    p = torch.softmax(torch.tensor([2.0, 0.0, 0.0, 0.0]), 0)
    steps = round(out["mean_length"] * 8)  # every action is an independent draw from p
    greedy, switch = p[0].item(), 1 - (p**2).sum().item()
    se = (greedy * (1 - greedy) / steps) ** 0.5
    assert abs(out["greedy_action_rate"] - greedy) < 4 * se  # 4 standard errors
    assert out["action_shares"][0] == out["greedy_action_rate"]
    se = (switch * (1 - switch) / (steps - 8)) ** 0.5  # pairs within episodes
    assert abs(out["action_switch_rate"] - switch) < 4 * se
    entropy = torch.distributions.Categorical(probs=p).entropy().item()
    assert out["mean_entropy"] == pytest.approx(entropy, rel=1e-5)
    plain = evaluate(RandomPolicy(env.action_spec), env, episodes=4, action_stats=True)
    assert "action_shares" not in plain
    with pytest.raises(TypeError, match="action_stats must be True or False"):
        evaluate(RandomPolicy(env.action_spec), env, episodes=4, action_stats=1)


def test_episode_workers_repeat_a_sampled_evaluation_from_its_seed():
    from functools import partial

    env = EpisodeWorkers([partial(GridWorldEnv, max_steps=30)] * 2)
    policy = _fixed_actor(16, [0.0, 0.0, 0.0, 0.0])  # uniform: every step is a draw
    try:
        results = []
        for _ in range(2):  # the same processes, their random streams moved on
            env.set_seed(7)
            results.append(evaluate(policy, env, episodes=20, deterministic=False,
                                    action_stats=True))  # fmt: skip
        env.set_seed(8)
        other = evaluate(policy, env, episodes=20, deterministic=False, action_stats=True)
        # Each process plays episodes of its own: seeded alike, the two would repeat
        # each other's 10 episodes, step for step.
        env.set_seed(7)
        lengths = env.play(policy, EpisodeRequest(20, False, 30, [], []))["length"]
    finally:
        env.close()
    assert results[0] == results[1]
    assert other["action_shares"] != results[0]["action_shares"]
    assert lengths[:10].tolist() != lengths[10:].tolist()


def test_process_i_plays_from_the_seed_plus_i():
    # What set_seed documents: the second process of two seeded with 7 plays the episodes
    # a lone process seeded with 8 plays.
    from functools import partial

    make = partial(GridWorldEnv, max_steps=30)
    policy = _fixed_actor(16, [0.0, 0.0, 0.0, 0.0])  # uniform: every step is a draw
    request = EpisodeRequest(10, False, 30, [], [])
    pair, alone = EpisodeWorkers([make] * 2), EpisodeWorkers([make])
    try:
        pair.set_seed(7)
        both = pair.play(policy, request._replace(episodes=20))
        alone.set_seed(8)
        second = alone.play(policy, request)
    finally:
        pair.close()
        alone.close()
    assert both["length"][10:].tolist() == second["length"].tolist()
    assert both["return"][10:].tolist() == second["return"].tolist()


def test_workers_dropped_without_closing_are_stopped():
    import gc

    env = EpisodeWorkers([GridWorldEnv])
    _ = env.batch_size  # starts the process
    ((process, _),) = env._workers
    del env
    gc.collect()
    process.join(timeout=30)
    assert not process.is_alive()


def test_only_the_ray_backend_asks_for_ray(monkeypatch):
    asked = []
    monkeypatch.setattr("rl_pg.episode_workers.require_extra", lambda *args: asked.append(args[0]))
    EpisodeWorkers([GridWorldEnv])
    assert asked == []
    EpisodeWorkers([GridWorldEnv], backend="ray")
    assert asked == ["ray"]


def test_action_stats_read_one_hot_actions():
    from torchrl.envs import GymEnv
    from torchrl.modules import OneHotCategorical

    env = GymEnv("CartPole-v1", categorical_action_encoding=False)  # one-hot actions
    linear = torch.nn.Linear(4, 2)
    with torch.no_grad():
        linear.weight.zero_()
        linear.bias.copy_(torch.tensor([0.0, 3.0]))
    actor = ProbabilisticActor(
        TensorDictModule(linear, ["observation"], ["logits"]),
        in_keys=["logits"],
        distribution_class=OneHotCategorical,
        spec=env.action_spec,
    )
    out = evaluate(actor, env, episodes=2, action_stats=True)  # always pushes right
    assert out["action_shares"] == [0.0, 1.0]
    assert out["action_switch_rate"] == 0.0 and out["greedy_action_rate"] == 1.0


def test_a_fixed_set_of_episodes_is_never_played_twice_in_one_evaluation():
    from functools import partial

    env = EpisodeWorkers([partial(_Scenarios, 0), partial(_Scenarios, 10)], distinct_episodes=5)
    policy = _fixed_actor(1, [0.0, 1.0])
    with pytest.raises(ValueError, match=r"fixed set of 5 episodes.*6 would play 1 of them twice"):
        evaluate(policy, env, episodes=6)
    assert env.is_closed  # refused before any process started
    with pytest.raises(ValueError, match="distinct_episodes must be an integer >= 2"):
        EpisodeWorkers([partial(_Scenarios, 0), partial(_Scenarios, 10)], distinct_episodes=1)
    try:
        assert evaluate(policy, env, episodes=5)["mean_length"] > 0  # the whole set: fine
    finally:
        env.close()
