"""rl_pg.models: policies and critics sized and bounded by the environment's specs."""

from __future__ import annotations

import copy
import math
import pickle

import gymnasium as gym
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import GymWrapper
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ConvNet, IndependentNormal, ProbabilisticActor, TanhNormal

from rl_pg import ReinforceLoss
from rl_pg.distributions import BoundedBeta
from rl_pg.envs import GridWorldEnv, gym_env
from rl_pg.lean import (
    DirectSequential,
    LeanCategoricalActor,
    LeanCategoricalPolicy,
    direct_network,
    lean_policy,
    sample_categorical,
)
from rl_pg.models import mlp_actor, mlp_actor_critic, mlp_critic
from rl_pg.normalization import RunningNorm, update_running_norms


class _BoxEnv(gym.Env):
    """One observation, a Box action with the given bounds; reward = first action value."""

    def __init__(self, low, high):
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(
            np.asarray(low, np.float32), np.asarray(high, np.float32), dtype=np.float32
        )

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        return np.zeros(2, np.float32), float(action[0]), False, False, {}


def _box_env(low, high, num_envs=None):
    if num_envs is None:
        return GymWrapper(_BoxEnv(low, high))
    vector = gym.vector.SyncVectorEnv(
        [lambda: _BoxEnv(low, high)] * num_envs,
        autoreset_mode=gym.vector.AutoresetMode.DISABLED,
    )
    return GymWrapper(vector)


def _sampled_actions(actor, env, steps=64):
    torch.manual_seed(0)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return env.rollout(steps, actor)


