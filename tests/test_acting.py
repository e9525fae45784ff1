"""The two-line load-and-act API: ``Agent.load(...)`` then ``agent.act(observation)`` on
the environment's own observations and actions (gymnasium's), one or a batch."""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rl_pg.app import Agent
from rl_pg.checkpoint import CheckpointError
from rl_pg.envs.gym import DRIVING_ACTIONS
from rl_pg.frame_difference import FrameDifference


@pytest.fixture(scope="module")
def cartpole():
    return Agent.load("cartpole", pretrained=True)


def _greedy_index(agent: Agent, observation: torch.Tensor, batch=(), **entries) -> torch.Tensor:
    """The policy's own greedy action on an observation entry, and any other entries it
    reads (the TorchRL way)."""
    data = TensorDict({"observation": observation, **entries}, batch_size=batch)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        return agent.policy(data)["action"]


def test_a_batch_of_observations_gets_one_action_each(cartpole):
    envs = gym.make_vec("CartPole-v1", num_envs=3, vectorization_mode="sync")
    observations, _ = envs.reset(seed=3)
    actions = cartpole.act(observations)
    assert isinstance(actions, np.ndarray) and actions.shape == (3,)
    assert list(actions) == [cartpole.act(o) for o in observations]  # the same one by one
    envs.step(actions)  # what the vector environment takes


def test_the_action_is_the_policys_and_sampling_draws_from_it(cartpole):
    observation = np.array([0.02, 0.3, -0.05, -0.6], dtype=np.float32)
    greedy = _greedy_index(cartpole, torch.as_tensor(observation)).item()
    assert cartpole.act(observation) == greedy
    # Near balance the policy hesitates: over many draws both actions show up.
    torch.manual_seed(0)
    draws = {cartpole.act(np.zeros(4, dtype=np.float32), sample=True) for _ in range(200)}
    assert draws == {0, 1}


def test_a_tensordict_is_acted_on_the_torchrl_way(cartpole):
    env = cartpole.make_env()
    data = cartpole.act(env.reset())
    assert data["action"].item() == _greedy_index(cartpole, data["observation"]).item()
    env.close()


def test_an_observation_of_the_wrong_shape_is_refused_naming_the_expected_one(cartpole):
    with pytest.raises(ValueError, match=r"shape \(4,\).*'observation'.*got \(3,\)"):
        cartpole.act(np.zeros(3, dtype=np.float32))


def test_a_driving_agent_gives_the_action_vector_its_environment_takes():
    pytest.importorskip("highway_env")
    agent = Agent.load("highway", pretrained=True)
    observation = np.random.default_rng(0).uniform(-1, 1, (5, 5)).astype(np.float32)
    action = agent.act(observation)
    index = _greedy_index(agent, torch.as_tensor(observation)).item()
    assert action.shape == (2,) and list(action) == pytest.approx(DRIVING_ACTIONS[index])


def test_a_frame_difference_agent_remembers_the_frame_before_until_reset():
    pytest.importorskip("ale_py")
    agent = Agent.load("pong", pretrained=True)
    rng = np.random.default_rng(0)
    frames = [rng.choice([144, 236], size=(210, 160, 3)).astype(np.uint8) for _ in range(3)]
    processed = [FrameDifference.process(torch.as_tensor(f)) for f in frames]
    expected = [torch.zeros(6400)] + [(b - a).flatten() for a, b in itertools.pairwise(processed)]
    # the shipped policy also sees the frame itself (--frame), kept as previous_frame
    for frame, now, difference in zip(frames, processed, expected, strict=True):
        assert agent.act(frame) == _greedy_index(agent, difference, previous_frame=now).item()
    agent.reset()  # a new episode: its first frame has no frame before it
    first = _greedy_index(agent, torch.zeros(6400), previous_frame=processed[2]).item()
    assert agent.act(frames[2]) == first


def test_loading_nothing_says_what_to_give(tmp_path):
    with pytest.raises(Exception, match="does not exist"):
        Agent.load(tmp_path / "missing")
    with pytest.raises(ValueError, match="No agent is shipped"):
        Agent.load("nothing", pretrained=True)
    for source in (None, 3, ""):
        with pytest.raises(TypeError, match="An agent's source is a run directory"):
            Agent.load(source)
    with pytest.raises(CheckpointError, match=r"holds no best.pt: not a run directory"):
        Agent.load(tmp_path)
    (tmp_path / "empty.pt").touch()
    with pytest.raises(CheckpointError, match=r"empty.pt is corrupted: the file is empty"):
        Agent.load(tmp_path / "empty.pt")


def test_a_recipes_name_without_pretrained_points_to_its_shipped_agent(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # where no folder is called cartpole
    with pytest.raises(CheckpointError, match=r"pretrained=True\)"):
        Agent.load("cartpole")


def test_what_an_agent_cannot_act_on_is_named(cartpole):
    observation, info = gym.make("CartPole-v1").reset(seed=0)
    with pytest.raises(ValueError, match=r"an \(observation, info\) pair.*obs, info = env"):
        cartpole.act((observation, info))
    for bad in (np.nan, np.inf):  # a meaningless action is not returned
        with pytest.raises(ValueError, match="holds 1 NaN or infinite value"):
            cartpole.act(np.array([0.0, bad, 0.0, 0.0], dtype=np.float32))
    with pytest.raises(TypeError, match="sample must be True or False, got 'yes'"):
        cartpole.act(observation, sample="yes")
    with pytest.raises(ValueError, match=r"reads numbers under 'observation', got str \(can't"):
        cartpole.act("left")


@pytest.mark.parametrize(
    ("name", "observation"), [("bandit", [1.0]), ("gridworld", np.eye(16)[12])]
)
def test_agents_of_batched_torch_native_environments_act_on_one_observation(name, observation):
    # Their environments step several copies at once: an observation is one copy's.
    agent = Agent.load(name, pretrained=True)
    action = agent.act(np.asarray(observation, dtype=np.float32))
    assert isinstance(action, int)
    assert agent.act(np.stack([observation] * 3).astype(np.float32)).tolist() == [action] * 3
    if name == "gridworld":  # from the start, the trained agent heads up or right
        assert action in (0, 3)
