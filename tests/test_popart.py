"""rl_pg.normalization.PopArt and ReinforceLoss(value_norm=...): a critic that learns returns of
any scale at the speed of returns near one, with its outputs preserved."""

from __future__ import annotations

import pytest
import torch
from conftest import N_ACT, N_OBS, make_batch, make_categorical_actor
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn
from torchrl.modules import PopArtValueNorm, RunningValueNorm, ValueOperator

from rl_pg import ReinforceLoss
from rl_pg.normalization import PopArt, popart_output


def _critic(hidden: int = 16) -> ValueOperator:
    body = nn.Sequential(nn.Linear(N_OBS, hidden), nn.Tanh(), nn.Linear(hidden, 1))
    return ValueOperator(body, in_keys=["observation"])


def _explained_variance(critic, batch) -> float:
    with torch.no_grad():
        value = critic(batch.clone())["state_value"]
    target = batch["value_target"]
    return float(1 - (target - value).var() / target.var())


class TestPopArt:
    @settings(max_examples=40, deadline=None)
    @given(
        seed=st.integers(0, 2**16),
        outputs=st.integers(1, 3),
        batches=st.lists(
            st.tuples(st.floats(-1e3, 1e3), st.floats(1e-2, 1e3)), min_size=2, max_size=6
        ),
    )
    def test_every_update_preserves_the_outputs(self, seed, outputs, batches):
        torch.manual_seed(seed)
        head = PopArt(nn.Linear(5, outputs).double())
        head.double()
        reference = PopArtValueNorm(shape=outputs, beta=0.99).double()
        x = torch.randn(32, 5, dtype=torch.double)
        for number, (loc, scale) in enumerate(batches):
            targets = loc + scale * torch.randn(64, outputs, dtype=torch.double)
            before = head(x)
            head.update(targets)
            reference.update(targets)
            if number:  # the first update has no trained outputs to keep
                torch.testing.assert_close(head(x), before, rtol=1e-9, atol=1e-9 * scale)
            torch.testing.assert_close(head.scale(), reference.scale())
            torch.testing.assert_close(head.normalize(targets), reference.normalize(targets))
        # The layer itself predicts the standardised value.
        torch.testing.assert_close(head.normalize(head(x)), head.linear(x))

    def test_the_identity_until_the_first_update(self):
        head = PopArt(nn.Linear(3, 1))
        x = torch.randn(4, 3)
        torch.testing.assert_close(head(x), head.linear(x))
        assert head.scale().item() == 1.0
        head.update(torch.full((8, 1), 5.0))
        assert head.updated

    def test_popart_output_wraps_the_last_linear_layer_once(self):
        critic = _critic()
        last = critic.module[-1]
        head = popart_output(critic)
        assert head.linear is last and critic.module[-1] is head
        assert popart_output(critic) is head
        with pytest.raises(ValueError, match="no"):
            popart_output(nn.Sequential(nn.Tanh()))

    @pytest.mark.parametrize(
        ("kwargs", "error", "match"),
        [
            ({"linear": nn.Tanh()}, TypeError, "nn.Linear"),
            ({"stats": RunningValueNorm(shape=2)}, ValueError, "shape"),
            ({"stats": object()}, TypeError, "ValueNorm"),
        ],
    )
    def test_bad_arguments(self, kwargs, error, match):
        with pytest.raises(error, match=match):
            PopArt(**{"linear": nn.Linear(3, 1), **kwargs})