class TestMlpActor:
    @pytest.mark.parametrize("num_envs", [None, 4])
    def test_pendulum_torques_span_its_bounds(self, num_envs):
        env = gym_env("Pendulum-v1", num_envs=num_envs)
        actor = mlp_actor(env)
        rollout = _sampled_actions(actor, env)
        action = rollout["action"]
        assert action.abs().max() <= 2.0
        assert action.abs().max() > 1.0  # not squashed into [-1, 1]
        loss = ReinforceLoss(actor)(rollout)
        assert torch.isfinite(loss["loss_actor"])

    @pytest.mark.parametrize("num_envs", [None, 3])
    def test_unequal_bounds_per_dimension(self, num_envs):
        low, high = [-1.0, 0.0], [1.0, 5.0]
        env = _box_env(low, high, num_envs)
        actor = mlp_actor(env, hidden=(8,))
        rollout = _sampled_actions(actor, env)
        action = rollout["action"].reshape(-1, 2)
        assert (action >= torch.tensor(low)).all() and (action <= torch.tensor(high)).all()
        assert action[:, 1].max() > 1.0 and action[:, 1].min() >= 0.0
        with torch.no_grad():
            dist = actor.get_dist(rollout)
        assert isinstance(dist, TanhNormal)
        torch.testing.assert_close(dist.low, torch.tensor(low))
        torch.testing.assert_close(dist.high, torch.tensor(high))
        assert torch.isfinite(ReinforceLoss(actor)(rollout)["loss_actor"])

    def test_unbounded_box_gets_a_plain_gaussian(self):
        env = _box_env([-np.inf, -np.inf], [np.inf, np.inf])
        actor = mlp_actor(env, hidden=(8,))
        rollout = _sampled_actions(actor, env, steps=4)
        assert isinstance(actor.get_dist(rollout), IndependentNormal)

    @pytest.mark.parametrize("num_envs", [None, 3])
    def test_state_independent_scale(self, num_envs):
        env = _box_env([-1.0, 0.0], [1.0, 5.0], num_envs)
        actor = mlp_actor(env, hidden=(8,), state_independent_scale=True, init_scale=0.5)
        rollout = _sampled_actions(actor, env, steps=16)
        scale = rollout["scale"].reshape(-1, 2)
        # One parameter per action dimension, the same in every state, starting at 0.5.
        torch.testing.assert_close(scale, torch.full_like(scale, 0.5))
        loss = ReinforceLoss(actor)(rollout)
        loss["loss_actor"].backward()
        (log_scale,) = [p for n, p in actor.named_parameters() if n.endswith("independent_scale")]
        assert log_scale.shape == (2,) and log_scale.grad.abs().min() > 0
        assert isinstance(actor.get_dist(rollout), TanhNormal)

    def test_unsquashed_gaussian_on_a_bounded_box(self):
        # bounded="normal": a plain Gaussian whose samples the environment clips; its
        # log-probability is the sample's, however far past the bounds the mean is.
        env = gym_env("Pendulum-v1", num_envs=4)
        actor = mlp_actor(env, bounded="normal", state_independent_scale=True, init_scale=3.0)
        rollout = _sampled_actions(actor, env)
        dist = actor.get_dist(rollout)
        assert isinstance(dist, IndependentNormal)
        assert rollout["action"].abs().max() > 2.0  # the environment clips, not the policy
        expected = torch.distributions.Normal(rollout["loc"], rollout["scale"])
        torch.testing.assert_close(
            dist.log_prob(rollout["action"]), expected.log_prob(rollout["action"]).sum(-1)
        )
        assert torch.isfinite(ReinforceLoss(actor)(rollout)["loss_actor"])

    def test_a_squashed_gaussian_keeps_the_log_probability_of_its_samples(self):
        # A mean far past the bound is squashed to within 5 units before the tanh, so the
        # samples stay short of the bound in float32 and keep their log-probability.
        # Unsquashed (TorchRL's default), a mean of 20 samples the bound itself and scores
        # it far below its true density.
        env = gym_env("Pendulum-v1")
        actor = mlp_actor(env, state_independent_scale=True, init_scale=0.5)
        td = TensorDict({"loc": torch.full((1000, 1), 20.0), "scale": torch.full((1000, 1), 0.5)})
        dist = actor[-1].get_dist(td)  # the distribution from these parameters
        sample = dist.sample()
        assert (sample < 2.0).all() and (sample > 1.99).all()
        # Its density by change of variables, in float64 from the float32 sample.
        y = sample.double() / 2
        loc = 5 * torch.tanh(torch.tensor(20.0 / 5, dtype=torch.float64))
        density = torch.distributions.Normal(loc, 0.5).log_prob(torch.atanh(y)) - torch.log(
            2 * (1 - y**2)
        )
        torch.testing.assert_close(dist.log_prob(sample).double(), density[:, 0], atol=0.05, rtol=0)
        unsquashed = TanhNormal(td["loc"], td["scale"], low=-2.0, high=2.0)
        assert unsquashed.log_prob(unsquashed.sample()).max() < -100

    @pytest.mark.parametrize("num_envs", [None, 3])
    def test_beta_policy_on_per_dimension_bounds(self, num_envs):
        low, high = [-1.0, 0.0], [1.0, 5.0]
        env = _box_env(low, high, num_envs)
        actor = mlp_actor(env, hidden=(8,), bounded="beta")
        rollout = _sampled_actions(actor, env)
        action = rollout["action"].reshape(-1, 2)
        assert (action >= torch.tensor(low)).all() and (action <= torch.tensor(high)).all()
        assert action[:, 1].max() > 2.5  # spread over [0, 5], not squeezed into [-1, 1]
        dist = actor.get_dist(rollout)
        assert isinstance(dist, BoundedBeta)
        torch.testing.assert_close(dist.high, torch.tensor(high))
        assert torch.isfinite(ReinforceLoss(actor)(rollout)["loss_actor"])

    def test_beta_policy_needs_finite_bounds(self):
        with pytest.raises(ValueError, match="needs a continuous action with finite bounds"):
            mlp_actor(_box_env([-np.inf], [np.inf]), bounded="beta")
        with pytest.raises(ValueError, match=r"finite bounds.*\(discrete\)"):
            mlp_actor(GridWorldEnv(), bounded="beta")
        with pytest.raises(ValueError, match="policy is a Beta"):
            mlp_actor(_box_env([-1.0], [1.0]), bounded="beta", state_independent_scale=True)
        with pytest.raises(ValueError, match="bounded must be"):
            mlp_actor(_box_env([-1.0], [1.0]), bounded="clip")

    def test_state_independent_scale_asks_for_a_continuous_action(self):
        with pytest.raises(ValueError, match="action space is discrete"):
            mlp_actor(GridWorldEnv(), state_independent_scale=True)
        with pytest.raises(ValueError, match="init_scale must be a finite number > 0"):
            mlp_actor(_box_env([-1.0], [1.0]), state_independent_scale=True, init_scale=0.0)

    def test_partly_bounded_box(self):
        env = _box_env([-1.0, -np.inf], [1.0, np.inf])
        with pytest.raises(ValueError, match="bounded in some dimensions and not in others"):
            mlp_actor(env)

    @pytest.mark.parametrize(
        ("hidden", "error", "match"),
        [
            ((0, 64), ValueError, r"hidden\[0\] must be an integer >= 1, got 0"),
            ((64, -3), ValueError, r"hidden\[1\] must be an integer >= 1"),
            ((64.5,), TypeError, r"hidden\[0\] must be an integer"),
            (64, TypeError, "hidden must be a sequence of layer widths"),
        ],
    )
    def test_bad_hidden_widths(self, hidden, error, match):
        with pytest.raises(error, match=match):
            mlp_actor(GridWorldEnv(), hidden=hidden)
        with pytest.raises(error, match=match):
            mlp_critic(GridWorldEnv(), hidden=hidden)

    def test_numpy_widths(self):
        actor = mlp_actor(GridWorldEnv(), hidden=np.array([8, 8]))
        assert sum(p.numel() for p in actor.parameters()) == (16 * 8 + 8) + (8 * 8 + 8) + 36

    def test_no_hidden_layer_is_a_linear_policy(self):
        actor, critic = mlp_actor_critic(GridWorldEnv(), hidden=())
        assert sum(p.numel() for p in actor.parameters()) == 16 * 4 + 4
        assert sum(p.numel() for p in critic.parameters()) == 16 + 1

    def test_missing_observation_key(self):
        with pytest.raises(KeyError, match="no observation 'pixels'"):
            mlp_actor(GridWorldEnv(), observation_key="pixels")


