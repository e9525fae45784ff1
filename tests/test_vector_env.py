"""``rl_pg.envs.VectorGymEnv``: gymnasium vector environments as a lean TorchRL env."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import GymWrapper, check_env_specs
from torchrl.envs.utils import RandomPolicy

from rl_pg.envs import EnvPoolEnv, VectorGymEnv, gym_env

DISABLED = {"autoreset_mode": gym.vector.AutoresetMode.DISABLED}


def _vector(env_id: str, n: int, **kwargs) -> gym.vector.VectorEnv:
    return gym.make_vec(
        env_id, num_envs=n, vectorization_mode="sync", vector_kwargs=DISABLED, **kwargs
    )


def _collect(env, seed: int, batches: int = 3, frames: int = 240):
    """Batches a collector gathers from ``env`` with a seeded uniformly random policy."""
    torch.manual_seed(seed)
    collector = Collector(
        env,
        RandomPolicy(env.action_spec),
        frames_per_batch=frames,
        total_frames=-1,
        auto_register_policy_transforms=False,
    )
    collector.set_seed(seed)
    collector.reset()
    batches = [b.clone() for _, b in zip(range(batches), collector, strict=False)]
    collector.shutdown()
    return torch.cat(batches, dim=-1)


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [
        ("CartPole-v1", {}),  # terminations every few steps: many partial resets
        ("Pendulum-v1", {"max_episode_steps": 50}),  # truncations, continuous actions
        ("LunarLander-v3", {"continuous": True}),  # Box(-1, 1, (2,)) actions
    ],
)
def test_same_data_as_torchrl_gym_wrapper(env_id, kwargs):
    """Same specs, same keys, same values, step for step, as TorchRL's GymWrapper."""
    ours = VectorGymEnv(_vector(env_id, 4, **kwargs))
    theirs = GymWrapper(_vector(env_id, 4, **kwargs), categorical_action_encoding=True)
    assert ours.observation_spec == theirs.observation_spec
    assert ours.action_spec == theirs.action_spec
    assert ours.full_done_spec == theirs.full_done_spec
    assert ours.reward_spec == theirs.reward_spec
    a, b = _collect(ours, seed=3), _collect(theirs, seed=3)
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in b.keys(True, True):
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=f"entry {key}")
    assert a["next", "done"].any()  # the comparison crossed episode ends


def _cartpoles(backend: str, n: int):
    if backend == "envpool":
        pytest.importorskip("envpool")
    return gym_env("CartPole-v1", num_envs=n, backend=backend)


BACKENDS = ["gymnasium", "envpool"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_final_observation_kept_and_only_finished_envs_reset(backend):
    """At a step that ends an episode, ``next`` holds that episode's last observation;
    the next root holds the reset one, and the other environments are not reset."""
    env = _cartpoles(backend, 3)
    env.set_seed(0)
    td = env.reset()
    always_left = torch.zeros(3, dtype=torch.long)
    for _ in range(100):
        td["action"] = always_left
        stepped, root = env.step_and_maybe_reset(td)
        done = stepped["next", "done"].squeeze(-1)
        if done.any():
            break
        td = root
    assert done.any() and not done.all()
    final = stepped["next", "observation"]
    assert (final[done, 2].abs() > 0.2).all()  # the pole fell: the final state
    assert (root["observation"][done].abs() <= 0.05).all()  # a fresh start
    torch.testing.assert_close(root["observation"][~done], final[~done], rtol=0, atol=0)
    assert not root["done"].any() and not root["terminated"].any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_specs_pass_torchrl_checks_and_seeding_is_reproducible(backend):
    env = _cartpoles(backend, 5)
    check_env_specs(env)
    first = _collect(env, seed=11, batches=1)
    again = _collect(env, seed=11, batches=1)
    other = _collect(env, seed=12, batches=1)
    assert torch.equal(first["observation"], again["observation"])
    assert not torch.equal(first["observation"], other["observation"])


class _DictObsEnv(gym.Env):
    """Two observation entries; ends after ``length`` steps."""

    def __init__(self, length: int = 3):
        self.observation_space = gym.spaces.Dict(
            {
                "position": gym.spaces.Box(-10, 10, (2,), np.float32),
                "count": gym.spaces.Box(0, 100, (), np.int64),
            }
        )
        self.action_space = gym.spaces.Discrete(3)
        self.length = length

    def _obs(self):
        return {"position": np.full(2, self.t, np.float32), "count": np.int64(self.t)}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        return self._obs(), float(action), self.t >= self.length, False, {}


def test_dict_observations_are_read_under_their_keys():
    vector = gym.vector.SyncVectorEnv([_DictObsEnv] * 2, autoreset_mode=DISABLED["autoreset_mode"])
    env = VectorGymEnv(vector)
    check_env_specs(env)
    assert set(env.observation_spec.keys()) == {"position", "count"}
    rollout = env.rollout(4, break_when_any_done=False)
    assert rollout["next", "count"].squeeze(-1).tolist() == [[1, 2, 3, 1]] * 2  # shape [1]
    assert rollout["next", "position"].dtype == torch.float32
    assert rollout["next", "done"].squeeze(-1).tolist() == [[False, False, True, False]] * 2


@pytest.mark.parametrize(
    "make",
    [
        lambda: _vector("CartPole-v1", 6),  # terminations: several resets at one step
        lambda: _vector("Pendulum-v1", 3, max_episode_steps=30),  # truncations
        lambda: gym.vector.SyncVectorEnv(
            [_DictObsEnv] * 2, autoreset_mode=DISABLED["autoreset_mode"]
        ),
    ],
    ids=["cartpole", "pendulum", "dict"],
)
def test_resetting_finished_environments_in_place_is_gymnasiums_masked_reset(make):
    """A SyncVectorEnv's finished environments are reset by VectorGymEnv itself (the
    sub-environments' own resets); the data are those of gymnasium's masked reset."""
    direct, masked = VectorGymEnv(make()), VectorGymEnv(make())
    assert direct._resets_directly
    masked._resets_directly = False
    a, b = _collect(direct, seed=5), _collect(masked, seed=5)
    assert a["next", "done"].sum() >= 6  # many steps reset some environments
    for key in b.keys(True, True):
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=f"entry {key}")


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_a_vector_env_that_reuses_its_buffers_gives_the_same_data(mode):
    """copy=False: gymnasium hands back one buffer, overwritten at every step (and, for
    a synchronous env, at every reset); the batches must still hold each step's own."""
    kwargs = {"vectorization_mode": mode, "num_envs": 3}
    copied = VectorGymEnv(gym.make_vec("CartPole-v1", vector_kwargs=DISABLED, **kwargs))
    shared = VectorGymEnv(
        gym.make_vec("CartPole-v1", vector_kwargs={**DISABLED, "copy": False}, **kwargs)
    )
    try:
        a, b = _collect(copied, seed=2, batches=2), _collect(shared, seed=2, batches=2)
        assert a["next", "done"].any()
        for key in a.keys(True, True):
            torch.testing.assert_close(b[key], a[key], rtol=0, atol=0, msg=f"entry {key}")
    finally:
        copied.close()
        shared.close()