class TestValueNormInTheLoss:
    @pytest.mark.parametrize("functional", [False, True])
    @pytest.mark.parametrize("estimator", ["reward_to_go", "gae"])
    def test_the_critic_regresses_standardised_targets(self, functional, estimator):
        torch.manual_seed(0)
        critic = _critic()
        head = popart_output(critic)
        loss = ReinforceLoss(
            make_categorical_actor(),
            critic,
            value_norm=head,
            functional=functional,
            loss_critic_type="l2",
        )
        loss.make_value_estimator(estimator, gamma=0.9)
        batch = make_batch(torch.randint(N_ACT, (4, 9)), seed=1)
        batch["next", "reward"] = 50 * batch["next", "reward"] + 200
        for _ in range(2):  # the second pass runs with statistics from the first
            data = batch.clone()
            out = loss(data)
            with torch.no_grad():
                hidden = critic.module[:-1](data["observation"])
                expected = (head.normalize(data["value_target"]) - head.linear(hidden)).pow(2)
            torch.testing.assert_close(out["loss_value"], expected.mean())
            out["loss_value"].backward()
            assert head.linear.weight.grad is not None
        # The advantages stay at the rewards' scale.
        torch.testing.assert_close(
            data["advantage"], data["value_target"] - data["state_value"], rtol=1e-5, atol=1e-3
        )
        assert data["value_target"].abs().mean() > 100

    def test_the_statistics_come_from_the_valid_steps_once_per_batch(self):
        # Padded episodes give the statistics of the same episodes back to back, and
        # value_loss (extra critic steps on the batch) does not count the batch again.
        batch = make_batch(torch.randint(N_ACT, (3, 7)), seed=2)
        flat = batch.reshape(-1)[:8].clone()
        flat["next", "done"][:] = False
        flat["next", "done"][[2, 7]] = True
        flat["next", "terminated"] = flat["next", "done"].clone()
        padded = batch[:2, :5].clone().zero_()
        padded[0, :3] = flat[:3]
        padded[1, :5] = flat[3:]
        padded["next", "reward"][0, 3:] = 1e4  # padding: must not count
        mask = torch.zeros(2, 5, 1, dtype=torch.bool)
        mask[0, :3] = mask[1, :5] = True
        padded["collector", "mask"] = mask
        stats = []
        for data in (flat, padded):
            norm = RunningValueNorm(shape=1)
            torch.manual_seed(0)
            loss = ReinforceLoss(make_categorical_actor(), _critic(), value_norm=norm)
            loss.make_value_estimator("reward_to_go", gamma=0.9)
            data = data.clone()
            loss(data)
            loss.value_loss(data)
            stats.append((norm.count.item(), norm.mean.item(), norm.scale().item()))
        assert stats[0] == pytest.approx(stats[1])
        assert stats[0][0] == 8

    def test_a_plain_value_norm_rescales_the_loss_only(self):
        torch.manual_seed(0)
        actor, critic = make_categorical_actor(), _critic()
        batch = make_batch(torch.randint(N_ACT, (3, 7)), seed=2)
        losses = {}
        for norm in (None, RunningValueNorm(shape=1)):
            loss = ReinforceLoss(actor, critic, value_norm=norm, loss_critic_type="l2")
            losses[norm is None] = (loss(batch.clone())["loss_value"], norm)
        (plain, _), (scaled, norm) = losses[True], losses[False]
        torch.testing.assert_close(scaled, plain / norm.scale().squeeze() ** 2)

    def test_popart_fits_large_returns_where_a_plain_critic_cannot(self):
        # Targets of mean ~100 and spread ~50, predictable from the observation: after
        # 100 Adam steps at 1e-3 the plain critic has barely moved its output, PopArt's
        # has fitted them.
        explained = {}
        for popart in (False, True):
            torch.manual_seed(0)
            critic = _critic(32)
            head = popart_output(critic) if popart else None
            loss = ReinforceLoss(
                make_categorical_actor(), critic, value_norm=head, loss_critic_type="l2"
            )
            loss.make_value_estimator("reward_to_go", gamma=0.0)
            batch = make_batch(torch.randint(N_ACT, (16, 50)), seed=3)
            batch["next", "reward"] = 100 + 50 * batch["observation"][..., :1]
            optimizer = torch.optim.Adam(critic.parameters(), lr=1e-3)
            for _ in range(100):
                out = loss(batch)
                optimizer.zero_grad()
                out["loss_value"].backward()
                optimizer.step()
            explained[popart] = _explained_variance(critic, batch)
        assert explained[True] > 0.8
        assert explained[False] < 0.3

    def test_clip_value_is_in_standardised_units(self):
        torch.manual_seed(0)
        critic = _critic()
        head = popart_output(critic)
        loss = ReinforceLoss(make_categorical_actor(), critic, value_norm=head, clip_value=0.1)
        loss.make_value_estimator("gae", gamma=0.9, lmbda=0.9)
        batch = make_batch(torch.randint(N_ACT, (3, 7)), seed=2)
        batch["next", "reward"] = 100 * batch["next", "reward"]
        loss(batch.clone())  # statistics first
        loss.value_estimator(batch)  # V at collection time: what the clip is around
        with torch.no_grad():
            head.linear.bias.add_(0.05)  # 0.05 standard deviations: inside the clip
        assert loss(batch.clone())["value_clip_fraction"] == 0
        with torch.no_grad():
            head.linear.bias.add_(0.1)  # 0.15: outside
        assert loss(batch.clone())["value_clip_fraction"] == 1

    @pytest.mark.parametrize(
        ("critic", "norm", "error", "match"),
        [
            (True, "not a norm", TypeError, "ValueNorm"),
            (False, RunningValueNorm(shape=1), ValueError, "no critic_network"),
        ],
    )
    def test_bad_value_norm(self, critic, norm, error, match):
        with pytest.raises(error, match=match):
            ReinforceLoss(make_categorical_actor(), _critic() if critic else None, value_norm=norm)