class TestRunningNorm:
    def test_standardises_with_the_statistics_of_every_update(self):
        torch.manual_seed(0)
        norm = RunningNorm(3, clip=100.0)
        x = torch.randn(50, 3) * torch.tensor([0.04, 1.0, 30.0]) + torch.tensor([0.5, 0, -7])
        assert torch.equal(norm(x), x)  # the identity before any statistics
        norm.update(x[:20])
        norm.update(x[20:])  # in two parts: the same as in one
        expected = (x - x.mean(0)) / x.std(0, unbiased=False)
        torch.testing.assert_close(norm(x), expected, atol=1e-4, rtol=1e-4)

    def test_clips_and_floors_the_spread(self):
        norm = RunningNorm(2, clip=5.0, min_std=0.01)
        norm.update(torch.tensor([[0.5, 0.0], [0.5, 2.0]]))  # feature 0 never varies
        out = norm(torch.tensor([[0.51, 1000.0]]))
        torch.testing.assert_close(out, torch.tensor([[1.0, 5.0]]))

    def test_actor_and_critic_share_one_set_of_statistics_saved_with_them(self):
        env = GridWorldEnv(batch_size=4)
        actor, critic = mlp_actor_critic(env, hidden=(8,), normalize=True)
        norms = [m for net in (actor, critic) for m in net.modules() if isinstance(m, RunningNorm)]
        assert len(norms) == 2 and norms[0] is norms[1]
        loss = ReinforceLoss(actor, critic, functional=False)
        batch = env.rollout(5, actor)
        update_running_norms(loss, batch)
        assert norms[0].stats.count.item() == 4 * 5  # updated once, not once per network
        assert any(key.endswith("stats.mean") for key in actor.state_dict())
        fresh = mlp_actor(env, hidden=(8,), normalize=True)
        fresh.load_state_dict(actor.state_dict())
        td = env.reset()
        torch.testing.assert_close(fresh(td.clone())["logits"], actor(td.clone())["logits"])

    def test_a_norm_of_another_shape_or_key_is_refused(self):
        with pytest.raises(ValueError, match=r"standardises 'observation' of shape \(3,\)"):
            mlp_actor(GridWorldEnv(), normalize=RunningNorm(3))
        with pytest.raises(TypeError, match="normalize must be True, False or a RunningNorm"):
            mlp_critic(GridWorldEnv(), normalize="yes")


