"""NaturalGradient: the step's length in KL, the line search, the policies it takes, its
checks, and learning with it. (Its direction against the exact natural gradient:
tests/test_exact_gradients.py.)"""

from __future__ import annotations

import copy

import pytest
import torch
from conftest import make_batch, make_categorical_actor, make_critic, make_gaussian_actor
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, ValueOperator

from rl_pg import ReinforceLoss
from rl_pg.natural_gradient import NaturalGradient
from rl_pg.policy_kl import kl_per_step, masked_mean


def _flat_parameters(update: NaturalGradient) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1).clone() for p in update.parameters])


def _measured_kl(actor, batch, old_state) -> float:
    """KL(old || new) on the batch, the old policy rebuilt from its saved weights."""
    new_state = {k: v.clone() for k, v in actor.state_dict().items()}
    with torch.no_grad():
        new = actor.get_dist(batch)
        actor.load_state_dict(old_state)
        old = actor.get_dist(batch)
        actor.load_state_dict(new_state)
    return float(masked_mean(kl_per_step(old, new, batch), None))


def _batch(seed=0):
    torch.manual_seed(seed)
    return make_batch(torch.randint(0, 4, (6, 10)), p_done=0.2, seed=seed)


class TestNaturalGradient:
    @pytest.mark.parametrize("max_kl", [0.001, 0.01])
    def test_a_step_moves_the_policy_by_about_max_kl(self, max_kl):
        torch.manual_seed(0)
        actor = make_categorical_actor()
        update = NaturalGradient(ReinforceLoss(actor), max_kl=max_kl, line_search=False)
        batch = _batch()
        old = {k: v.clone() for k, v in actor.state_dict().items()}
        out = update.step(batch)
        kl = _measured_kl(actor, batch, old)
        # The quadratic model of the KL is good for small steps.
        assert kl == pytest.approx(max_kl, rel=0.2)
        assert float(out["kl"]) == pytest.approx(kl, rel=1e-4)
        assert float(out["step_fraction"]) == 1.0

    def test_the_first_order_gain_is_what_the_step_predicts(self):
        torch.manual_seed(1)
        actor = make_categorical_actor()
        update = NaturalGradient(ReinforceLoss(actor), max_kl=1e-4)
        out = update.step(_batch(1))
        assert float(out["improvement"]) == pytest.approx(
            float(out["expected_improvement"]), rel=0.05
        )

    def test_a_step_no_trial_accepts_is_not_taken(self):
        # Two arms, reward for arm 0: the loss -log p0 saturates, so a step of KL 10
        # gains far less than its linear prediction at every backtrack.
        linear = nn.Linear(1, 2, bias=False)
        nn.init.zeros_(linear.weight)
        actor = ProbabilisticActor(
            TensorDictModule(linear, ["observation"], ["logits"]),
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
        )
        batch = TensorDict(
            {
                "observation": torch.ones(4, 1),
                "action": torch.tensor([0, 1, 0, 1]),
                "next": {"reward": torch.tensor([[1.0], [0.0], [1.0], [0.0]]),
                         "done": torch.ones(4, 1, dtype=torch.bool)},
            },
            batch_size=[4],
        )  # fmt: skip
        update = NaturalGradient(ReinforceLoss(actor), max_kl=10.0, accept_ratio=0.99)
        before = _flat_parameters(update)
        out = update.step(batch)
        assert torch.equal(_flat_parameters(update), before)
        assert float(out["step_fraction"]) == 0.0 and float(out["kl"]) == 0.0
        # Without the line search the same step is taken.
        update = NaturalGradient(ReinforceLoss(actor), max_kl=10.0, line_search=False)
        assert float(update.step(batch)["kl"]) > 1.0

    def test_no_signal_no_step(self, categorical_actor):
        batch = _batch()
        batch["next", "reward"] = torch.zeros_like(batch["next", "reward"])
        update = NaturalGradient(ReinforceLoss(categorical_actor))
        before = _flat_parameters(update)
        out = update.step(batch)
        assert torch.equal(_flat_parameters(update), before)
        assert float(out["step_fraction"]) == 0.0

    @pytest.mark.parametrize("distribution", ["normal", "tanh_normal"])
    def test_continuous_policies(self, distribution):
        # A Normal has a closed-form KL; a TanhNormal has none: its Fisher is the
        # stored actions' scores' outer product, its KL estimated from them.
        from torchrl.modules import TanhNormal

        torch.manual_seed(2)
        kind = {"normal": torch.distributions.Normal, "tanh_normal": TanhNormal}[distribution]
        actor = make_gaussian_actor(n_act=2, distribution_class=kind)
        root = TensorDict({"observation": torch.randn(64, 3)}, batch_size=[64])
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
            action = actor(root)["action"]
        batch = make_batch(torch.zeros(64, 1, 2), seed=2).reshape(64)
        batch.update({"observation": root["observation"], "action": action})
        old = {k: v.clone() for k, v in actor.state_dict().items()}
        update = NaturalGradient(ReinforceLoss(actor), max_kl=0.005, line_search=False)
        out = update.step(batch)
        if distribution == "normal":
            assert _measured_kl(actor, batch, old) == pytest.approx(0.005, rel=0.3)
        else:  # the sampled Fisher on 64 actions: the KL is near, not at, the target
            assert 0.001 < float(out["kl"]) < 0.02
        assert float(out["improvement"]) > 0

    def test_the_critic_is_left_to_its_own_optimiser(self, categorical_actor, critic):
        loss = ReinforceLoss(categorical_actor, critic)
        update = NaturalGradient(loss)
        critic_before = [p.detach().clone() for p in critic.parameters()]
        batch = _batch()
        update.step(batch)
        assert all(torch.equal(a, b) for a, b in zip(critic_before, critic.parameters(),
                                                     strict=True))  # fmt: skip
        optimiser = torch.optim.Adam(critic.parameters(), lr=0.01)
        loss.value_loss(batch).backward()  # the targets the step wrote
        optimiser.step()
        assert not torch.equal(critic_before[0], next(critic.parameters()))

    @pytest.mark.parametrize("fisher", ["exact", "kfac"])
    def test_weights_taken_beforehand_give_the_same_step(self, categorical_actor, critic, fisher):
        steps = []
        for given in (False, True):
            actor = copy.deepcopy(categorical_actor)
            loss = ReinforceLoss(actor, copy.deepcopy(critic), functional=False)
            loss.make_value_estimator("reward_to_go", gamma=0.99)
            batch = _batch()
            torch.manual_seed(1)
            if given:
                weights, valid, value = loss.policy_weights(batch, keep_value=True)
                out = NaturalGradient(loss, fisher=fisher).step(batch, weights, valid)
                assert value is not None
            else:
                out = NaturalGradient(loss, fisher=fisher).step(batch)
            steps.append((out, [p.detach().clone() for p in actor.parameters()]))
        (out_a, after_a), (out_b, after_b) = steps
        for a, b in zip(after_a, after_b, strict=True):
            torch.testing.assert_close(a, b)
        torch.testing.assert_close(out_a["kl"], out_b["kl"])

    def test_weights_and_valid_go_together(self, categorical_actor):
        loss = ReinforceLoss(categorical_actor)
        batch = _batch()
        batch["collector", "mask"] = torch.ones(6, 10, 1, dtype=torch.bool)
        batch["collector", "mask"][0, 5:] = False
        weights, valid = loss.policy_weights(batch)
        update = NaturalGradient(loss)
        with pytest.raises(ValueError, match="weights without valid for a batch with steps"):
            update.step(batch, weights)
        with pytest.raises(ValueError, match="valid without weights"):
            update.step(batch, valid=valid)
        assert float(update.step(batch, weights, valid)["kl"]) > 0

    def test_a_critic_that_shares_the_policys_parameters_is_refused(self):
        trunk = nn.Linear(3, 8)
        actor = ProbabilisticActor(
            TensorDictModule(nn.Sequential(trunk, nn.Linear(8, 4)), ["observation"], ["logits"]),
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
        )
        critic = ValueOperator(nn.Sequential(trunk, nn.Linear(8, 1)), in_keys=["observation"])
        with pytest.raises(ValueError, match="critic shares 2 parameter tensor"):
            NaturalGradient(ReinforceLoss(actor, critic))

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"max_kl": 0}, "max_kl"),
            ({"damping": -1}, "damping"),
            ({"cg_iters": 0}, "cg_iters"),
            ({"backtrack_ratio": 1}, "backtrack_ratio"),
            ({"accept_ratio": 2}, "accept_ratio"),
            ({"kl_tolerance": 0.5}, "kl_tolerance"),
            ({"fisher": "diagonal"}, r"fisher must be one of \('exact', 'kfac'\)"),
            ({"fisher": "kfac", "damping": 0}, "fisher='kfac' needs damping > 0"),
        ],
    )
    def test_bad_arguments_are_refused(self, categorical_actor, kwargs, match):
        with pytest.raises(ValueError, match=match):
            NaturalGradient(ReinforceLoss(categorical_actor), **kwargs)

    def test_a_loss_of_another_kind_is_refused(self, categorical_actor):
        from torchrl.objectives import ReinforceLoss as TorchRLReinforceLoss

        loss = TorchRLReinforceLoss(categorical_actor, make_critic())
        with pytest.raises(TypeError, match=r"rl_pg.ReinforceLoss, got ReinforceLoss"):
            NaturalGradient(loss)

    @pytest.mark.parametrize("fisher", ["exact", "kfac"])
    def test_learns_the_gridworld(self, fisher):
        # 30 natural steps of 30 episodes each find the shortest path (return 0.5): the
        # greedy episode takes it, and the last batch's sampled episodes average near it
        # (the untrained policy's first batch: about -3.3).
        from rl_pg.collectors import SegmentCollector
        from rl_pg.envs import GridWorldEnv
        from rl_pg.episode_collector import EpisodeCollector
        from rl_pg.models import mlp_actor

        torch.manual_seed(0)
        env = GridWorldEnv(batch_size=30, max_steps=100)
        actor = mlp_actor(env, hidden=(32,))
        loss = ReinforceLoss(actor, baseline="running_mean")
        loss.make_value_estimator("reward_to_go", gamma=1.0)
        update = NaturalGradient(loss, max_kl=0.05, fisher=fisher)
        collector = EpisodeCollector(SegmentCollector(env, actor, frames_per_batch=240), 30)
        for _ in range(30):
            batch = collector.next()
            update.step(batch)
        collector.shutdown()
        assert float(batch["next", "reward"].sum()) / 30 >= 0.3
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            greedy = GridWorldEnv(max_steps=100).rollout(100, actor)
        assert float(greedy["next", "reward"].sum()) == pytest.approx(0.5, abs=1e-5)


