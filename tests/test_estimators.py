"""RewardToGo and DiscountedReturn on TensorDict batches."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import N_ACT, make_batch, make_critic
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from test_functional import reference_returns
from torch import nn
from torchrl.modules import ValueOperator

from rl_pg import DiscountedReturn, RewardToGo


def _reference(whole_episode: bool):
    """The plain loop of test_functional (forward sums over each episode), in the
    kernels' signature: the expected values owe nothing to the code under test."""

    def returns(reward, done, gamma, *, terminated=None, next_value=None):
        terminated = done if terminated is None else terminated

        def rows(x):  # [..., T, 1] -> list of [T] float64 lists, time last
            x = x.squeeze(-1).double()
            return x.reshape(-1, x.shape[-1]).tolist()

        steps = reward.shape[-2]
        out = reference_returns(
            rows(reward), rows(done), rows(terminated),
            rows(next_value) if next_value is not None else [None] * len(rows(reward)),
            [[gamma] * steps] * len(rows(reward)), whole_episode,
        )  # fmt: skip
        return torch.tensor(out, dtype=reward.dtype).reshape(reward.shape)

    return returns


PAIRS = [(RewardToGo, _reference(False)), (DiscountedReturn, _reference(True))]


@pytest.fixture
def batch():
    return make_batch(torch.randint(N_ACT, (3, 9)), p_done=0.25, seed=5)


def _truncate(batch):
    """Marks every third done as a truncation (done but not terminated)."""
    done = batch["next", "done"]
    terminated = done.clone()
    terminated[done.cumsum(1) % 3 == 0] = False
    batch["next", "terminated"] = terminated
    return batch


def _full_pass(fn, critic, batch):
    """The critic's values at every observation and next observation, and the returns
    ``fn`` bootstraps from them: what an estimator with that critic must write."""
    with torch.no_grad():
        value = critic(batch.select("observation").clone())["state_value"]
        next_value = critic(batch["next"].select("observation").clone())["state_value"]
    expected = fn(
        batch["next", "reward"],
        batch["next", "done"],
        0.9,
        terminated=batch["next", "terminated"],
        next_value=next_value,
    )
    return value, next_value, expected