class TestLeanPolicy:
    """``lean_policy``: the actor's own actions, sampled with less overhead."""

    @staticmethod
    def _trunk_and_head(env):
        """A shared trunk then a head, as ActorValueOperator builds (the Pong recipe)."""
        n_obs = env.observation_spec["observation"].shape[-1]
        trunk = TensorDictModule(
            nn.Sequential(nn.Linear(n_obs, 16), nn.ReLU()), ["observation"], ["hidden"]
        )
        head = TensorDictModule(nn.Linear(16, env.action_spec.space.n), ["hidden"], ["logits"])
        return ProbabilisticActor(
            TensorDictSequential(trunk, head),
            in_keys=["logits"],
            spec=env.action_spec,
            distribution_class=torch.distributions.Categorical,
        )

    @pytest.mark.parametrize("structure", ["mlp", "trunk_and_head"])
    def test_same_actions_and_entries_as_the_actor(self, structure):
        env = GridWorldEnv(batch_size=64)
        actor = mlp_actor(env, hidden=(16,)) if structure == "mlp" else self._trunk_and_head(env)
        lean = lean_policy(actor)
        assert isinstance(lean, LeanCategoricalPolicy)
        td = env.reset()
        with set_exploration_type(ExplorationType.RANDOM):
            for seed in range(5):
                torch.manual_seed(seed)
                expected = actor(td.clone())
                torch.manual_seed(seed)
                got = lean(td.clone())
                assert set(got.keys(True, True)) == set(expected.keys(True, True))
                for key in expected.keys(True, True):
                    torch.testing.assert_close(got[key], expected[key], rtol=0, atol=0)
        assert len(set(got["action"].tolist())) > 1  # it samples, not argmax

    def test_greedy_play_defers_to_the_actor(self):
        env = GridWorldEnv(batch_size=16)
        actor = mlp_actor(env, hidden=(8,))
        td = env.reset()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            greedy = lean_policy(actor)(td.clone())["action"]
        logits = actor.module[0](td.clone())["logits"]
        assert torch.equal(greedy, logits.argmax(-1))

    def test_training_gradients_flow_to_the_same_parameters(self):
        env = GridWorldEnv(batch_size=4)
        actor = mlp_actor(env, hidden=(8,))
        lean = lean_policy(actor)
        assert {id(p) for p in lean.parameters()} == {id(p) for p in actor.parameters()}

    @settings(max_examples=200, deadline=None)
    @given(
        shape=st.lists(st.integers(1, 9), min_size=0, max_size=2),
        num_actions=st.integers(1, 20),
        scale=st.floats(0.1, 30.0),
        masked=st.floats(0.0, 0.9),
        double=st.booleans(),
        seed=st.integers(0, 2**31 - 1),
    )
    def test_sampling_draws_what_categorical_sample_draws(
        self, shape, num_actions, scale, masked, double, seed
    ):
        gen = torch.Generator().manual_seed(seed)
        dtype = torch.float64 if double else torch.float32
        logits = scale * torch.randn(*shape, num_actions, generator=gen, dtype=dtype)
        hidden = torch.rand(logits.shape, generator=gen) < masked  # actions masked out
        hidden[..., int(torch.randint(num_actions, (), generator=gen))] = False
        logits = logits.masked_fill(hidden, -torch.inf)
        reference = torch.distributions.Categorical(logits=logits)
        torch.manual_seed(seed)
        expected, expected_after = reference.sample(), torch.rand(3)
        torch.manual_seed(seed)
        got, got_after = sample_categorical(reference.probs), torch.rand(3)
        assert got.dtype == torch.int64 and got.shape == expected.shape
        assert torch.equal(got, expected)
        assert torch.equal(got_after, expected_after)  # the random stream carries on alike
        assert not hidden.gather(-1, got.unsqueeze(-1)).any()

    def test_nan_probabilities_are_an_error_not_an_action(self):
        probs = torch.tensor([[0.5, 0.5, 0.0], [float("nan"), 0.5, 0.5]])
        with pytest.raises(ValueError, match=r"1 NaN value.*diverged"):
            sample_categorical(probs)
        env = GridWorldEnv(batch_size=4)
        actor = mlp_actor(env, hidden=(8,))
        with torch.no_grad():
            actor.module[0].module[0].weight.fill_(torch.nan)
        with set_exploration_type(ExplorationType.RANDOM), pytest.raises(ValueError, match="NaN"):
            lean_policy(actor)(env.reset())

    def test_other_actors_are_kept_as_they_are(self):
        pendulum = gym_env("Pendulum-v1")
        gaussian = mlp_actor(pendulum)
        assert lean_policy(gaussian) is gaussian
        with pytest.raises(TypeError, match="lean_policy"):
            LeanCategoricalPolicy(gaussian)
        env = GridWorldEnv(batch_size=2)
        with_log_prob = mlp_actor(env)
        with_log_prob.module[-1].return_log_prob = True
        assert lean_policy(with_log_prob) is with_log_prob


