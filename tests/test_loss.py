"""rl_pg.ReinforceLoss: outputs, keys, reductions, gradients, actors, baselines, errors."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
from conftest import (
    N_ACT,
    N_OBS,
    make_batch,
    make_categorical_actor,
    make_composite_actor,
    make_critic,
    make_gaussian_actor,
    make_one_hot_actor,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torchrl.data import Bounded, Composite
from torchrl.modules import MaskedOneHotCategorical, ProbabilisticActor, TanhNormal
from torchrl.objectives.value import GAE

from rl_pg import DiscountedReturn, ReinforceLoss, RewardToGo
from rl_pg.functional import reward_to_go
from rl_pg.loss_checks import per_step


def _surrogate(actor, batch, weights):
    """-mean(weights * log pi(stored action)), computed by hand."""
    dist = actor.get_dist(batch)
    log_prob = dist.log_prob(batch["action"])
    if log_prob.shape != weights.shape[:-1]:
        log_prob = log_prob.sum(-1)
    return -(log_prob.unsqueeze(-1) * weights).mean()


class TestReinforceLoss:
    def test_output_keys_without_critic(self, categorical_actor, categorical_batch):
        out = ReinforceLoss(categorical_actor)(categorical_batch)
        assert set(out.keys()) == {"loss_actor", "advantage_mean", "advantage_std"}
        assert out.batch_size == torch.Size([])

    def test_output_keys_with_critic(self, categorical_actor, critic, categorical_batch):
        out = ReinforceLoss(categorical_actor, critic)(categorical_batch)
        assert set(out.keys()) == {
            "loss_actor",
            "loss_value",
            "advantage_mean",
            "advantage_std",
            "explained_variance",
        }

    def test_output_keys_with_entropy_and_scalar_baseline(
        self, categorical_actor, categorical_batch
    ):
        loss = ReinforceLoss(categorical_actor, baseline="ema", entropy_coeff=0.1)
        out = loss(categorical_batch)
        assert {"loss_entropy", "entropy", "baseline"} <= set(out.keys())
        assert loss.out_keys == ["loss_actor", "loss_entropy"]

    def test_explained_variance_is_the_share_of_the_returns_variance_the_critic_explains(
        self, categorical_actor, critic, categorical_batch
    ):
        loss = ReinforceLoss(categorical_actor, critic)
        batch = categorical_batch.clone()
        batch["collector", "mask"] = torch.ones(batch.shape, dtype=torch.bool)
        batch["collector", "mask"][:, -2:] = False  # padding counts in neither variance
        out = loss(batch)
        valid = batch["collector", "mask"]
        target, value = batch["value_target"][valid], batch["state_value"][valid].detach()
        expected = 1 - (target - value).var(unbiased=False) / target.var(unbiased=False)
        torch.testing.assert_close(out["explained_variance"], expected)
        # A critic that predicts every return explains all of it.
        batch["value_target"] = batch["state_value"].detach()
        assert loss(batch)["explained_variance"].item() == pytest.approx(1.0)
        # Values the batch brings with their graph (the critic run by the caller): the
        # diagnostic is detached all the same.
        batch["state_value"] = critic(batch.select("observation"))["state_value"]
        assert batch["state_value"].requires_grad
        assert not loss(batch)["explained_variance"].requires_grad
        # Returns all alike: their variance, the divisor, is floored at 1e-8.
        batch["value_target"] = torch.full_like(batch["value_target"], 2.0)
        batch["state_value"] = 2.0 + 1e-5 * torch.randn_like(batch["value_target"])
        error = (batch["state_value"] - 2.0)[valid].var(unbiased=False)
        torch.testing.assert_close(loss(batch)["explained_variance"], 1 - error / 1e-8)

    def test_diagnostics_are_detached(self, categorical_actor, critic, categorical_batch):
        out = ReinforceLoss(categorical_actor, critic, entropy_coeff=0.1)(categorical_batch)
        for key, value in out.items():
            assert value.requires_grad == key.startswith("loss_"), key

    def test_actor_loss_is_the_reward_to_go_surrogate(self, categorical_actor, categorical_batch):
        loss = ReinforceLoss(categorical_actor)
        out = loss(categorical_batch.clone())
        returns = reward_to_go(
            categorical_batch["next", "reward"], categorical_batch["next", "done"], 0.99
        )
        expected = _surrogate(categorical_actor, categorical_batch, returns)
        torch.testing.assert_close(out["loss_actor"], expected)

    def test_default_estimators(self, categorical_actor, critic):
        without = ReinforceLoss(categorical_actor)
        assert isinstance(without.value_estimator, RewardToGo)
        assert without.value_estimator.gamma.item() == 0.99
        assert isinstance(ReinforceLoss(categorical_actor, critic).value_estimator, GAE)

    @pytest.mark.parametrize(
        ("value_type", "cls"),
        [("reward_to_go", RewardToGo), ("discounted_return", DiscountedReturn)],
    )
    def test_make_value_estimator_by_name(self, categorical_actor, value_type, cls):
        loss = ReinforceLoss(categorical_actor).make_value_estimator(value_type, gamma=0.5)
        assert type(loss.value_estimator) is cls
        assert loss.value_estimator.gamma.item() == 0.5
        # without a gamma, the registered default: TorchRL's 0.99
        loss = ReinforceLoss(categorical_actor).make_value_estimator(value_type)
        assert type(loss.value_estimator) is cls and loss.value_estimator.gamma.item() == 0.99

    def test_make_value_estimator_by_class_receives_the_critic(
        self, categorical_actor, critic, categorical_batch
    ):
        loss = ReinforceLoss(categorical_actor, critic)
        loss.make_value_estimator(DiscountedReturn, gamma=0.9)
        assert loss.value_estimator.value_network is loss.critic_network
        loss(categorical_batch)
        value_target = categorical_batch["value_target"]
        advantage = categorical_batch["advantage"]
        torch.testing.assert_close(advantage, value_target - categorical_batch["state_value"])

    def test_precomputed_advantage_is_used(self, categorical_actor, critic, categorical_batch):
        categorical_batch["advantage"] = torch.ones_like(categorical_batch["next", "reward"])
        categorical_batch["value_target"] = torch.zeros_like(categorical_batch["next", "reward"])
        out = ReinforceLoss(categorical_actor, critic)(categorical_batch)
        weights = torch.ones_like(categorical_batch["advantage"])
        torch.testing.assert_close(
            out["loss_actor"], _surrogate(categorical_actor, categorical_batch, weights)
        )

    def test_set_keys_round_trip(self, categorical_actor, categorical_batch):
        reference = ReinforceLoss(categorical_actor)(categorical_batch.clone())
        renamed = categorical_batch.clone()
        renamed.rename_key_("action", "act")
        renamed.rename_key_(("next", "reward"), ("next", "rew"))
        renamed.rename_key_(("next", "done"), ("next", "finished"))
        loss = ReinforceLoss(categorical_actor)
        loss.set_keys(action="act", reward="rew", done="finished", value_target="ret")
        out = loss(renamed)
        torch.testing.assert_close(out["loss_actor"], reference["loss_actor"])
        assert "ret" in renamed.keys() and "value_target" not in renamed.keys()
        loss.set_keys(action=None)
        assert loss.tensor_keys.action == "action"

    def test_set_keys_rejects_unknown_names(self, categorical_actor):
        with pytest.raises(ValueError, match="rewards is not an accepted tensordict key"):
            ReinforceLoss(categorical_actor).set_keys(rewards="r")

    @pytest.mark.parametrize("reduction", ["none", "mean", "sum"])
    def test_reduction(self, categorical_actor, critic, categorical_batch, reduction):
        loss = ReinforceLoss(categorical_actor, critic, reduction=reduction, entropy_coeff=0.1)
        out = loss(categorical_batch)
        mean = ReinforceLoss(categorical_actor, critic, entropy_coeff=0.1)(categorical_batch)
        for key in ("loss_actor", "loss_value", "loss_entropy"):
            if reduction == "none":
                assert out[key].shape == categorical_batch.shape
                torch.testing.assert_close(out[key].mean(), mean[key])
            elif reduction == "sum":
                torch.testing.assert_close(out[key], mean[key] * categorical_batch.numel())
            else:
                torch.testing.assert_close(out[key], mean[key])

    def test_gradient_isolation(self, categorical_actor, critic, categorical_batch):
        loss = ReinforceLoss(categorical_actor, critic)
        out = loss(categorical_batch)
        actor_params = list(loss.actor_network_params.values(True, True))
        critic_params = list(loss.critic_network_params.values(True, True))
        actor_grads = torch.autograd.grad(
            out["loss_actor"], actor_params + critic_params, retain_graph=True, allow_unused=True
        )
        assert all(g is not None for g in actor_grads[: len(actor_params)])
        assert all(g is None for g in actor_grads[len(actor_params) :])
        value_grads = torch.autograd.grad(
            out["loss_value"], actor_params + critic_params, allow_unused=True
        )
        assert all(g is None for g in value_grads[: len(actor_params)])
        assert all(g is not None for g in value_grads[len(actor_params) :])

    def test_one_hot_actor_scores_the_stored_action(self):
        torch.manual_seed(0)
        actor = make_one_hot_actor()
        index = torch.randint(N_ACT, (3, 7))
        batch = make_batch(torch.nn.functional.one_hot(index, N_ACT))
        out = ReinforceLoss(actor)(batch.clone())
        returns = reward_to_go(batch["next", "reward"], batch["next", "done"], 0.99)
        torch.testing.assert_close(out["loss_actor"], _surrogate(actor, batch, returns))

    def test_returns_of_each_agent_weight_its_own_action(self):
        # Two agents a step, each with its action and its return ([*B, agents, 1]):
        # each agent's log π is weighted by its own return.
        torch.manual_seed(0)
        heads = torch.nn.Sequential(
            torch.nn.Linear(N_OBS, 2 * N_ACT), torch.nn.Unflatten(-1, (2, N_ACT))
        )
        actor = ProbabilisticActor(
            TensorDictModule(heads, ["observation"], ["logits"]),
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
        )
        batch = make_batch(torch.randint(N_ACT, (3, 7, 2)))
        batch["value_target"] = torch.randn(3, 7, 2, 1)
        out = ReinforceLoss(actor)(batch.clone())
        log_prob = actor.get_dist(batch).log_prob(batch["action"]).unsqueeze(-1)
        torch.testing.assert_close(out["loss_actor"], -(log_prob * batch["value_target"]).mean())

    def test_masked_one_hot_actor_scores_the_stored_action(self):
        torch.manual_seed(0)
        actor = ProbabilisticActor(
            TensorDictModule(torch.nn.Linear(N_OBS, N_ACT), ["observation"], ["logits"]),
            in_keys={"logits": "logits", "mask": "action_mask"},
            distribution_class=MaskedOneHotCategorical,
        )
        allowed = torch.rand(3, 7, N_ACT, generator=torch.Generator().manual_seed(1)) < 0.7
        allowed[..., 0] = True
        index = torch.multinomial(allowed.reshape(-1, N_ACT).float(), 1).reshape(3, 7)
        batch = make_batch(torch.nn.functional.one_hot(index, N_ACT))
        batch["action_mask"] = allowed
        out = ReinforceLoss(actor)(batch.clone())
        returns = reward_to_go(batch["next", "reward"], batch["next", "done"], 0.99)
        torch.testing.assert_close(out["loss_actor"], _surrogate(actor, batch, returns))
        batch["action"][0, 0] = 1  # a row of ones: no action the policy takes
        with pytest.raises(ValueError, match="not one-hot rows"):
            ReinforceLoss(actor)(batch)

    @pytest.mark.parametrize("distribution", ["tanh_normal", "normal"])
    def test_continuous_actor_scores_the_stored_action(self, distribution):
        torch.manual_seed(0)
        cls = {"tanh_normal": None, "normal": torch.distributions.Normal}[distribution]
        actor = (
            make_gaussian_actor() if cls is None else make_gaussian_actor(distribution_class=cls)
        )
        batch = make_batch(torch.rand(3, 7, N_ACT) * 1.8 - 0.9)
        out = ReinforceLoss(actor)(batch.clone())
        returns = reward_to_go(batch["next", "reward"], batch["next", "done"], 0.99)
        # Scoring a resampled action would make the loss random; the stored one is fixed.
        torch.testing.assert_close(out["loss_actor"], _surrogate(actor, batch, returns))
        torch.testing.assert_close(
            ReinforceLoss(actor)(batch.clone())["loss_actor"], out["loss_actor"]
        )

    def test_entropy_bonus(self, categorical_actor, categorical_batch):
        out = ReinforceLoss(categorical_actor, entropy_coeff=0.5)(categorical_batch)
        entropy = categorical_actor.get_dist(categorical_batch).entropy().mean()
        torch.testing.assert_close(out["entropy"], entropy.detach())
        torch.testing.assert_close(out["loss_entropy"], -0.5 * entropy)

    def test_entropy_without_closed_form_is_estimated(self):
        torch.manual_seed(0)
        actor = make_gaussian_actor()
        batch = make_batch(torch.rand(3, 7, N_ACT) * 1.8 - 0.9)
        out = ReinforceLoss(actor, entropy_coeff=0.1)(batch)
        assert torch.isfinite(out["loss_entropy"]) and out["loss_entropy"].requires_grad

    def test_the_estimated_entropy_is_the_entropy(self):
        # Every step's policy is tanh(u), u ~ N(0, 1) per action dimension, whose entropy
        # is that of N(0, 1) plus E[log(1 - tanh(u)^2)] (by quadrature): the mean of the
        # one-sample estimates over 4096 steps must be within 5 standard errors of it.
        torch.manual_seed(0)
        actor = make_gaussian_actor()
        for parameter in actor.parameters():
            torch.nn.init.zeros_(parameter)  # loc 0, scale 1 (softplus biased to 1 at 0)
        batch = make_batch(torch.rand(64, 64, N_ACT) * 1.8 - 0.9)
        out = ReinforceLoss(actor, entropy_coeff=0.1, reduction="none")(batch)
        u = torch.linspace(-12, 12, 200_001, dtype=torch.float64)
        density = torch.exp(-(u**2) / 2) / math.sqrt(2 * math.pi)
        jacobian = torch.trapezoid(density * torch.log1p(-(torch.tanh(u) ** 2)), u)
        exact = N_ACT * (0.5 * math.log(2 * math.pi * math.e) + jacobian.item())
        estimates = -out["loss_entropy"].detach() / 0.1
        error = estimates.std() / estimates.numel() ** 0.5
        assert abs(estimates.mean().item() - exact) < 5 * error.item(), (estimates.mean(), exact)

    # returns of spread 1, and of spread 1e-6, where the divisor's 1e-8 counts
    @pytest.mark.parametrize("scale", [1.0, 1e-6])
    def test_normalize_advantage(self, categorical_actor, categorical_batch, scale):
        categorical_batch["next", "reward"] *= scale
        out = ReinforceLoss(categorical_actor, normalize_advantage=True)(categorical_batch)
        returns = categorical_batch["value_target"]
        weights = (returns - returns.mean()) / (returns.std(unbiased=False) + 1e-8)
        expected = _surrogate(categorical_actor, categorical_batch, weights)
        torch.testing.assert_close(out["loss_actor"], expected)

    def test_scalar_baseline_is_subtracted(self, categorical_actor, categorical_batch):
        loss = ReinforceLoss(categorical_actor, baseline="batch_mean")
        out = loss(categorical_batch)
        returns = categorical_batch["value_target"]
        done = categorical_batch["next", "done"]
        starts = torch.cat([torch.ones_like(done[:, :1]), done[:, :-1]], dim=1)
        baseline = returns[starts].mean()
        torch.testing.assert_close(out["baseline"], baseline)
        expected = _surrogate(categorical_actor, categorical_batch, returns - baseline)
        torch.testing.assert_close(out["loss_actor"], expected)

    def test_without_done_flags_the_scalar_baseline_averages_every_kept_step(
        self, categorical_actor, categorical_batch
    ):
        # Returns given and no ("next", "done"): no episode's first step can be found, so
        # each step the padding keeps counts once.
        batch = categorical_batch.clone()
        batch["value_target"] = torch.randn(*batch.shape, 1)
        del batch["next", "done"], batch["next", "terminated"]
        mask = torch.ones(*batch.shape, 1, dtype=torch.bool)
        mask[0, -3:] = False
        batch["collector", "mask"] = mask
        out = ReinforceLoss(categorical_actor, baseline="batch_mean")(batch.clone())
        torch.testing.assert_close(out["baseline"], batch["value_target"][mask].mean())

    def test_baseline_state_is_in_state_dict(self, categorical_actor, categorical_batch):
        loss = ReinforceLoss(categorical_actor, baseline="running_mean")
        loss(categorical_batch)
        state = loss.state_dict()
        assert state["baseline_module.count"] > 0
        restored = ReinforceLoss(make_categorical_actor(), baseline="running_mean")
        restored.load_state_dict(state)
        assert restored.baseline_module.value == loss.baseline_module.value

    def test_critic_coeff_weights_the_value_loss(
        self, categorical_actor, critic, categorical_batch
    ):
        plain = ReinforceLoss(categorical_actor, critic)(categorical_batch.clone())
        weighted = ReinforceLoss(categorical_actor, critic, critic_coeff=2.0)(categorical_batch)
        torch.testing.assert_close(weighted["loss_value"], 2 * plain["loss_value"])

    def test_the_moving_averages_default_rate(self, categorical_actor):
        assert ReinforceLoss(categorical_actor, baseline="ema").baseline_module.rate == 0.01

    def test_eval_mode_does_not_update_the_baseline(self, categorical_actor, categorical_batch):
        loss = ReinforceLoss(categorical_actor, baseline="ema", baseline_rate=0.5).eval()
        loss(categorical_batch)
        assert loss.baseline_module.value == 0

    def test_non_functional_without_critic(self, categorical_actor, categorical_batch):
        functional = ReinforceLoss(categorical_actor)(categorical_batch.clone())
        plain = ReinforceLoss(categorical_actor, functional=False)(categorical_batch.clone())
        torch.testing.assert_close(plain["loss_actor"], functional["loss_actor"])

    @pytest.mark.parametrize("estimator", ["reward_to_go", "discounted_return"])
    @pytest.mark.parametrize("baseline", ["critic", "batch_mean"])
    def test_the_estimator_s_value_pass_is_regressed_as_it_is(
        self, categorical_actor, critic, categorical_batch, estimator, baseline
    ):
        """Non-functional, the critic loss regresses the V(s) the Monte-Carlo estimator
        computed (kept in the graph); TorchRL evaluates the critic on s once more. Same
        losses and gradients, a third fewer rows through the critic."""
        rows, results = [], []
        critic.register_forward_hook(lambda _, args, __: rows.append(args[0].numel()))
        for share in (True, False):
            loss = ReinforceLoss(categorical_actor, critic, functional=False, baseline=baseline)
            loss.make_value_estimator(estimator, gamma=0.9)
            if not share:
                loss._shares_critic_pass = lambda: False
            rows.clear()
            batch = categorical_batch.clone()
            out = loss(batch)
            loss.zero_grad()
            (out["loss_actor"] + out["loss_value"]).backward()
            grads = [p.grad.clone() for p in loss.parameters()]
            results.append((out, grads, batch, sum(rows)))
        (shared, shared_grads, shared_batch, shared_rows), (two, two_grads, two_batch, two_rows) = (
            results
        )
        steps = categorical_batch.numel()
        assert (shared_rows, two_rows) == (2 * steps, 3 * steps)
        for key in ("loss_actor", "loss_value", "advantage_mean"):
            torch.testing.assert_close(shared[key], two[key])
        for a, b in zip(shared_grads, two_grads, strict=True):
            torch.testing.assert_close(a, b)
        for key in ("state_value", "value_target", "advantage"):
            assert not shared_batch[key].requires_grad
            torch.testing.assert_close(shared_batch[key], two_batch[key])

    def test_flat_batch_of_episodes(self, categorical_actor, categorical_batch):
        flat = categorical_batch.reshape(-1)
        flat["next", "done"][6::7] = True  # each row's end is an episode end
        out = ReinforceLoss(categorical_actor)(flat)
        assert torch.isfinite(out["loss_actor"])

    def test_padding_is_ignored(self, categorical_actor, categorical_batch):
        # Two episodes (lengths 3 and 5) padded to [2, 5], as Collector(trajs_per_batch=...)
        # yields them, against the same episodes laid back to back.
        flat = categorical_batch.reshape(-1)[:8].clone()
        flat["next", "done"][:] = False
        flat["next", "done"][[2, 7]] = True
        padded = categorical_batch[:2, :5].clone().zero_()
        padded[0, :3] = flat[:3]
        padded[1, :5] = flat[3:]
        mask = torch.zeros(2, 5, 1, dtype=torch.bool)
        mask[0, :3] = mask[1, :5] = True
        padded["collector", "mask"] = mask
        losses = []
        for data in (flat, padded):
            loss = ReinforceLoss(categorical_actor, baseline="running_mean")
            losses.append((loss(data.clone()), loss.baseline_module.count.item()))
        (flat_out, flat_count), (padded_out, padded_count) = losses
        torch.testing.assert_close(padded_out["loss_actor"], flat_out["loss_actor"])
        torch.testing.assert_close(padded_out["advantage_mean"], flat_out["advantage_mean"])
        assert padded_count == flat_count == 2

    @pytest.mark.parametrize("baseline", ["running_mean", None])
    def test_what_measurements_read_of_the_loss_leaves_its_state_alone(
        self, categorical_actor, categorical_batch, baseline
    ):
        # The public reads the gradient statistics and the natural gradient build on.
        batch = categorical_batch.clone()
        mask = torch.ones(*batch.shape, 1, dtype=torch.bool)
        mask[0, -2:] = False
        batch["collector", "mask"] = mask
        loss = ReinforceLoss(categorical_actor, baseline=baseline)
        loss(categorical_batch.clone())  # the baseline has a state
        state = {k: v.clone() for k, v in loss.state_dict().items()}
        as_they_are = loss.weights_as_they_are(batch.clone())
        for key, value in loss.state_dict().items():
            assert torch.equal(value, state[key]), key
        if baseline is not None:  # and it goes on learning from the batches the loss takes
            assert loss.baseline_module.training
        weights, valid = loss.policy_weights(batch.clone())  # takes the batch in
        torch.testing.assert_close(as_they_are, weights)
        assert torch.equal(valid, mask) and torch.equal(loss.valid_steps(batch), mask)
        expected = categorical_actor.get_dist(batch).log_prob(batch["action"]).unsqueeze(-1)
        log_prob = loss.log_prob(batch)
        torch.testing.assert_close(log_prob, expected)
        assert log_prob.requires_grad
        starts = loss.episode_returns(batch, weights, valid)
        assert starts.numel() == int((batch["next", "done"][:, :-1] & mask[:, 1:]).sum()) + 3


class TestReinforceLossErrors:
    def test_unknown_baseline(self, categorical_actor):
        with pytest.raises(ValueError, match="baseline must be one of"):
            ReinforceLoss(categorical_actor, baseline="median")

    def test_critic_baseline_without_critic(self, categorical_actor):
        with pytest.raises(ValueError, match="baseline='critic' needs a critic_network"):
            ReinforceLoss(categorical_actor, baseline="critic")

    def test_negative_critic_coeff(self, categorical_actor, critic):
        with pytest.raises(ValueError, match="critic_coeff must be a finite number >= 0"):
            ReinforceLoss(categorical_actor, critic, critic_coeff=-1.0)

    def test_negative_entropy_coeff(self, categorical_actor):
        with pytest.raises(ValueError, match="entropy_coeff must be a finite number >= 0"):
            ReinforceLoss(categorical_actor, entropy_coeff=-0.1)

    def test_missing_actor(self):
        with pytest.raises(TypeError, match="needs an actor_network"):
            ReinforceLoss(critic_network=make_critic())

    def test_gamma_argument_is_rejected_like_torchrl(self, categorical_actor):
        with pytest.raises(TypeError, match="make_value_estimator"):
            ReinforceLoss(categorical_actor, gamma=0.9)

    def test_missing_action(self, categorical_actor, categorical_batch):
        del categorical_batch["action"]
        with pytest.raises(KeyError, match="no action entry 'action'"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    def test_missing_reward(self, categorical_actor, categorical_batch):
        del categorical_batch["next", "reward"]
        with pytest.raises(KeyError, match=r"no entry \('next', 'reward'\)"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    def test_empty_batch(self, categorical_actor, categorical_batch):
        with pytest.raises(ValueError, match="empty batch"):
            ReinforceLoss(categorical_actor)(categorical_batch[:, :0])

    def test_non_finite_reward(self, categorical_actor, categorical_batch):
        categorical_batch["next", "reward"][1, 3] = float("nan")
        with pytest.raises(ValueError, match="reward holds 1 non-finite"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    def test_non_finite_log_prob(self):
        torch.manual_seed(0)
        actor = make_gaussian_actor(distribution_class=torch.distributions.Normal)
        action = torch.zeros(3, 7, N_ACT)
        action[0, 0, 0] = float("inf")  # e.g. a diverged policy's sample stored by a collector
        batch = make_batch(action)
        with pytest.raises(ValueError, match="non-finite log-probabilities"):
            ReinforceLoss(actor)(batch)

    def test_returns_shape_mismatch(self, categorical_actor, categorical_batch):
        # Two reward channels give two returns per step, but the policy scores one action.
        categorical_batch["next", "reward"] = torch.randn(3, 7, 2)
        with pytest.raises(ValueError, match=r"'value_target' has shape \(3, 7, 2\)"):
            ReinforceLoss(categorical_actor)(categorical_batch)


def test_per_step_quantities_of_another_shape_are_named_as_they_came():
    # Two agents' log-probabilities per step against three agents' returns: refused, and
    # the message quotes the shape the policy gave, not one summed from it.
    with pytest.raises(ValueError, match=r"have shape \(3, 7, 2, 4\) but the returns have shape"):
        per_step(torch.zeros(3, 7, 2, 4), torch.Size([3, 7, 3, 1]), "log-probabilities")
    summed = per_step(torch.ones(3, 7, 2, 4), torch.Size([3, 7, 2, 1]), "log-probabilities")
    assert torch.equal(summed, torch.full((3, 7, 2, 1), 4.0))  # independent dimensions


def _bounded_actor(low, high):
    """A TanhNormal policy that declares its bounds through a Bounded spec."""
    low, high = torch.as_tensor(low), torch.as_tensor(high)
    net = torch.nn.Sequential(torch.nn.Linear(3, 2 * low.numel()), NormalParamExtractor())
    spec = Bounded(low, high, shape=low.shape)
    return ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": low, "high": high},
    )


class TestReinforceLossBadInput:
    """Malformed data or settings raise an error that names them, never a wrong loss."""

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"entropy_coeff": float("inf")}, "entropy_coeff must be a finite number >= 0"),
            ({"entropy_coeff": "0.1"}, "entropy_coeff must be a real number"),
            ({"critic_coeff": float("nan")}, "critic_coeff must be a finite number >= 0"),
            ({"baseline": "ema", "baseline_rate": 0.0}, r"baseline_rate must be .* > 0"),
            ({"baseline": "ema", "baseline_rate": 1.5}, r"baseline_rate must be .* <= 1"),
            ({"loss_critic_type": "huber"}, "loss_critic_type must be one of"),
            ({"reduction": "max"}, "reduction must be one of"),
            ({"clip_value": -0.5}, r"clip_value must be a finite number > 0"),
            ({"clip_value": float("nan")}, r"clip_value must be a finite number > 0"),
        ],
    )
    def test_bad_setting(self, categorical_actor, critic, kwargs, match):
        with pytest.raises((ValueError, TypeError), match=match):
            ReinforceLoss(categorical_actor, critic, **kwargs)

    @pytest.mark.parametrize(
        ("policy", "action", "distribution", "expected"),
        [
            ("categorical", torch.randint(N_ACT, (4, 4, 1)), "Categorical", (4, 4)),
            ("gaussian", torch.rand(4, 4, 1) - 0.5, "TanhNormal", (4, 4, N_ACT)),
            ("normal", torch.randn(4, 4, 1), "Normal", (4, 4, N_ACT)),
            ("one_hot", torch.randint(N_ACT, (4, 4)), "OneHotCategorical", (4, 4, N_ACT)),
        ],
    )
    def test_actions_shaped_unlike_the_policys_are_refused(
        self, policy, action, distribution, expected
    ):
        # log_prob would broadcast them against the policy's batch: a [*B, 1] categorical
        # action on a [4, 4] batch gave a finite, wrong loss.
        torch.manual_seed(0)
        actor = {
            "categorical": make_categorical_actor,
            "gaussian": make_gaussian_actor,
            "normal": lambda: make_gaussian_actor(distribution_class=torch.distributions.Normal),
            "one_hot": make_one_hot_actor,
        }[policy]()
        message = (
            f"The stored actions at 'action' have shape {tuple(action.shape)}, but the "
            f"policy's {distribution} scores actions of shape {expected}"
        )
        with pytest.raises(ValueError, match=re.escape(message)):
            ReinforceLoss(actor)(make_batch(action))

    @pytest.mark.parametrize("name", ["functional", "delay_value", "normalize_advantage"])
    def test_flags_must_be_booleans(self, categorical_actor, name):
        with pytest.raises(TypeError, match=f"{name} must be True or False"):
            ReinforceLoss(categorical_actor, **{name: "no"})

    def test_numpy_clip_value(self, categorical_actor, critic):
        loss = ReinforceLoss(categorical_actor, critic, clip_value=np.float32(0.5))
        assert loss.clip_value.item() == 0.5

    def test_numpy_numbers_are_numbers(self, categorical_actor, categorical_batch):
        loss = ReinforceLoss(categorical_actor, entropy_coeff=np.float32(0.01))
        assert loss.entropy_coeff == pytest.approx(0.01)
        assert torch.isfinite(loss(categorical_batch)["loss_entropy"])

    def test_actor_without_a_distribution(self):
        with pytest.raises(TypeError, match="must be a probabilistic policy with get_dist"):
            ReinforceLoss(torch.nn.Linear(3, 2))

    def test_critic_that_is_not_a_tensordict_module(self, categorical_actor):
        with pytest.raises(TypeError, match="critic_network must be a TensorDictModule"):
            ReinforceLoss(categorical_actor, torch.nn.Linear(3, 1))

    def test_batch_of_zero_rows(self, categorical_actor, categorical_batch):
        with pytest.raises(ValueError, match=r"empty batch \(batch_size=\(0, 7\)\)"):
            ReinforceLoss(categorical_actor)(categorical_batch[:0])

    def test_every_step_masked(self, categorical_actor, categorical_batch):
        categorical_batch["collector", "mask"] = torch.zeros(3, 7, dtype=torch.bool)
        with pytest.raises(ValueError, match="Every step of the batch is masked out"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    def test_fractional_action_for_a_categorical_policy(self, categorical_actor, categorical_batch):
        categorical_batch["action"] = categorical_batch["action"].float() + 0.5
        with pytest.raises(ValueError, match="not in the policy's support"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    def test_integral_float_action_is_scored(self, categorical_actor, categorical_batch):
        as_int = ReinforceLoss(categorical_actor)(categorical_batch.clone())
        categorical_batch["action"] = categorical_batch["action"].float()
        as_float = ReinforceLoss(categorical_actor)(categorical_batch)
        torch.testing.assert_close(as_float["loss_actor"], as_int["loss_actor"])

    def test_integer_actions_are_scored_as_categorical_log_prob_scores_them(
        self, categorical_actor, critic, categorical_batch
    ):
        # Integer actions are looked up in the logits directly; integral floats go through
        # Categorical.log_prob. Bit for bit the same loss and the same gradients.
        outputs, grads = [], []
        for action in (categorical_batch["action"], categorical_batch["action"].double()):
            batch = categorical_batch.clone()
            batch["action"] = action
            loss = ReinforceLoss(categorical_actor, critic, entropy_coeff=0.01)
            out = loss(batch)
            categorical_actor.zero_grad()
            critic.zero_grad()
            (out["loss_actor"] + out["loss_entropy"] + out["loss_value"]).backward()
            outputs.append(out)
            grads.append([p.grad.clone() for p in loss.parameters()])
        assert (outputs[0] == outputs[1]).all()
        assert all(torch.equal(g, h) for g, h in zip(*grads, strict=True))

    @pytest.mark.parametrize("bad", [-1, N_ACT])
    def test_categorical_action_out_of_range(self, categorical_actor, categorical_batch, bad):
        categorical_batch["action"][0, 0] = bad
        with pytest.raises(ValueError, match=f"for example {bad}"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    @pytest.mark.parametrize("row", [[0, 0, 0, 0], [1, 1, 0, 0], [0.5, 0.5, 0, 0]])
    def test_invalid_one_hot_action(self, row):
        torch.manual_seed(0)
        actor = make_one_hot_actor()
        action = torch.nn.functional.one_hot(torch.randint(N_ACT, (3, 7)), N_ACT).float()
        action[1, 2] = torch.tensor(row, dtype=torch.float)
        with pytest.raises(ValueError, match="1 stored action"):
            ReinforceLoss(actor)(make_batch(action))

    @pytest.mark.parametrize(
        ("low", "high", "action"),
        [([-2.0], [2.0], [2.5]), ([-1.0, 0.0], [1.0, 5.0], [0.5, -0.1])],
    )
    def test_action_outside_declared_bounds(self, low, high, action):
        torch.manual_seed(0)
        actions = torch.zeros(3, 7, len(low)).clamp(torch.tensor(low), torch.tensor(high))
        actions[2, 6] = torch.tensor(action)
        with pytest.raises(ValueError, match=r"1 stored action.* not inside the policy's bounds"):
            ReinforceLoss(_bounded_actor(low, high))(make_batch(actions))

    @pytest.mark.parametrize("declared", ["spec", "distribution_kwargs", "nested_spec"])
    def test_bounds_declared_either_way_are_enforced(self, declared):
        # A Bounded spec alone (at the action's key, nested or not), or low and high
        # given to the distribution alone: both declare the bounds [-1, 1].
        torch.manual_seed(0)
        low, high = torch.tensor([-1.0]), torch.tensor([1.0])
        key = ("agent", "action") if declared == "nested_spec" else "action"
        if declared == "distribution_kwargs":
            declaration = {"distribution_kwargs": {"low": low, "high": high}}
        elif declared == "spec":
            declaration = {"spec": Bounded(low, high, shape=(1,))}
        else:
            declaration = {"spec": Composite({key: Bounded(low, high, shape=(1,))})}
        net = torch.nn.Sequential(torch.nn.Linear(3, 2), NormalParamExtractor())
        actor = ProbabilisticActor(
            TensorDictModule(net, ["observation"], ["loc", "scale"]),
            in_keys=["loc", "scale"],
            out_keys=[key],
            distribution_class=TanhNormal,
            **declaration,
        )
        actions = torch.zeros(3, 7, 1)
        actions[2, 6] = 1.5
        batch = make_batch(actions)
        batch[key] = batch.pop("action")
        loss = ReinforceLoss(actor)
        loss.set_keys(action=key)
        with pytest.raises(ValueError, match=r"1 stored action.* not inside the policy's bounds"):
            loss(batch)

    def test_actions_on_the_declared_bounds_are_scored(self):
        torch.manual_seed(0)
        actions = torch.tensor([-2.0, 2.0]).repeat(3, 4)[:, :7, None]
        out = ReinforceLoss(_bounded_actor([-2.0], [2.0]))(make_batch(actions))
        assert torch.isfinite(out["loss_actor"])

    def test_nan_observation(self, categorical_actor, categorical_batch):
        categorical_batch["observation"][1, 1, 0] = float("nan")
        with pytest.raises(ValueError, match=r"input .observation. holds 1 NaN/inf value"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    @pytest.mark.parametrize("key", ["value_target", "advantage"])
    def test_non_finite_precomputed_returns(
        self, categorical_actor, critic, categorical_batch, key
    ):
        GAE(gamma=0.9, lmbda=0.9, value_network=critic)(categorical_batch)
        categorical_batch[key][0, 3] = float("nan")
        loss = ReinforceLoss(
            categorical_actor, critic, baseline="critic" if key == "advantage" else "running_mean"
        )
        with pytest.raises(ValueError, match=f"'{key}' holds .*non-finite"):
            loss(categorical_batch)
        if loss.baseline_module is not None:  # nothing was taken into the baseline
            assert loss.baseline_module.count == 0

    def test_nan_reward_through_torchrl_s_estimator(
        self, categorical_actor, critic, categorical_batch
    ):
        categorical_batch["next", "reward"][2, 2] = float("nan")
        loss = ReinforceLoss(categorical_actor, critic)  # GAE, which does not check rewards
        with pytest.raises(
            ValueError, match=r"'advantage' holds .* \('next', 'reward'\) holds NaN"
        ):
            loss(categorical_batch)

    def test_nan_from_the_value_network(self, categorical_actor, categorical_batch):
        critic = make_critic()
        with torch.no_grad():
            critic.module.bias.fill_(float("nan"))
        with pytest.raises(ValueError, match="the value network gave NaN/inf"):
            ReinforceLoss(categorical_actor, critic)(categorical_batch)

    def test_precomputed_returns_of_the_wrong_shape(self, categorical_actor, categorical_batch):
        categorical_batch["value_target"] = torch.zeros(3, 7, 2)
        with pytest.raises(ValueError, match=r"'value_target' has shape \(3, 7, 2\)"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    def test_precomputed_returns_without_the_trailing_dim(
        self, categorical_actor, categorical_batch
    ):
        with_dim = ReinforceLoss(categorical_actor)(categorical_batch.clone())
        categorical_batch["value_target"] = reward_to_go(
            categorical_batch["next", "reward"], categorical_batch["next", "done"], 0.99
        ).squeeze(-1)
        without = ReinforceLoss(categorical_actor)(categorical_batch)
        torch.testing.assert_close(without["loss_actor"], with_dim["loss_actor"])

    def test_critic_output_that_broadcasts(self, categorical_actor, categorical_batch):
        flat = TensorDictModule(
            _SumObservation(), in_keys=["observation"], out_keys=["state_value"]
        )
        loss = ReinforceLoss(categorical_actor, flat, baseline="running_mean")
        categorical_batch["value_target"] = torch.zeros(3, 7, 1)
        with pytest.raises(
            ValueError, match=r"critic's 'state_value' does not have the shape of 'value_target'"
        ):
            loss(categorical_batch)


class TestReinforceLossKeysAndMasks:
    @pytest.mark.parametrize("key", [3, ("next", 3), (), ["action"]])
    def test_set_keys_refuses_what_is_not_a_key(self, categorical_actor, key):
        with pytest.raises(TypeError, match=r"set_keys\(action=...\) must be a string or a tuple"):
            ReinforceLoss(categorical_actor).set_keys(action=key)

    def test_set_keys_none_restores_the_default(self, categorical_actor):
        loss = ReinforceLoss(categorical_actor)
        loss.set_keys(action="act")
        loss.set_keys(action=None)
        assert loss.tensor_keys.action == "action"

    def test_unknown_value_estimator(self, categorical_actor):
        with pytest.raises(KeyError, match=r"Unknown value estimator 'bogus'.*'reward_to_go'"):
            ReinforceLoss(categorical_actor).make_value_estimator("bogus")

    def test_padding_mask_that_is_not_boolean(self, categorical_actor, categorical_batch):
        categorical_batch["collector", "mask"] = torch.ones(3, 7)
        with pytest.raises(TypeError, match=r"padding mask .* must be boolean"):
            ReinforceLoss(categorical_actor)(categorical_batch)

    def test_padding_mask_with_several_values_per_step(self, categorical_actor, categorical_batch):
        categorical_batch["collector", "mask"] = torch.ones(3, 7, 2, dtype=torch.bool)
        with pytest.raises(ValueError, match="needs one value per step of the batch"):
            ReinforceLoss(categorical_actor)(categorical_batch)


class TestValueLoss:
    """``value_loss``: the critic's loss alone, for more critic steps per batch."""

    @pytest.mark.parametrize("padded", [False, True])
    def test_it_is_forwards_loss_value(self, categorical_actor, critic, categorical_batch, padded):
        if padded:  # padding steps hold garbage that must not count
            mask = torch.ones(3, 7, 1, dtype=torch.bool)
            mask[0, 4:] = mask[2, 2:] = False
            categorical_batch["collector", "mask"] = mask
            categorical_batch["next", "reward"][~mask] = 1e6
        loss = ReinforceLoss(categorical_actor, critic, critic_coeff=0.5)
        out = loss(categorical_batch)
        torch.testing.assert_close(loss.value_loss(categorical_batch), out["loss_value"])

    def test_steps_on_it_fit_the_critic_and_leave_the_actor_alone(
        self, categorical_actor, critic, categorical_batch
    ):
        loss = ReinforceLoss(categorical_actor, critic)
        first = loss(categorical_batch)["loss_value"].item()
        actor_before = [p.detach().clone() for p in categorical_actor.parameters()]
        optimizer = torch.optim.Adam(loss.parameters(), lr=0.05)
        for _ in range(50):
            optimizer.zero_grad(set_to_none=True)
            loss.value_loss(categorical_batch).backward()
            optimizer.step()
        assert loss.value_loss(categorical_batch).item() < 0.9 * first
        for before, after in zip(actor_before, categorical_actor.parameters(), strict=True):
            assert torch.equal(before, after)

    @pytest.mark.parametrize("padded", [False, True])
    def test_the_value_kept_by_policy_weights_gives_the_same_loss_and_gradient(
        self, categorical_actor, critic, categorical_batch, padded
    ):
        if padded:
            mask = torch.ones(3, 7, 1, dtype=torch.bool)
            mask[1, 3:] = False
            categorical_batch["collector", "mask"] = mask
        loss = ReinforceLoss(categorical_actor, critic, critic_coeff=0.5, functional=False)
        loss.make_value_estimator("reward_to_go", gamma=0.9)
        weights, valid, value = loss.policy_weights(categorical_batch.clone(), keep_value=True)
        assert value is not None and value.requires_grad
        batch = categorical_batch.clone()
        expected_weights, expected_valid = loss.policy_weights(batch)
        torch.testing.assert_close(weights, expected_weights)
        assert (valid is None) == (expected_valid is None) == (not padded)
        if padded:
            assert torch.equal(valid, expected_valid)
        kept = loss.value_loss(batch, value=value)
        called = loss.value_loss(batch)
        torch.testing.assert_close(kept, called)
        grads = [torch.autograd.grad(x, list(critic.parameters())) for x in (kept, called)]
        for a, b in zip(*grads, strict=True):
            torch.testing.assert_close(a, b)

    @pytest.mark.parametrize(
        "setting, returns", [({"clip_value": 0.5}, "reward_to_go"), ({"functional": True},
        "reward_to_go"), ({}, "gae")]
    )  # fmt: skip
    def test_no_value_is_kept_where_the_returns_pass_is_not_plain(
        self, categorical_actor, critic, categorical_batch, setting, returns
    ):
        loss = ReinforceLoss(categorical_actor, critic, **{"functional": False, **setting})
        loss.make_value_estimator(returns, gamma=0.9)
        *_, value = loss.policy_weights(categorical_batch, keep_value=True)
        assert value is None

    def test_a_detached_or_clipped_value_is_refused(
        self, categorical_actor, critic, categorical_batch
    ):
        loss = ReinforceLoss(categorical_actor, critic, functional=False)
        loss.make_value_estimator("reward_to_go", gamma=0.9)
        *_, value = loss.policy_weights(categorical_batch, keep_value=True)
        with pytest.raises(ValueError, match="detached from the critic: its loss"):
            loss.value_loss(categorical_batch, value=value.detach())
        clipped = ReinforceLoss(categorical_actor, critic, clip_value=0.5)
        clipped(categorical_batch)
        with pytest.raises(ValueError, match="skips clip_value's and value_norm's"):
            clipped.value_loss(categorical_batch, value=value)

    def test_without_a_critic(self, categorical_actor, categorical_batch):
        loss = ReinforceLoss(categorical_actor)
        loss(categorical_batch)
        with pytest.raises(ValueError, match="no critic: value_loss needs a critic_network"):
            loss.value_loss(categorical_batch)

    def test_before_the_targets_are_computed(self, categorical_actor, critic, categorical_batch):
        with pytest.raises(KeyError, match="no value target 'value_target' yet: call the loss"):
            ReinforceLoss(categorical_actor, critic).value_loss(categorical_batch)