class TestKroneckerFactoredFisher:
    """``fisher="kfac"``: the factors, the step they size, the policies they take."""

    def _mlp_actor(self):
        net = nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 4))
        return ProbabilisticActor(
            TensorDictModule(net, ["observation"], ["logits"]),
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
        )

    def test_the_factors_are_the_second_moments_of_inputs_and_sampled_scores(self):
        # A plain recomputation: A from the layer's inputs with a 1 for the bias, G from
        # the per-step gradient of log pi(a~|s) at the layer's outputs (a~ resampled
        # with the same random numbers), over the steps the loss learns from.
        from rl_pg.fisher import kronecker_factors, recording

        torch.manual_seed(4)
        actor = self._mlp_actor()
        update = NaturalGradient(ReinforceLoss(actor), fisher="kfac")
        batch = _batch(4)
        rows = update._fisher_rows(batch, None)
        with recording(update._layers) as seen:
            dist = actor.get_dist(batch)
        torch.manual_seed(5)
        factors = kronecker_factors(update._layers, seen, dist, batch.batch_size, rows)
        torch.manual_seed(5)
        flat = batch.reshape(-1)
        hidden = torch.tanh(actor.module[0].module[0](flat["observation"]))
        logits = actor.module[0].module[2](hidden.detach().requires_grad_())
        sampled = torch.distributions.Categorical(logits=actor.get_dist(batch).logits).sample()
        first_a = torch.cat([flat["observation"], torch.ones(len(flat), 1)], -1)
        second_a = torch.cat([hidden, torch.ones(len(flat), 1)], -1)
        score_logits = torch.nn.functional.one_hot(sampled.reshape(-1), 4) - logits.softmax(-1)
        second_g = score_logits
        first_g = (score_logits @ actor.module[0].module[2].weight) * (1 - hidden**2)
        n = len(flat)
        expected = [(first_a.T @ first_a / n, first_g.T @ first_g / n),
                    (second_a.T @ second_a / n, second_g.T @ second_g / n)]  # fmt: skip
        for (a, g), (want_a, want_g) in zip(factors, expected, strict=True):
            torch.testing.assert_close(a, want_a.detach(), atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(g, want_g.detach(), atol=1e-5, rtol=1e-5)

    def test_steps_left_out_count_in_no_factor(self):
        # Greedy and padding steps (valid False) change neither the factors nor the step.
        from rl_pg.fisher import kronecker_factors, recording

        torch.manual_seed(6)
        actor = self._mlp_actor()
        update = NaturalGradient(ReinforceLoss(actor), fisher="kfac")
        batch = _batch(6)
        valid = torch.rand(batch.batch_size) < 0.6
        rows = update._fisher_rows(batch, valid.unsqueeze(-1))
        assert torch.equal(rows, valid.reshape(-1).nonzero().squeeze(-1))
        changed = batch.clone()
        changed["observation"][~valid] = 100.0
        factors = []
        for data in (batch, changed):
            with recording(update._layers) as seen:
                dist = actor.get_dist(data)
            torch.manual_seed(7)
            factors.append(kronecker_factors(update._layers, seen, dist, data.batch_size, rows))
        for (a, g), (a2, g2) in zip(*factors, strict=True):
            torch.testing.assert_close(a, a2)
            torch.testing.assert_close(g, g2)

    def test_a_step_moves_the_policy_by_about_max_kl(self):
        # K-FAC's quadratic leaves out the layers' cross terms: the measured KL is near
        # max_kl, not at it; the line search keeps it within kl_tolerance.
        torch.manual_seed(0)
        actor = self._mlp_actor()
        update = NaturalGradient(ReinforceLoss(actor), max_kl=0.005, fisher="kfac")
        batch = _batch()
        old = {k: v.clone() for k, v in actor.state_dict().items()}
        out = update.step(batch)
        kl = _measured_kl(actor, batch, old)
        assert 0.001 < kl <= 1.5 * 0.005
        assert float(out["kl"]) == pytest.approx(kl, rel=1e-4)
        assert float(out["improvement"]) > 0

    def test_a_gaussian_whose_parameters_are_all_in_linear_layers(self):
        torch.manual_seed(2)
        actor = make_gaussian_actor(n_act=2, distribution_class=torch.distributions.Normal)
        root = TensorDict({"observation": torch.randn(64, 3)}, batch_size=[64])
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
            action = actor(root)["action"]
        batch = make_batch(torch.zeros(64, 1, 2), seed=2).reshape(64)
        batch.update({"observation": root["observation"], "action": action})
        out = NaturalGradient(ReinforceLoss(actor), max_kl=0.005, fisher="kfac").step(batch)
        assert 0 < float(out["kl"]) <= 1.5 * 0.005
        assert float(out["improvement"]) > 0

    def test_a_parameter_outside_linear_layers_is_refused(self):
        # A Gaussian's learned scale, one per action dimension, is no layer's weight.
        from rl_pg.envs import GridWorldEnv
        from rl_pg.models import mlp_actor

        env = GridWorldEnv()
        actor = mlp_actor(env, hidden=(8,))
        actor.module[0].module.register_parameter("extra", nn.Parameter(torch.zeros(2)))
        with pytest.raises(ValueError, match=r"parameters of shapes \[\(2,\)\] outside them"):
            NaturalGradient(ReinforceLoss(actor), fisher="kfac")