class TestLeanCategoricalActor:
    """mlp_actor's categorical actor: ProbabilisticActor's distribution, built faster."""

    @staticmethod
    def _pair(env, **kwargs):
        """A LeanCategoricalActor and a plain ProbabilisticActor with equal weights."""
        lean = mlp_actor(env, hidden=(16,), **kwargs)
        assert isinstance(lean, LeanCategoricalActor) and lean._lean is not None
        plain = ProbabilisticActor(
            copy.deepcopy(lean.module[0]),
            in_keys=["logits"],
            spec=env.action_spec,
            distribution_class=torch.distributions.Categorical,
        )
        assert type(plain) is ProbabilisticActor
        return lean, plain

    def test_same_distribution_entries_gradients_and_state_dict(self):
        env = GridWorldEnv(batch_size=32)
        lean, plain = self._pair(env, normalize=True)
        assert lean.state_dict().keys() == plain.state_dict().keys()
        td = env.reset()
        got, expected = td.clone(), td.clone()
        dist, reference = lean.get_dist(got), plain.get_dist(expected)
        assert type(dist) is type(reference)
        torch.testing.assert_close(dist.logits, reference.logits, rtol=0, atol=0)
        assert set(got.keys(True, True)) == set(expected.keys(True, True))
        actions = torch.arange(32) % 4
        dist.log_prob(actions).sum().backward()
        reference.log_prob(actions).sum().backward()
        for (name, p), q in zip(lean.named_parameters(), plain.parameters(), strict=True):
            assert p.grad is not None and torch.equal(p.grad, q.grad), name

    @pytest.mark.parametrize("functional", [True, False])
    def test_a_loss_holding_it_computes_what_it_does_with_the_plain_actor(self, functional):
        env = GridWorldEnv(batch_size=8)
        lean, plain = self._pair(env)
        batch = env.rollout(6, plain, break_when_any_done=False)
        losses = []
        for actor in (lean, plain):
            loss = ReinforceLoss(actor, functional=functional)
            out = loss(batch.clone())
            out["loss_actor"].backward()
            grads = [p.grad for p in loss.parameters() if p.requires_grad]
            losses.append((out["loss_actor"].detach(), grads))
        torch.testing.assert_close(losses[0][0], losses[1][0], rtol=0, atol=0)
        for got, expected in zip(losses[0][1], losses[1][1], strict=True):
            torch.testing.assert_close(got, expected, rtol=0, atol=0)

    def test_a_copy_builds_its_distribution_from_its_own_weights(self):
        env = GridWorldEnv(batch_size=4)
        actor = mlp_actor(env, hidden=(8,))
        copied = pickle.loads(pickle.dumps(copy.deepcopy(actor)))
        with torch.no_grad():
            for parameter in copied.parameters():
                parameter.zero_()
        td = env.reset()
        assert torch.equal(copied.get_dist(td.clone()).logits, torch.full((4, 4), -math.log(4)))
        assert not torch.equal(actor.get_dist(td.clone()).logits, copied.get_dist(td).logits)

    def test_another_structure_builds_its_distribution_as_probabilistic_actor_does(self):
        env = GridWorldEnv(batch_size=4)
        actor = LeanCategoricalActor(
            TensorDictModule(nn.Linear(16, 4), ["observation"], ["logits"]),
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
            return_log_prob=True,  # a structure the shortcut does not reproduce
        )
        assert actor._lean is None
        td = env.reset()
        expected = torch.distributions.Categorical(logits=actor.module[0](td.clone())["logits"])
        torch.testing.assert_close(actor.get_dist(td).logits, expected.logits)