def test_other_vector_environments_reset_through_gymnasium():
    wrapped = gym.wrappers.vector.RecordEpisodeStatistics(_vector("CartPole-v1", 2))
    asynchronous = gym.make_vec(
        "CartPole-v1", num_envs=2, vectorization_mode="async", vector_kwargs=DISABLED
    )
    try:
        for vector in (wrapped, asynchronous):
            env = VectorGymEnv(vector)
            assert not env._resets_directly
            rollout = env.rollout(40, break_when_any_done=False)
            assert rollout["next", "done"].any() and not rollout[..., 1:]["done"].any()
    finally:
        asynchronous.close()


def test_bad_environments_are_refused_with_the_fix():
    with pytest.raises(TypeError, match=r"gymnasium\.vector\.VectorEnv.*make_vec"):
        VectorGymEnv(gym.make("CartPole-v1"))
    autoreset = gym.make_vec("CartPole-v1", num_envs=2, vectorization_mode="sync")
    with pytest.raises(ValueError, match=r"AutoresetMode\.DISABLED"):
        VectorGymEnv(autoreset)
    tuple_obs = gym.vector.SyncVectorEnv(
        [lambda: gym.make("Blackjack-v1")], autoreset_mode=DISABLED["autoreset_mode"]
    )
    with pytest.raises(TypeError, match=r"Box or Dict observations.*Tuple"):
        VectorGymEnv(tuple_obs)


def test_close_closes_the_gymnasium_environments():
    vector = _vector("CartPole-v1", 2)
    env = VectorGymEnv(vector)
    env.close()
    assert env.is_closed and vector.closed


def test_gym_env_builds_it_for_several_environments():
    assert isinstance(gym_env("CartPole-v1", num_envs=3), VectorGymEnv)
    assert not isinstance(gym_env("CartPole-v1"), VectorGymEnv)