@pytest.mark.parametrize(("cls", "fn"), PAIRS)
class TestMonteCarloEstimators:
    """What RewardToGo and DiscountedReturn share; each only differs by its return."""

    def test_collector_batch_without_value_network(self, cls, fn, batch):
        cls(gamma=0.9)(batch)
        expected = fn(batch["next", "reward"], batch["next", "done"], 0.9)
        torch.testing.assert_close(batch["value_target"], expected)
        torch.testing.assert_close(batch["advantage"], expected)

    def test_flat_batch_of_episodes(self, cls, fn, batch):
        flat = batch.reshape(-1)
        cls(gamma=0.9)(flat)
        expected = fn(flat["next", "reward"], flat["next", "done"], 0.9)
        torch.testing.assert_close(flat["value_target"], expected)

    def test_value_network_baseline_and_bootstrap(self, cls, fn, batch):
        torch.manual_seed(0)
        critic = make_critic()
        batch = _truncate(batch)
        value, _, expected = _full_pass(fn, critic, batch)
        cls(gamma=0.9, value_network=critic)(batch)
        torch.testing.assert_close(batch["value_target"], expected)
        torch.testing.assert_close(batch["advantage"], expected - value)
        assert not batch["value_target"].requires_grad

    @pytest.mark.parametrize("differentiable", [True, False, "default"])
    def test_differentiable_as_torchrl_gradients_reach_inputs_never_the_critic(
        self, cls, fn, batch, differentiable
    ):
        """TorchRL's ``differentiable``: the estimate is a function of the inputs (their
        gradients flow), never of the value network's parameters (held out); without it,
        no graph at all. TorchRL's TD(1) on the same batch behaves alike."""
        from torchrl.objectives.value import TD1Estimator

        torch.manual_seed(0)
        critic = make_critic()
        batch = _truncate(batch)
        given = {} if differentiable == "default" else {"differentiable": differentiable}
        differentiable = given.get("differentiable", False)  # TorchRL's default: no graph
        for estimator in (
            cls(gamma=0.9, value_network=critic, **given),
            TD1Estimator(gamma=0.9, value_network=critic, **given),
        ):
            data = batch.clone()
            observation = data["observation"].detach().requires_grad_(True)
            data["observation"] = observation
            estimator(data)
            advantage = data["advantage"]
            assert advantage.requires_grad == differentiable, type(estimator).__name__
            if differentiable:
                advantage.sum().backward()
                assert observation.grad is not None and observation.grad.abs().sum() > 0
                assert all(p.grad is None for p in critic.parameters())

    @pytest.mark.parametrize("given", ["both", "params"])
    def test_the_parameters_given_are_the_ones_the_values_come_from(self, cls, fn, batch, given):
        """TorchRL's ``params`` and ``target_params``: V(s_t) from ``params``, the
        bootstrap V(s_{t+1}) from ``target_params`` (``params`` when only those are
        given), never the value network's own parameters; ``target_params`` alone is
        refused, as TorchRL refuses it (not silently ignored)."""
        torch.manual_seed(0)
        own, current, target = make_critic(), make_critic(), make_critic()
        batch = _truncate(batch)
        kwargs = {"params": current, "target_params": target}
        if given == "params":
            del kwargs["target_params"]
        value, _, _ = _full_pass(fn, current, batch)
        _, _, expected = _full_pass(fn, kwargs.get("target_params", current), batch)
        as_params = {k: TensorDict.from_module(m).detach() for k, m in kwargs.items()}
        cls(gamma=0.9, value_network=own)(batch, **as_params)
        torch.testing.assert_close(batch["value_target"], expected)
        torch.testing.assert_close(batch["advantage"], expected - value)
        with pytest.raises(ValueError, match="both provided or not"):
            cls(gamma=0.9, value_network=own)(batch, target_params=as_params["params"])
        # The bootstrap is a target: a differentiable estimate carries no graph into
        # the parameters it was read with.
        data = batch.clone()
        attached = {k: TensorDict.from_module(m) for k, m in kwargs.items()}
        cls(gamma=0.9, value_network=own, differentiable=True)(data, **attached)
        assert not data["value_target"].requires_grad

    def test_without_differentiable_no_input_carries_a_graph_into_the_returns(self, cls, fn, batch):
        batch["next", "reward"] = batch["next", "reward"].detach().requires_grad_(True)
        cls(gamma=0.9)(batch)  # TorchRL's default: not differentiable
        assert not batch["value_target"].requires_grad
        assert not batch["advantage"].requires_grad

    @pytest.mark.parametrize("shape", ["batched", "flat"])
    def test_one_call_of_the_value_network_matches_torchrl_vmapped_pair(
        self, cls, fn, batch, shape
    ):
        """The estimator calls the critic once on root and next inputs laid end to end;
        TorchRL vmaps two calls. Same values, NaN next observations replaced alike."""
        torch.manual_seed(0)
        critic = make_critic()
        batch = batch.reshape(-1) if shape == "flat" else batch
        batch["next", "observation"][..., 1, :] = float("nan")  # e.g. compact observations
        estimator = cls(gamma=0.9, value_network=critic)
        with torch.no_grad():
            value, next_value, _ = estimator._call_value_nets(
                data=batch.clone(),
                params=None,
                next_params=None,
                single_call=False,
                value_key="state_value",
                detach_next=True,
            )
        estimator(batch)
        torch.testing.assert_close(batch["state_value"], value, rtol=0, atol=1e-6)
        torch.testing.assert_close(batch["next", "state_value"], next_value, rtol=0, atol=1e-6)
        assert torch.isfinite(next_value).all()

    @pytest.mark.parametrize("dims", [2, 3])
    def test_a_critic_with_hooks_is_called_as_a_module(self, cls, fn, batch, dims):
        """Plain networks are run on tensors, without a TensorDict around them; a
        critic whose module has a forward hook is called whole, so the hook runs (on a
        batch of environments in two dimensions too: [B, E, T])."""
        torch.manual_seed(0)
        critic = make_critic()
        if dims == 3:
            batch = batch.unsqueeze(1)
        plain = cls(gamma=0.9, value_network=critic)(batch.clone())
        critic.register_forward_hook(
            lambda module, args, out: out.set("state_value", out["state_value"] + 1.0)
        )
        hooked = cls(gamma=0.9, value_network=critic)(batch.clone())
        torch.testing.assert_close(hooked["state_value"], plain["state_value"] + 1.0)
        torch.testing.assert_close(
            hooked["next", "state_value"], plain["next", "state_value"] + 1.0
        )

    @pytest.mark.parametrize("graph", [False, True])
    @pytest.mark.parametrize(
        "broken", [None, "integer_done", "observation", "time_first", "two_batch_dims"]
    )
    def test_next_values_taken_from_the_following_step_match_a_full_pass(
        self, cls, fn, monkeypatch, graph, broken
    ):
        """In a segment collected in time order, V(s_{t+1}) is the following step's
        V(s_t) unless an episode ended at t: the critic then runs on the segment's last
        steps and the episode ends only. Values, targets and advantages are those of a
        full pass; a batch that is not such a segment (a next observation that differs
        from the following one, time first) gets the full pass."""
        monkeypatch.setattr("rl_pg.estimators.REUSE_MIN_WORK", 0)
        generator = torch.Generator().manual_seed(3)
        envs, steps = 4, 11
        states = torch.randn(envs, steps + 1, 3, generator=generator)
        done = torch.rand(envs, steps, 1, generator=generator) < 0.25
        next_obs = states[:, 1:].clone()
        # After an episode's end the following observation is a fresh reset's.
        next_obs[done.squeeze(-1)] = torch.randn(int(done.sum()), 3, generator=generator)
        terminated = done & (torch.rand(envs, steps, 1, generator=generator) < 0.5)
        batch = TensorDict(
            {
                "observation": states[:, :-1],
                "next": {
                    "observation": next_obs,
                    "reward": torch.randn(envs, steps, 1, generator=generator),
                    "done": done,
                    "terminated": terminated,
                },
            },
            batch_size=[envs, steps],
        )
        if broken == "integer_done":  # episode ends as 0/1 numbers: read as they are
            batch["next", "done"] = done.to(torch.uint8)
        if broken == "observation":  # not the following step's, though no episode ended
            t = int((~done[0, :-1, 0]).nonzero()[0])
            batch["next", "observation"][0, t] += 1.0
        torch.manual_seed(0)
        critic = ValueOperator(
            nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 1)), in_keys=["observation"]
        )
        value, next_value, expected = _full_pass(fn, critic, batch)
        if broken == "two_batch_dims":  # environments in a grid: [2, 2, T], no less a segment
            batch = batch.reshape(2, 2, steps)
            value, next_value, expected = (x.reshape(2, 2, *x.shape[1:]) for x in
                                           (value, next_value, expected))  # fmt: skip
        if broken == "time_first":
            batch = batch.transpose(0, 1).contiguous()
            batch.names = ["time", None]
            value, next_value, expected = (x.transpose(0, 1) for x in (value, next_value, expected))
        seen = []  # rows the critic's first layer computes
        critic.module[0].register_forward_hook(
            lambda module, args, out: seen.append(out.shape[:-1].numel())
        )
        estimator = cls(gamma=0.9, value_network=critic)
        attached = estimator.estimate(batch, value_graph=graph)
        torch.testing.assert_close(batch["state_value"], value, rtol=0, atol=1e-6)
        torch.testing.assert_close(batch["next", "state_value"], next_value, rtol=0, atol=1e-6)
        torch.testing.assert_close(batch["value_target"], expected, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(batch["advantage"], expected - value, rtol=1e-5, atol=1e-5)
        if graph:
            assert attached.requires_grad
            torch.testing.assert_close(attached.detach(), value)
        rows = sum(seen)
        if broken in (None, "integer_done", "two_batch_dims"):  # each row's last step, the ends
            assert rows == envs * steps + envs + int(done[:, :-1].sum())
        else:
            assert rows == 2 * envs * steps

    def test_named_time_dimension(self, cls, fn, batch):
        time_major = batch.transpose(0, 1).contiguous()
        time_major.names = ["time", None]
        cls(gamma=0.9)(time_major)
        cls(gamma=0.9)(batch)
        torch.testing.assert_close(
            time_major["value_target"].transpose(0, 1), batch["value_target"]
        )

    def test_set_keys(self, cls, fn, batch):
        renamed = batch.clone()
        renamed.rename_key_(("next", "reward"), ("next", "r"))
        renamed.rename_key_(("next", "done"), ("next", "d"))
        estimator = cls(gamma=0.9)
        estimator.set_keys(reward="r", done="d", value_target="g", advantage="psi")
        estimator(renamed)
        cls(gamma=0.9)(batch)
        torch.testing.assert_close(renamed["g"], batch["value_target"])
        torch.testing.assert_close(renamed["psi"], batch["advantage"])
        assert ("next", "r") in estimator.in_keys

    def test_set_keys_rejects_unknown_names(self, cls, fn):
        with pytest.raises(KeyError, match="rewards is not an accepted tensordict key"):
            cls(gamma=0.9).set_keys(rewards="r")

    def test_gamma_is_in_state_dict(self, cls, fn):
        assert cls(gamma=0.5).state_dict()["gamma"].item() == 0.5

    @pytest.mark.parametrize("gamma", [-0.5, 1.2, float("nan")])
    def test_gamma_outside_unit_interval(self, cls, fn, gamma):
        with pytest.raises(ValueError, match=r"gamma must be a finite number >= 0 and <= 1"):
            cls(gamma=gamma)

    @pytest.mark.parametrize("gamma", ["0.9", None, True])
    def test_gamma_that_is_not_a_number(self, cls, fn, gamma):
        with pytest.raises(TypeError, match="gamma must be a real number"):
            cls(gamma=gamma)

    @pytest.mark.parametrize("gamma", [np.float32(0.9), torch.tensor(0.9)])
    def test_gamma_as_a_numpy_or_torch_scalar(self, cls, fn, gamma, batch):
        expected = cls(gamma=0.9)(batch.clone())["value_target"]
        torch.testing.assert_close(cls(gamma=gamma)(batch)["value_target"], expected)

    @pytest.mark.parametrize("time_dim", [1.0, "time", True])
    def test_time_dim_that_is_not_an_integer(self, cls, fn, time_dim):
        with pytest.raises(TypeError, match="time_dim must be an integer or None"):
            cls(gamma=0.9, time_dim=time_dim)

    def test_value_network_output_without_the_value_dimension(self, cls, fn, batch):
        squeezed = TensorDictModule(
            lambda obs: obs.sum(-1), in_keys=["observation"], out_keys=["state_value"]
        )
        with pytest.raises(ValueError, match=r"writes 'state_value' of shape \(3, 9\)"):
            cls(gamma=0.9, value_network=squeezed)(batch)

    def test_value_network_that_is_not_a_tensordict_module(self, cls, fn):
        with pytest.raises(TypeError, match="value_network must be a TensorDictModule"):
            cls(gamma=0.9, value_network=torch.nn.Linear(3, 1))

    def test_gamma_tensor_with_many_values(self, cls, fn):
        with pytest.raises(ValueError, match="one-element tensor"):
            cls(gamma=torch.tensor([0.9, 0.8]))

    def test_data_without_time_dimension(self, cls, fn, batch):
        with pytest.raises(ValueError, match="needs a tensordict with a time dimension"):
            cls(gamma=0.9)(batch[0, 0])

    def test_missing_reward(self, cls, fn, batch):
        del batch["next", "reward"]
        with pytest.raises(KeyError, match=r"no entry \('next', 'reward'\)"):
            cls(gamma=0.9)(batch)

    def test_done_that_does_not_match_reward(self, cls, fn, batch):
        batch["next", "done"] = torch.zeros(3, 9, 2, dtype=torch.bool)
        with pytest.raises(ValueError, match=r"done of shape \(3, 9, 2\) does not match reward"):
            cls(gamma=0.9)(batch)

    def test_flags_of_one_entry_answer_for_a_reward_of_several(self, cls, fn, batch):
        # Two rewards per step (say, two objectives): each column's returns are those of
        # its own reward under the step's one done and terminated flag.
        batch = _truncate(batch)
        two = torch.cat([batch["next", "reward"], -2.0 * batch["next", "reward"]], -1)
        batch["next", "reward"] = two
        cls(gamma=0.9)(batch)
        for column in (0, 1):
            expected = fn(
                two[..., column : column + 1], batch["next", "done"], 0.9,
                terminated=batch["next", "terminated"],
            )  # fmt: skip
            torch.testing.assert_close(batch["value_target"][..., column : column + 1], expected)

    @pytest.mark.parametrize("done", ["missing", "two_flags"])
    def test_a_malformed_done_gets_the_same_error_with_a_critic_that_could_reuse_values(
        self, cls, fn, batch, done, monkeypatch
    ):
        # The check for values to reuse reads done first: it must leave a malformed one
        # to the estimate's own check, not fail on it in its own way.
        monkeypatch.setattr("rl_pg.estimators.REUSE_MIN_WORK", 0)
        if done == "missing":
            del batch["next", "done"]
            error, match = KeyError, r"no entry \('next', 'done'\)"
        else:
            batch["next", "done"] = torch.zeros(3, 9, 2, dtype=torch.bool)
            error, match = ValueError, r"done of shape \(3, 9, 2\) does not match reward"
        with pytest.raises(error, match=match):
            cls(gamma=0.9, value_network=make_critic())(batch)


class TestRewardToGo:
    def test_each_step_answers_for_the_rewards_after_it(self):
        batch = make_batch(torch.zeros(1, 3, dtype=torch.long), p_done=0.0)
        batch["next", "reward"] = torch.tensor([[[1.0], [2.0], [4.0]]])
        RewardToGo(gamma=1.0)(batch)
        assert batch["value_target"].flatten().tolist() == [7.0, 6.0, 4.0]


class TestDiscountedReturn:
    def test_every_step_gets_the_episode_return(self):
        batch = make_batch(torch.zeros(1, 3, dtype=torch.long), p_done=0.0)
        batch["next", "reward"] = torch.tensor([[[1.0], [2.0], [4.0]]])
        DiscountedReturn(gamma=0.5)(batch)
        assert batch["value_target"].flatten().tolist() == [3.0, 3.0, 3.0]