class TestDirectSequential:
    """``direct_network``: a stack of layers run without nn.Module's call machinery,
    computing exactly what the stack computes."""

    @staticmethod
    def _networks():
        torch.manual_seed(0)
        yield MLP(in_features=5, out_features=3, num_cells=[16, 16], activation_class=nn.Tanh)
        yield MLP(in_features=5, out_features=3, num_cells=[16], activation_class=nn.ReLU)
        yield nn.Sequential(  # direct layers mixed with ones left to nn.Module
            nn.Linear(5, 16), nn.ELU(), nn.LayerNorm(16), nn.Linear(16, 8),
            nn.ReLU(inplace=True), nn.Sigmoid(), nn.Linear(8, 3),
        )  # fmt: skip

    def test_same_outputs_and_gradients_as_the_network(self):
        x = torch.randn(7, 5)
        for network in self._networks():
            direct = direct_network(network)
            assert isinstance(direct, DirectSequential)
            reference = copy.deepcopy(network)
            got, expected = direct(x), reference(x)
            assert torch.equal(got, expected)
            got.square().sum().backward()
            expected.square().sum().backward()
            for p, q in zip(network.parameters(), reference.parameters(), strict=True):
                assert torch.equal(p.grad, q.grad)

    def test_weights_are_read_at_each_call(self):
        network = next(self._networks())
        direct, x = direct_network(network), torch.randn(3, 5)
        with torch.no_grad():
            network[0].weight.add_(1.0)  # an optimiser's in-place step
        assert torch.equal(direct(x), network(x))
        network[2] = nn.Linear(16, 16)  # a layer replaced
        assert torch.equal(direct(x), network(x))
        zeros = TensorDict.from_module(network).apply(torch.zeros_like)
        with zeros.to_module(network):  # what a functional loss does
            assert torch.equal(direct(x), torch.zeros(3, 3))
        assert not torch.equal(direct(x), torch.zeros(3, 3))

    def test_hooks_and_several_inputs_go_through_nn_module(self):
        network = next(self._networks())
        direct, x = direct_network(network), torch.randn(3, 5)
        calls = []
        handle = network[1].register_forward_hook(lambda m, i, o: calls.append(m) or o * 0)
        assert torch.equal(direct(x), network(x)) and len(calls) == 2
        handle.remove()
        handle = network.register_forward_pre_hook(lambda m, i: (i[0] * 2,))
        assert torch.equal(direct(x), network(x))
        handle.remove()
        handle = nn.modules.module.register_module_forward_hook(lambda m, i, o: o + 1)
        try:
            assert torch.equal(direct(x), network(x))
        finally:
            handle.remove()
        two = MLP(in_features=5, out_features=3, num_cells=[8])
        assert torch.equal(direct_network(two)(x[:, :2], x[:, 2:]), two(x[:, :2], x[:, 2:]))

    def test_other_networks_are_kept_as_they_are(self):
        reshaped = MLP(in_features=5, out_features=(3, 2), num_cells=[8])
        conv = ConvNet(num_cells=[4], kernel_sizes=3, strides=1)
        linear = nn.Linear(5, 3)
        for network in (reshaped, conv, linear):
            assert direct_network(network) is network