class TestRejectedBatches:
    """A batch with NaN or inf leaves running statistics as they were."""

    def test_popart_refuses_non_finite_targets_and_keeps_its_state(self):
        layer = PopArt(nn.Linear(3, 1))
        layer.update(torch.randn(32, 1) * 50 + 100)
        before = {k: v.clone() for k, v in layer.state_dict().items()}
        for bad in (float("nan"), float("inf")):
            targets = torch.randn(32, 1)
            targets[5] = bad
            with pytest.raises(ValueError, match=r"PopArt got 1 non-finite value targets"):
                layer.update(targets)
            for key, value in layer.state_dict().items():
                assert torch.equal(value, before[key]), key
        layer.update(torch.randn(32, 1))  # and it goes on learning from good batches
        assert not torch.equal(layer.state_dict()["mean"], before["mean"])

    def test_running_norm_refuses_non_finite_observations_and_bad_arguments(self):
        from rl_pg.normalization import RunningNorm

        norm = RunningNorm(4)
        norm.update(torch.randn(16, 4))
        before = {k: v.clone() for k, v in norm.state_dict().items()}
        x = torch.randn(16, 4)
        x[3, 2] = float("-inf")
        with pytest.raises(ValueError, match=r"RunningNorm\('observation'\) got 1 non-finite"):
            norm.update(x)
        for key, value in norm.state_dict().items():
            assert torch.equal(value, before[key]), key
        bad = [("clip", 0), ("clip", -1), ("clip", float("nan"))]
        bad += [("min_std", 0), ("min_std", -1), ("min_std", float("inf"))]
        for name, value in bad:
            with pytest.raises(ValueError, match=rf"{name} must be"):
                RunningNorm(4, **{name: value})


@pytest.mark.parametrize("baseline", ["running_mean", "ema"])
def test_a_rejected_batch_leaves_the_loss_s_baseline_as_it_was(baseline):
    from rl_pg.envs import GridWorldEnv
    from rl_pg.models import mlp_actor

    env = GridWorldEnv(batch_size=4)
    actor = mlp_actor(env)
    loss = ReinforceLoss(actor, baseline=baseline)
    batch = env.rollout(6, actor, break_when_any_done=False)
    loss(batch.clone())
    before = {k: v.clone() for k, v in loss.state_dict().items() if "baseline" in k}
    assert before
    bad = batch.clone()
    bad["next", "reward"][0, 2] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        loss(bad)
    for key, value in before.items():
        assert torch.equal(loss.state_dict()[key], value), key