class _SumObservation(torch.nn.Module):
    """A 'critic' that forgets the trailing value dimension."""

    def __init__(self) -> None:
        super().__init__()
        self.weight = torch.nn.Parameter(torch.ones(()))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.weight * observation.sum(-1)


def test_invalid_distribution_parameters_name_the_input(categorical_actor, categorical_batch):
    # TorchRL turns argument validation off; a user who turns it back on gets the same
    # diagnosis from the distribution's own check.
    categorical_batch["observation"][0, 0, 0] = float("inf")
    torch.distributions.Distribution.set_default_validate_args(True)
    try:
        # the first line of torch's own message, and the input named
        match = r"invalid distribution from this batch \(Expected parameter logits .*invalid "
        match += r"values:\)\. The policy's input 'observation'"
        with pytest.raises(ValueError, match=match):
            ReinforceLoss(categorical_actor)(categorical_batch)
    finally:
        torch.distributions.Distribution.set_default_validate_args(False)


def test_a_policy_that_diverged_on_finite_inputs_is_named_so(categorical_actor, categorical_batch):
    with torch.no_grad():
        categorical_actor.module[0].module.weight[0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite log-probabilities") as raised:
        ReinforceLoss(categorical_actor)(categorical_batch)
    assert "weights diverged" in str(raised.value) and "holds" not in str(raised.value)


# ---------------------------------------------------------------------------------------
# Malformed batches: finite losses that match the hand-computed surrogate, or an error
# that names what was wrong; never a non-finite or silently wrong loss.

_LOSS_CORRUPTIONS = {  # corruption -> what the error must name (None: still valid)
    "fractional_action": "action",
    "action_out_of_range": "action",
    "float_whole_action": None,
    "nan_reward": "reward",
    "fractional_done": "done",
    "nan_observation": "observation",
    "nan_value_target": "value_target",
    "value_target_shape": "value_target",
    "value_target_without_dim": None,
    "empty_batch": "empty batch",
    "all_masked": "masked",
    "missing_action": "action",
}


@st.composite
def malformed_batches(draw):
    rows, steps = draw(st.integers(1, 3)), draw(st.integers(1, 6))
    seed = draw(st.integers(0, 2**31 - 1))
    generator = torch.Generator().manual_seed(seed)
    batch = make_batch(torch.randint(N_ACT, (rows, steps), generator=generator), seed=seed)
    with torch.no_grad():
        batch["value_target"] = reward_to_go(batch["next", "reward"], batch["next", "done"], 0.9)
    at = (draw(st.integers(0, rows - 1)), draw(st.integers(0, steps - 1)))
    names = draw(st.lists(st.sampled_from(sorted(_LOSS_CORRUPTIONS)), max_size=2, unique=True))
    for name in names:
        if name == "fractional_action":
            batch["action"] = batch["action"].float()
            batch["action"][at] = 1.5
        elif name == "action_out_of_range":
            batch["action"][at] = draw(st.sampled_from([-1, N_ACT]))
        elif name == "float_whole_action":
            batch["action"] = batch["action"].float()
        elif name == "nan_reward":
            batch["next", "reward"][at] = float("nan")
        elif name == "fractional_done":
            batch["next", "done"] = batch["next", "done"].float()
            batch["next", "done"][at] = 0.5
        elif name == "nan_observation":
            batch["observation"][at] = float("nan")
        elif name == "nan_value_target":
            batch["value_target"][at] = float("nan")
        elif name == "value_target_shape":
            batch["value_target"] = torch.zeros(rows, steps, 2)
        elif name == "value_target_without_dim":
            batch["value_target"] = batch["value_target"].squeeze(-1)
        elif name == "all_masked":
            batch["collector", "mask"] = torch.zeros(*batch.shape, dtype=torch.bool)
    precomputed = {"nan_value_target", "value_target_shape", "value_target_without_dim"}
    reads_the_data = {"nan_reward", "fractional_done"} & set(names)
    if reads_the_data or (draw(st.booleans()) and not precomputed & set(names)):
        del batch["value_target"]  # the loss's own estimator computes it from the data
    if "missing_action" in names:
        del batch["action"]
    if "empty_batch" in names:
        batch = batch[:0]
    return batch, names


@settings(max_examples=300, deadline=None)
@given(problem=malformed_batches())
def test_malformed_batches_give_a_correct_loss_or_a_clear_error(problem):
    batch, names = problem
    torch.manual_seed(0)
    actor = make_categorical_actor()
    loss = ReinforceLoss(actor)
    loss.make_value_estimator("reward_to_go", gamma=0.9)
    expected_names = {_LOSS_CORRUPTIONS[n] for n in names} - {None}
    try:
        out = loss(batch.clone())
    except (ValueError, TypeError, KeyError) as err:
        assert expected_names, f"valid batch ({names}) refused: {err}"
        assert any(name in str(err) for name in expected_names), (names, str(err))
        return
    assert not expected_names, f"{names} went through: {out['loss_actor']}"
    assert torch.isfinite(out["loss_actor"])
    returns = reward_to_go(batch["next", "reward"], batch["next", "done"].bool(), 0.9)
    torch.testing.assert_close(out["loss_actor"], _surrogate(actor, batch, returns))


def test_a_composite_action_weights_the_sum_of_its_parts_log_probabilities():
    """Two categorical heads (tensordict's CompositeDistribution): log pi(a) is the sum
    of the heads' log-probabilities, and so is the entropy."""
    torch.manual_seed(0)
    actor = make_composite_actor()
    batch = make_batch(torch.zeros(2, 6, dtype=torch.long), n_obs=3, seed=1)
    del batch["action"]
    with torch.no_grad():
        actor(batch)
    loss = ReinforceLoss(actor, None, baseline="none", entropy_coeff=0.1)
    out = loss(batch)
    logits_a, logits_b = actor.module[0].module(batch["observation"])
    log_prob = torch.distributions.Categorical(logits=logits_a).log_prob(
        batch["action", "a"]
    ) + torch.distributions.Categorical(logits=logits_b).log_prob(batch["action", "b"])
    returns = reward_to_go(batch["next", "reward"], batch["next", "done"], 0.99)  # its default
    torch.testing.assert_close(out["loss_actor"], -(log_prob * returns.squeeze(-1)).mean())
    entropy = (
        torch.distributions.Categorical(logits=logits_a).entropy()
        + torch.distributions.Categorical(logits=logits_b).entropy()
    )
    torch.testing.assert_close(out["entropy"], entropy.mean())


def _grouped_episodes(lengths, groups, greedy=None, seed=0):
    """Episodes as the rows of a padded ``[E, T]`` batch (``("collector", "mask")``),
    with their groups (and greedy flags) on every step."""
    generator = torch.Generator().manual_seed(seed)
    n, width = len(lengths), max(lengths)
    mask = torch.arange(width) < torch.tensor(lengths).unsqueeze(-1)
    done = torch.zeros(n, width, dtype=torch.bool)
    done[torch.arange(n), torch.tensor(lengths) - 1] = True
    entries = {
        "observation": torch.randn(n, width, 3, generator=generator),
        "action": torch.randint(0, N_ACT, (n, width), generator=generator),
        "group": torch.tensor(groups).unsqueeze(-1).expand(n, width),
        "collector": {"mask": mask},
        "next": {
            "observation": torch.randn(n, width, 3, generator=generator),
            "reward": torch.randn(n, width, 1, generator=generator),
            "done": done.unsqueeze(-1),
            "terminated": done.unsqueeze(-1).clone(),
        },
    }
    if greedy is not None:
        entries["greedy"] = torch.tensor(greedy).unsqueeze(-1).expand(n, width)
    return TensorDict(entries, batch_size=[n, width])


def _flat(batch):
    """The same episodes back to back, batch size ``[steps]``, without padding."""
    return batch[batch["collector", "mask"]].exclude("collector")


def _expected_weights(batch, baseline, gamma, whole_episode, scale=False):
    """The group advantage of every valid step, by the plain loop of test_groups."""
    from test_groups import reference_advantage

    mask = batch["collector", "mask"]
    reward = batch["next", "reward"].squeeze(-1)
    rows = []
    for row, valid in zip(reward.tolist(), mask.tolist(), strict=True):
        r = [x for x, v in zip(row, valid, strict=True) if v]
        to_go = [sum(gamma**k * x for k, x in enumerate(r[t:])) for t in range(len(r))]
        rows.append([to_go[0]] if whole_episode else to_go)
    width = max(map(len, rows))
    padded = [row + [0.0] * (width - len(row)) for row in rows]
    group = batch["group"][:, 0].tolist()
    greedy = batch["greedy"][:, 0].tolist() if "greedy" in batch.keys() else [False] * len(rows)
    advantage = reference_advantage(padded, group, baseline, greedy, scale)
    weights = torch.zeros(mask.shape, dtype=torch.float64)
    for i, length in enumerate(mask.sum(-1).tolist()):
        for t in range(length):
            weights[i, t] = advantage[i][0 if whole_episode else t]
    return weights


def _grouped_loss(actor, baseline, estimator=RewardToGo, gamma=0.9, **kwargs):
    loss = ReinforceLoss(actor, baseline=baseline, **kwargs)
    loss.make_value_estimator(estimator, gamma=gamma)
    return loss


class TestReinforceLossGroupBaselines:
    LENGTHS = (3, 5, 1, 4, 2, 6, 2)
    GROUPS = (7, 7, 7, 2, 2, 2, 2)

    @pytest.mark.parametrize("baseline", ["leave_one_out", "group_mean"])
    @pytest.mark.parametrize("estimator", [RewardToGo, DiscountedReturn])
    @pytest.mark.parametrize("scale", [False, True])
    def test_weights_are_those_of_a_plain_loop(self, categorical_actor, baseline, estimator, scale):
        batch = _grouped_episodes(self.LENGTHS, self.GROUPS)
        loss = _grouped_loss(categorical_actor, baseline, estimator, group_scale=scale)
        out = loss(batch.clone())
        weights = _expected_weights(batch, baseline, 0.9, estimator is DiscountedReturn, scale)
        mask = batch["collector", "mask"]
        log_prob = categorical_actor.get_dist(batch).log_prob(batch["action"])
        expected = -(log_prob.double() * weights)[mask].mean()
        torch.testing.assert_close(out["loss_actor"].double(), expected, rtol=1e-5, atol=1e-6)

    @pytest.mark.parametrize("baseline", ["leave_one_out", "group_mean"])
    def test_padded_rows_and_episodes_back_to_back_give_the_same_loss(
        self, categorical_actor, baseline
    ):
        batch = _grouped_episodes(self.LENGTHS, self.GROUPS)
        loss = _grouped_loss(categorical_actor, baseline)
        padded, flat = loss(batch.clone()), loss(_flat(batch))
        torch.testing.assert_close(padded["loss_actor"], flat["loss_actor"])

    def test_the_greedy_episodes_give_the_baseline_and_nothing_else(
        self, categorical_actor, critic
    ):
        greedy = [False, False, True, False, True, False, False]
        batch = _grouped_episodes(self.LENGTHS, self.GROUPS, greedy)
        loss = _grouped_loss(categorical_actor, "greedy", critic_network=critic, entropy_coeff=0.1)
        loss.make_value_estimator(RewardToGo, gamma=0.9)  # V(s) only bootstraps
        out = loss(batch.clone())
        weights = _expected_weights(batch, "greedy", 0.9, False)
        sampled = batch["collector", "mask"] & ~batch["greedy"].squeeze(-1)
        dist = categorical_actor.get_dist(batch)
        expected = -(dist.log_prob(batch["action"]).double() * weights)[sampled].mean()
        torch.testing.assert_close(out["loss_actor"].double(), expected, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(out["loss_entropy"], -0.1 * dist.entropy()[sampled].mean())
        torch.testing.assert_close(out["entropy"], dist.entropy()[sampled].mean())
        assert torch.equal(loss.valid_steps(batch).squeeze(-1), sampled)
        padding = loss.valid_steps(batch, greedy=True).squeeze(-1)
        assert torch.equal(padding, batch["collector", "mask"].reshape(padding.shape))
        assert {"greedy", "group"} <= set(loss.in_keys)
        # The greedy steps' observations and actions reach no loss term.
        changed = batch.clone()
        on_greedy = changed["greedy"].squeeze(-1)
        changed["observation"][on_greedy] = 100.0
        changed["action"][on_greedy] = 0
        again = loss(changed)
        for key in ("loss_actor", "loss_entropy", "loss_value"):
            torch.testing.assert_close(again[key], out[key])
        torch.testing.assert_close(loss.value_loss(changed), out["loss_value"])

    def test_a_renamed_group_key_is_read(self, categorical_actor):
        batch = _grouped_episodes(self.LENGTHS, self.GROUPS)
        loss = _grouped_loss(categorical_actor, "leave_one_out")
        expected = loss(batch.clone())["loss_actor"]
        batch.rename_key_("group", ("collector", "start"))
        loss.set_keys(group=("collector", "start"))
        assert ("collector", "start") in loss.in_keys
        torch.testing.assert_close(loss(batch)["loss_actor"], expected)

    def test_group_scale_needs_a_group_baseline(self, categorical_actor):
        with pytest.raises(ValueError, match="group_scale divides a group baseline"):
            ReinforceLoss(categorical_actor, baseline="batch_mean", group_scale=True)

    @pytest.mark.parametrize(
        ("change", "error", "match"),
        [
            (lambda b: b.exclude("group"), KeyError, r"baseline='leave_one_out': the key group"),
            (lambda b: b.set("group", b["group"].float()), TypeError, "integer group ids"),
            (lambda b: b.set("group", b["group"].unsqueeze(-1).expand(7, 6, 2)), ValueError,
             "one value per step"),
            (lambda b: b.set("group", torch.arange(42).reshape(7, 6)), ValueError,
             "changes inside an episode"),
            (lambda b: b.set(("next", "done"), torch.zeros(7, 6, 1, dtype=torch.bool)),
             ValueError, "cut by the batch"),
            (lambda b: b.set("group", torch.arange(7).unsqueeze(-1).expand(7, 6)),
             ValueError, "at least 2 sampled episodes"),
        ],
    )  # fmt: skip
    def test_bad_groups_are_refused(self, categorical_actor, change, error, match):
        batch = change(_grouped_episodes(self.LENGTHS, self.GROUPS))
        with pytest.raises(error, match=match):
            _grouped_loss(categorical_actor, "leave_one_out")(batch)

    def test_greedy_flags_are_required(self, categorical_actor):
        batch = _grouped_episodes(self.LENGTHS, self.GROUPS)
        with pytest.raises(KeyError, match=r"baseline='greedy': the key greedy"):
            _grouped_loss(categorical_actor, "greedy")(batch)

    def test_greedy_flags_that_are_not_boolean(self, categorical_actor):
        greedy = [False, False, True, False, True, False, False]
        batch = _grouped_episodes(self.LENGTHS, self.GROUPS, greedy)
        batch["greedy"] = batch["greedy"].long()
        with pytest.raises(TypeError, match="'greedy' must be boolean"):
            _grouped_loss(categorical_actor, "greedy")(batch)