@pytest.mark.parametrize("groups", [1, 2])
@pytest.mark.parametrize("env_id", ["CartPole-v1", "LunarLander-v3", "Pendulum-v1"])
def test_envpool_has_the_specs_of_gymnasium(env_id, groups):
    pytest.importorskip("envpool")
    with warnings.catch_warnings(record=True) as caught:  # nothing for a user to act on
        warnings.simplefilter("always", UserWarning)  # what a user sees by default
        ours = gym_env(env_id, num_envs=3, backend="envpool", groups=groups)
        ours.set_seed(1)  # builds its pools again
        ours.rollout(3)
    assert not [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    reference = gym_env(env_id, num_envs=3)
    assert isinstance(ours, EnvPoolEnv)
    assert ours.observation_spec == reference.observation_spec
    assert ours.action_spec == reference.action_spec
    assert ours.full_done_spec == reference.full_done_spec


def test_envpool_spends_no_step_on_its_own_resets():
    """EnvPool resets an environment at the step after its end (reward 0, action
    ignored); EnvPoolEnv resets it at once, so every CartPole step earns its 1."""
    pytest.importorskip("envpool")
    env = gym_env("CartPole-v1", num_envs=4, backend="envpool")
    steps = _collect(env, seed=0, batches=2, frames=400)
    assert steps["next", "done"].sum() > 10  # many episodes ended
    assert (steps["next", "reward"] == 1).all()
    length = torch.zeros(4)
    for t in range(steps.shape[-1]):  # episodes start at the cart's rest position
        length += 1
        assert (steps["observation"][:, t].abs()[length == 1] <= 0.05).all()
        length[steps["next", "done"][:, t, 0]] = 0


def test_envpool_errors_name_the_fix():
    pytest.importorskip("envpool")
    with pytest.raises(ValueError, match="EnvPool has no task 'NoSuchEnv-v0'"):
        gym_env("NoSuchEnv-v0", num_envs=2, backend="envpool")
    with pytest.raises(ValueError, match="give num_envs"):
        gym_env("CartPole-v1", backend="envpool")
    with pytest.raises(ValueError, match="backend must be 'gymnasium' or 'envpool'"):
        gym_env("CartPole-v1", num_envs=2, backend="gym")


@pytest.mark.parametrize(
    ("task_id", "steps"),
    [
        ("CartPole-v1", 120),  # many terminations
        ("LunarLanderContinuous-v3", 60),  # float actions
        ("Pong-v5", 30),  # image observations, extra info arrays
    ],
)
def test_envpool_steps_through_its_arrays_as_through_its_api(task_id, steps):
    """EnvPoolEnv reads and writes EnvPool's arrays directly; every step (observations,
    rewards, terminations, truncations, partial resets) is what EnvPool's gymnasium API
    gives for the same actions."""
    pytest.importorskip("envpool")
    import envpool

    from rl_pg.envs.envpool import _direct_layout

    env = EnvPoolEnv(task_id, num_envs=3, max_episode_steps=25)  # seeds 0, 1, 2
    assert env._env._direct[0] is not None  # the direct path is the one under test
    api = envpool.make_gymnasium(task_id, num_envs=3, seed=0, max_episode_steps=25)
    obs, _ = api.reset()
    root = env.reset()
    torch.testing.assert_close(root["observation"], torch.as_tensor(obs), rtol=0, atol=0)
    ended = 0
    for _ in range(steps):
        action = env.action_spec.rand().numpy()
        step, root = env.step_and_maybe_reset(root.set("action", torch.as_tensor(action)))
        obs, reward, terminated, truncated, _ = api.step(action)
        for key, expected in (
            (("next", "observation"), obs),
            (("next", "reward"), reward.reshape(3, 1)),
            (("next", "terminated"), terminated.reshape(3, 1)),
            (("next", "truncated"), truncated.reshape(3, 1)),
        ):
            torch.testing.assert_close(
                step[key], torch.as_tensor(expected).to(step[key].dtype), rtol=0, atol=0
            )
        done = terminated | truncated
        if done.any():  # EnvPoolEnv reset those at once: so does the reference
            ended += int(done.sum())
            fresh, _ = api.reset(np.flatnonzero(done).astype(np.int32))
            obs = obs.copy()
            obs[done] = fresh
        torch.testing.assert_close(root["observation"], torch.as_tensor(obs), rtol=0, atol=0)
    assert ended > 0  # the comparison crossed episode ends
    assert _direct_layout(gym.make_vec("CartPole-v1", num_envs=2)) is None  # not a pool


def test_a_reset_seeds_each_environment_with_its_own_seed():
    env = gym_env("CartPole-v1", num_envs=4)
    first = env.reset(seed=[7, 7, 9, 7])["observation"]
    assert torch.equal(first[0], first[1]) and torch.equal(first[0], first[3])
    assert not torch.equal(first[0], first[2])
    alone = gym_env("CartPole-v1", num_envs=1).reset(seed=[9])["observation"]
    assert torch.equal(alone[0], first[2])
    with pytest.raises(ValueError, match=r"one non-negative integer per environment \(4\)"):
        env.reset(seed=[1, 2])
    with pytest.raises(ValueError, match="takes a non-negative integer"):
        env.reset(seed=-1)


def test_envpool_refuses_a_seed_per_environment():
    pytest.importorskip("envpool")
    env = gym_env("CartPole-v1", num_envs=2, backend="envpool")
    with pytest.raises(ValueError, match="cannot reset them with a seed each"):
        env.reset(seed=[1, 1])
