"""rl_pg.gradient_statistics: the statistics, the units, and what the measurement leaves alone.

Exact answers (bandit, gridworld) are in test_exact_gradients.py."""

from __future__ import annotations

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
)
from hypothesis import given
from hypothesis import strategies as st
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torch.distributions import Normal
from torchrl.modules import ProbabilisticActor

from rl_pg import ReinforceLoss
from rl_pg.gradient_noise import noise_statistics, unit_index
from rl_pg.gradient_statistics import ESTIMATORS, GradientStatistics
from rl_pg.groups import GROUP_BASELINES

GROUP_ESTIMATORS = ("leave_one_out", "group_mean", "group_mean_scaled", "greedy")

Z_MAX = 5.0


class TestNoiseStatistics:
    def test_recovers_a_known_gaussian_noise_scale(self):
        # g_u = G + eps, eps ~ N(0, diag(s^2)): tr(Sigma) = sum s^2, |grad J|^2 = |G|^2,
        # B = tr(Sigma) / |G|^2. Both estimates are unbiased per batch, so their means
        # over 4 000 batches of 16 units are within 5 standard errors of the truth.
        generator = torch.Generator().manual_seed(0)
        signal = torch.tensor([1.0, -2.0, 0.5, 0.0, 3.0], dtype=torch.float64)
        scale = torch.tensor([2.0, 1.0, 4.0, 3.0, 0.5], dtype=torch.float64)
        batches = 4000
        noise = torch.randn(batches, 16, 5, generator=generator, dtype=torch.float64)
        stats = [noise_statistics(signal + scale * eps) for eps in noise]
        trace = torch.stack([s["trace_covariance"] for s in stats])
        norm_sq = torch.stack([s["grad_norm_sq"] for s in stats])
        true_trace, true_norm_sq = scale.pow(2).sum().item(), signal.pow(2).sum().item()
        for estimate, truth in ((trace, true_trace), (norm_sq, true_norm_sq)):
            se = estimate.std() / batches**0.5
            assert abs(estimate.mean().item() - truth) <= Z_MAX * se
        # The noise scale as a ratio of the means (per-batch ratios are biased).
        noise_scale = trace.mean() / norm_sq.mean()
        assert noise_scale.item() == pytest.approx(true_trace / true_norm_sq, rel=0.05)
        snr = torch.stack([s["snr"] for s in stats]).mean().item()
        assert snr == pytest.approx(16 * true_norm_sq / true_trace, rel=0.1)
        # Halves agree when the signal dominates.
        assert torch.stack([s["half_cosine"] for s in stats]).mean() > 0.5

    def test_pure_noise_gives_no_signal(self):
        generator = torch.Generator().manual_seed(1)
        stats = [noise_statistics(torch.randn(32, 50, generator=generator)) for _ in range(500)]
        assert abs(torch.stack([s["snr"] for s in stats]).mean().item()) < 0.1
        assert abs(torch.stack([s["half_cosine"] for s in stats]).mean().item()) < 0.02

    def test_noise_scale_is_nan_when_the_signal_estimate_is_not_positive(self):
        stats = noise_statistics(torch.tensor([[1.0, 0.0], [-1.0, 0.0]]))
        assert stats["grad_norm_sq"].item() < 0
        assert torch.isnan(stats["noise_scale"])
        # Two units a and b: |G|^2 is estimated as a.b, exactly 0 here (the spread is 4):
        # no noise scale of a signal estimated at 0 either.
        stats = noise_statistics(torch.tensor([[0.0, 0.0], [2.0, 2.0]], dtype=torch.float64))
        assert stats["grad_norm_sq"].item() == 0 and torch.isnan(stats["noise_scale"])
        # a small positive signal has one: 0.5 * 1 = 0.5 and (1 - 0.5)^2 / 2 = 0.125
        stats = noise_statistics(torch.tensor([[1.0], [0.5]], dtype=torch.float64))
        assert stats["noise_scale"].item() == pytest.approx(0.125 / 0.5)

    def test_a_spread_that_overflows_is_refused(self):
        # Finite gradients whose squared spread is beyond float32: not a number to log.
        with pytest.raises(ValueError, match="NaN/inf"):
            noise_statistics(torch.tensor([[3e19], [-3e19]], dtype=torch.float32))

    @pytest.mark.parametrize(
        ("bad", "match"),
        [
            (torch.zeros(1, 3), "at least 2 independent units"),
            (torch.zeros(3), r"\[\.\.\., units, parameters\]"),
            (torch.tensor([[0.0, float("nan")], [1.0, 2.0]]), "NaN"),
        ],
    )
    def test_rejects(self, bad, match):
        with pytest.raises(ValueError, match=match):
            noise_statistics(bad)


def _plain_unit_index(done: list[list[bool]], unit: str) -> list[list[int]]:
    out, next_id = [], 0
    for row in done:
        ids = []
        for t, _ in enumerate(row):
            if t > 0 and unit == "episode" and row[t - 1]:
                next_id += 1
            ids.append(next_id)
        out.append(ids)
        next_id += 1
    return out


class TestUnitIndex:
    @given(
        st.integers(1, 4).flatmap(
            lambda rows: st.integers(1, 9).flatmap(
                lambda steps: st.lists(
                    st.lists(st.booleans(), min_size=steps, max_size=steps),
                    min_size=rows,
                    max_size=rows,
                )
            )
        ),
        st.sampled_from(["episode", "row"]),
    )
    def test_matches_a_plain_loop(self, done, unit):
        mask = torch.tensor(done)
        batch = TensorDict({"next": {"done": mask.unsqueeze(-1)}}, list(mask.shape))
        index, units = unit_index(batch, unit=unit)
        assert index.tolist() == _plain_unit_index(done, unit)
        assert units == int(index.max()) + 1

    @pytest.mark.parametrize("unit", ["episode", "row"])
    def test_environments_in_two_dimensions_and_several_done_flags(self, unit):
        # [2, 2, T]: the rows are the environments in order; a step is an episode's end
        # when any of its flags says so.
        generator = torch.Generator().manual_seed(0)
        done = torch.rand(2, 2, 7, 2, generator=generator) < 0.2
        batch = TensorDict({"next": {"done": done}}, [2, 2, 7])
        index, units = unit_index(batch, unit=unit)
        rows = done.any(-1).reshape(4, 7).tolist()
        assert index.reshape(4, 7).tolist() == _plain_unit_index(rows, unit)
        assert units == int(index.max()) + 1

    def test_time_dimension_by_name(self):
        done = torch.tensor([[False, True], [False, False], [True, False]])  # [T=3, B=2]
        batch = TensorDict({"next": {"done": done.unsqueeze(-1)}}, [3, 2], names=["time", None])
        index, units = unit_index(batch)
        assert index.T.tolist() == [[0, 0, 0], [1, 2, 2]]
        assert units == 3

    def test_groups_of_a_batch_of_one_row(self):
        group = torch.tensor([[4, 4, 2]]).unsqueeze(-1)
        batch = TensorDict({"group": group, "next": {"done": torch.zeros(1, 3, 1)}}, [1, 3])
        index, units = unit_index(batch, unit="group")
        assert index.tolist() == [[1, 1, 0]] and units == 2

    def test_groups_are_numbered_by_id_wherever_their_steps_lie(self):
        done = torch.zeros(3, 2, 1, dtype=torch.bool)
        group = torch.tensor([[5, 5], [-1, 5], [9, -1]]).unsqueeze(-1)
        batch = TensorDict({"group": group, "next": {"done": done}}, [3, 2])
        index, units = unit_index(batch, unit="group")
        assert index.tolist() == [[1, 1], [0, 1], [2, 0]] and units == 3

    def test_rejects(self):
        batch = TensorDict({"next": {"done": torch.zeros(3, 1, dtype=torch.bool)}}, [3])
        with pytest.raises(ValueError, match="unit must be one of"):
            unit_index(batch, unit="step")
        with pytest.raises(KeyError, match="episode ends"):
            unit_index(batch, done_key="ended")
        with pytest.raises(KeyError, match="unit='group' reads each step's group"):
            unit_index(batch, unit="group")
        batch["group"] = torch.zeros(3, 1)
        with pytest.raises(TypeError, match="integer group ids"):
            unit_index(batch, unit="group")
        batch["group"] = torch.zeros(3, 2, dtype=torch.long)
        with pytest.raises(ValueError, match="one id per step"):
            unit_index(batch, unit="group")


def _segment_batch(seed=0):
    generator = torch.Generator().manual_seed(seed)
    return make_batch(torch.randint(N_ACT, (6, 20), generator=generator), p_done=0.1, seed=seed)


class TestGradientStatistics:
    def test_every_estimator_with_a_critic(self):
        torch.manual_seed(0)
        loss = ReinforceLoss(make_categorical_actor(), make_critic())
        stats = GradientStatistics(loss)(_segment_batch())
        ungrouped = [e for e in ESTIMATORS if e not in GROUP_ESTIMATORS]
        assert sorted(stats.keys()) == sorted(ungrouped)
        for name in ungrouped:
            assert stats[name, "units"].item() > 6  # episodes, not rows
            assert torch.isfinite(stats[name, "trace_covariance"])

    def test_gae_weights_are_torchrls_gae_and_a_cut_episode_is_bootstrapped(self):
        # An episode cut by a time limit (done, not terminated) goes on in V(s_{t+1}); a
        # terminated one does not. TorchRL's GAE is the reference.
        from torchrl.objectives.value import GAE

        torch.manual_seed(0)
        critic = make_critic()
        loss = ReinforceLoss(make_categorical_actor(), critic)
        loss.make_value_estimator("gae", gamma=0.9, lmbda=0.8)
        batch = _segment_batch()
        done = batch["next", "done"]
        cut = torch.rand(done.shape, generator=torch.Generator().manual_seed(3)) < 0.5
        batch["next", "terminated"] = done & ~cut
        batch["next", "truncated"] = done & cut
        assert (done & cut).any() and (done & ~cut).any()
        weights = GradientStatistics(loss, estimators=["gae"]).weights(batch)["gae"]
        expected = GAE(gamma=0.9, lmbda=0.8, value_network=critic)(batch.clone())["advantage"]
        torch.testing.assert_close(weights, expected.squeeze(-1))

    def test_row_units(self):
        torch.manual_seed(0)
        loss = ReinforceLoss(make_categorical_actor())
        stats = GradientStatistics(loss, unit="row")(_segment_batch())
        assert stats["reward_to_go", "units"].item() == 6

    def test_mean_gradient_is_the_loss_gradient(self):
        # With the sum reduction, -d(loss_actor)/d(theta) is the sum of unit gradients.
        torch.manual_seed(0)
        loss = ReinforceLoss(make_categorical_actor(), make_critic(), reduction="sum")
        batch = _segment_batch()
        stats = GradientStatistics(loss, estimators=["loss"])
        gradients = stats.unit_gradients(batch, stats.weights(batch))["loss"]
        with loss.actor_network_params.to_module(loss.actor_network):
            params = [p for _, p in loss.actor_network.named_parameters()]
        grads = torch.autograd.grad(loss(batch.clone())["loss_actor"], params)
        expected = -torch.cat([g.reshape(-1) for g in grads])
        torch.testing.assert_close(gradients.sum(0), expected)

    def test_continuous_policy(self):
        torch.manual_seed(0)
        actor = make_gaussian_actor(distribution_class=Normal)
        loss = ReinforceLoss(actor, functional=False)
        batch = make_batch(torch.randn(4, 10, N_ACT), p_done=0.2)
        stats = GradientStatistics(loss, estimators=["reward_to_go"])(batch)
        n_params = sum(p.numel() for p in actor.parameters())
        assert stats["reward_to_go", "mean_gradient"].shape == (n_params,)

    @pytest.mark.parametrize("functional", [True, False])
    @pytest.mark.parametrize(
        "policy", ["categorical", "gaussian", "composite", "composite-apart", "nested"]
    )
    # chunks of 7 steps: a few units each, one unit per backward pass; the default: every
    # unit in one chunk (a sparse product) and ten units per backward pass
    @pytest.mark.parametrize("chunk", [7, None])
    def test_both_methods_agree_and_vmap_needs_no_fallback(self, functional, policy, chunk):
        torch.manual_seed(0)
        observation = ("agent", "observation") if policy == "nested" else "observation"
        if policy == "categorical":
            actor, batch = make_categorical_actor(), _segment_batch()
        elif policy == "gaussian":
            actor = make_gaussian_actor(distribution_class=Normal)
            batch = make_batch(torch.randn(4, 10, N_ACT), p_done=0.2)
        elif policy.startswith("composite"):  # two heads, two actions, one distribution
            # their actions under "action", or each under a key of its own
            actor = make_composite_actor(action=None if policy.endswith("apart") else "action")
            batch = _segment_batch()
            del batch["action"]
            with torch.no_grad():
                actor(batch)
        else:  # an observation under a nested key, as multi-agent environments give it
            actor, batch = make_categorical_actor(observation_key=observation), _segment_batch()
            batch[observation] = batch.pop("observation")
            batch["next", "agent", "observation"] = batch.pop(("next", "observation"))
        loss = ReinforceLoss(actor, make_critic(observation_key=observation), functional=functional)
        by_steps = GradientStatistics(loss, method="auto", chunk=chunk)
        by_units = GradientStatistics(loss, method="backward", chunk=chunk)
        weights = by_steps.weights(batch)
        expected = by_units.unit_gradients(batch, weights)
        for name, value in by_steps.unit_gradients(batch, weights).items():
            torch.testing.assert_close(value, expected[name], rtol=1e-4, atol=1e-5)
        assert by_steps.method == "auto"  # torch.func handled it: no fallback was taken

    @pytest.mark.parametrize(("p_done", "chunk"), [(0.6, 30), (1.0, 8)])
    def test_chunks_of_many_short_episodes_agree_with_autograd(self, p_done, chunk):
        # Chunks of more units than the dense product takes (16 to 20), or exactly as
        # many (8 one-step episodes), all but the first starting past unit 0: the
        # products' rows and columns count from the chunk's first unit and step.
        torch.manual_seed(0)
        loss = ReinforceLoss(make_categorical_actor(), make_critic())
        actions = torch.randint(N_ACT, (4, 30), generator=torch.Generator().manual_seed(1))
        batch = make_batch(actions, p_done=p_done)
        index, _ = unit_index(batch, unit="episode")
        spans = [len(part.unique()) for part in index.reshape(-1).split(chunk)]
        assert min(spans[:-1]) > 8 if p_done < 1 else spans[:-1] == [8] * 14
        by_steps = GradientStatistics(loss, method="vmap", chunk=chunk)
        weights = by_steps.weights(batch)
        expected = GradientStatistics(loss, method="backward").unit_gradients(batch, weights)
        for name, value in by_steps.unit_gradients(batch, weights).items():
            torch.testing.assert_close(value, expected[name], rtol=1e-4, atol=1e-5)

    def test_a_policy_torch_func_cannot_map_falls_back_to_autograd(self):
        # A policy that branches on its input's values: vmap refuses it. "auto" takes the
        # backward passes, and from then on; "vmap" says so.
        class Branching(nn.Module):
            def __init__(self):
                super().__init__()
                self.linear = nn.Linear(N_OBS, N_ACT)

            def forward(self, observation):
                logits = self.linear(observation)
                return logits if bool((observation > 1e6).any()) else logits * 1.5

        torch.manual_seed(0)
        actor = ProbabilisticActor(
            TensorDictModule(Branching(), ["observation"], ["logits"]),
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
            return_log_prob=True,
        )
        loss = ReinforceLoss(actor)
        batch = _segment_batch()
        auto = GradientStatistics(loss, estimators=["reward_to_go"], method="auto")
        weights = auto.weights(batch)
        got = auto.unit_gradients(batch, weights)["reward_to_go"]
        assert auto.method == "backward"
        expected = GradientStatistics(loss, method="backward").unit_gradients(batch, weights)
        torch.testing.assert_close(got, expected["reward_to_go"])
        with pytest.raises(RuntimeError, match="data-dependent"):
            GradientStatistics(loss, method="vmap").unit_gradients(batch, weights)

    def test_a_time_dimension_first_gives_the_same_units(self):
        torch.manual_seed(0)
        loss = ReinforceLoss(make_categorical_actor(), make_critic())
        batch = _segment_batch()
        stats = GradientStatistics(loss, chunk=5)
        expected = stats(batch)
        # The same data laid out time first, the dimension named.
        flipped = batch.transpose(0, 1).contiguous()
        flipped.names = ["time", None]
        got = stats(flipped)
        for name in expected.keys():
            torch.testing.assert_close(got[name, "mean_gradient"], expected[name, "mean_gradient"])
            torch.testing.assert_close(
                got[name, "trace_covariance"], expected[name, "trace_covariance"]
            )

    def test_leaves_the_loss_and_the_random_stream_alone(self):
        torch.manual_seed(0)
        loss = ReinforceLoss(make_categorical_actor(), baseline="running_mean")
        loss(_segment_batch(1))  # the baseline has a state now
        before = {k: v.clone() for k, v in loss.state_dict().items()}
        rng = torch.get_rng_state()
        GradientStatistics(loss)(_segment_batch(2))
        assert torch.equal(rng, torch.get_rng_state())
        for key, value in loss.state_dict().items():
            assert torch.equal(value, before[key]), key
        assert all(p.grad is None for p in loss.parameters())

    def test_padding_steps_do_not_count(self):
        torch.manual_seed(0)
        loss = ReinforceLoss(make_categorical_actor())
        batch = _segment_batch()
        batch["collector", "mask"] = torch.ones(batch.shape, dtype=torch.bool)
        full = GradientStatistics(loss, estimators=["reward_to_go"], unit="row")(batch.clone())
        batch["collector", "mask"][:, 15:] = False
        batch["action"][:, 15:] = 0  # whatever sits on padding must not matter
        cut = GradientStatistics(loss, estimators=["reward_to_go"], unit="row")(batch)
        assert not torch.allclose(
            full["reward_to_go", "mean_gradient"], cut["reward_to_go", "mean_gradient"]
        )

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"estimators": ["gae"]}, "has no critic"),
            ({"estimators": ["advantage"]}, "estimators must be names"),
            ({"unit": "step"}, "unit must be one of"),
            ({"chunk": 0}, "chunk must be an integer >= 1"),
            ({"gae_lambda": 1.5}, "gae_lambda"),
        ],
    )
    def test_rejects(self, kwargs, match):
        loss = ReinforceLoss(make_categorical_actor())
        with pytest.raises(ValueError, match=match):
            GradientStatistics(loss, **kwargs)

    def test_chunks_of_one_unit_and_other_losses(self):
        torch.manual_seed(0)
        loss = ReinforceLoss(make_categorical_actor())
        batch = _segment_batch()
        whole = GradientStatistics(loss, estimators=["reward_to_go"])(batch)
        one = GradientStatistics(loss, estimators=["reward_to_go"], chunk=1)(batch)
        torch.testing.assert_close(
            one["reward_to_go", "mean_gradient"], whole["reward_to_go", "mean_gradient"]
        )
        for chunk in (True, 2.5):
            with pytest.raises(TypeError, match="chunk must be an integer"):
                GradientStatistics(loss, chunk=chunk)
        from torchrl.objectives import ReinforceLoss as TorchRLLoss

        with pytest.raises(TypeError, match=r"an rl_pg\.ReinforceLoss's policy term, got Rein"):
            GradientStatistics(TorchRLLoss(make_categorical_actor(), make_critic()))

    def test_each_estimators_weights_are_its_definition(self):
        from rl_pg.functional import discounted_return, reward_to_go

        torch.manual_seed(0)
        critic = make_critic()
        loss = ReinforceLoss(make_categorical_actor(), critic)
        batch = _segment_batch()
        reward, done = batch["next", "reward"], batch["next", "done"]
        terminated = batch["next", "terminated"]
        with torch.no_grad():
            value = critic(batch.clone())["state_value"]
            next_value = critic(batch["next"].clone())["state_value"]
        gamma = float(loss.value_estimator.gamma)
        common = {"terminated": terminated, "next_value": next_value}
        to_go = reward_to_go(reward, done, gamma, **common)
        first = torch.cat([torch.ones_like(done[:, :1]), done[:, :-1]], dim=1)  # starts
        expected = {
            "episode_return": discounted_return(reward, done, gamma, **common),
            "reward_to_go": to_go,
            "reward_to_go_minus_mean": to_go - to_go[first].mean(),
            "reward_to_go_minus_value": to_go - value,
        }
        weights = GradientStatistics(loss, estimators=list(expected)).weights(batch)
        for name, definition in expected.items():
            torch.testing.assert_close(weights[name], definition.squeeze(-1), msg=name)
        fixed = GradientStatistics(loss, estimators=["reward_to_go_minus_mean"],
                                   scalar_baseline=2.5).weights(batch)  # fmt: skip
        torch.testing.assert_close(fixed["reward_to_go_minus_mean"], (to_go - 2.5).squeeze(-1))

    def test_group_estimators_need_group_units(self):
        loss = ReinforceLoss(make_categorical_actor())
        with pytest.raises(ValueError, match="measure them with unit='group'"):
            GradientStatistics(loss, estimators=["reward_to_go", "leave_one_out"])
        assert not set(GradientStatistics(loss).estimators) & set(GROUP_ESTIMATORS)

    def test_one_unit_is_refused(self):
        loss = ReinforceLoss(make_categorical_actor())
        batch = _segment_batch()[:1]
        with pytest.raises(ValueError, match="at least 2 independent units"):
            GradientStatistics(loss, unit="row")(batch)


def _grouped(lengths, groups, greedy=None, seed=0):
    """Whole episodes as the rows of a padded ``[E, T]`` batch, their group (and
    greedy flag) on every step, as EpisodeCollector lays them out."""
    generator = torch.Generator().manual_seed(seed)
    n, width = len(lengths), max(lengths)
    mask = torch.arange(width) < torch.tensor(lengths).unsqueeze(-1)
    done = torch.zeros(n, width, 1, dtype=torch.bool)
    done[torch.arange(n), torch.tensor(lengths) - 1] = True
    batch = make_batch(torch.randint(N_ACT, (n, width), generator=generator), seed=seed)
    batch["next", "done"], batch["next", "terminated"] = done, done.clone()
    batch["collector", "mask"] = mask
    batch["group"] = torch.tensor(groups).unsqueeze(-1).expand(n, width).clone()
    if greedy is not None:
        batch["greedy"] = torch.tensor(greedy).unsqueeze(-1).expand(n, width).clone()
    return batch


class TestGroupEstimators:
    """Measured by group (the independent unit of episodes that share a start), each
    group baseline's unit gradient is the gradient of the loss with that baseline on
    the group's own episodes (whose weights test_loss.py checks against a plain loop)."""

    LENGTHS = (3, 5, 1, 4, 2, 6, 2, 3, 4, 2, 5, 1)
    GROUPS = (7, 7, 7, 2, 2, 2, 4, 4, 4, 0, 0, 0)
    GREEDY = (False, False, True) * 4

    def _loss_gradient(self, actor, batch, baseline, scale):
        loss = ReinforceLoss(actor, baseline=baseline, group_scale=scale, reduction="sum")
        params = [p for p in actor.parameters() if p.requires_grad]
        with loss.actor_network_params.to_module(loss.actor_network):
            params = [p for _, p in loss.actor_network.named_parameters()]
        grads = torch.autograd.grad(loss(batch.clone())["loss_actor"], params)
        return -torch.cat([g.reshape(-1) for g in grads])

    @pytest.mark.parametrize("greedy", [False, True])
    def test_unit_gradients_are_each_groups_loss_gradient(self, greedy):
        torch.manual_seed(0)
        actor = make_categorical_actor()
        flags = self.GREEDY if greedy else None
        batch = _grouped(self.LENGTHS, self.GROUPS, flags)
        stats = GradientStatistics(
            ReinforceLoss(actor, baseline="greedy" if greedy else "leave_one_out"), unit="group"
        )
        expected_names = set(GROUP_ESTIMATORS) - (set() if greedy else {"greedy"})
        assert expected_names <= set(stats._estimators(batch))
        gradients = stats.unit_gradients(batch, stats.weights(batch))
        assert not ({"greedy"} - expected_names) & gradients.keys()
        torch.testing.assert_close(
            gradients["loss"], gradients["greedy" if greedy else "leave_one_out"]
        )
        for name in expected_names:
            baseline, scale = {"group_mean_scaled": ("group_mean", True)}.get(name, (name, False))
            if greedy and baseline != "greedy":  # the others learn from sampled episodes
                rows = ~torch.tensor(self.GREEDY)
            else:
                rows = torch.ones(len(self.LENGTHS), dtype=torch.bool)
            for unit, group in enumerate(sorted(set(self.GROUPS))):
                own = rows & (torch.tensor(self.GROUPS) == group)
                part = batch[own]
                if baseline != "greedy":
                    part = part.exclude("greedy")
                expected = self._loss_gradient(actor, part, baseline, scale)
                torch.testing.assert_close(gradients[name][unit], expected, msg=name)

    @pytest.mark.parametrize("key", ["greedy", ("collector", "greedy")])
    def test_greedy_episodes_count_in_no_estimator(self, key):
        torch.manual_seed(0)
        actor = make_categorical_actor()
        batch = _grouped(self.LENGTHS, self.GROUPS, self.GREEDY)
        batch[key] = batch.pop("greedy")
        sampled = batch[~torch.tensor(self.GREEDY)].exclude(key)
        estimators = ["episode_return", "reward_to_go", "leave_one_out", "group_mean"]
        loss = ReinforceLoss(actor)
        loss.set_keys(greedy=key)
        stats = GradientStatistics(loss, unit="group", estimators=estimators)
        got, expected = stats(batch), stats(sampled)
        for name in estimators:
            torch.testing.assert_close(got[name, "mean_gradient"], expected[name, "mean_gradient"])
        assert got["reward_to_go", "units"].item() == 4
        # By default, the greedy baseline is measured where the batch has greedy episodes.
        assert "greedy" in GradientStatistics(loss, unit="group")(batch).keys()
        assert "greedy" not in GradientStatistics(loss, unit="group")(sampled).keys()

    def test_the_greedy_estimator_needs_greedy_episodes_when_asked_for(self):
        loss = ReinforceLoss(make_categorical_actor())
        batch = _grouped(self.LENGTHS, self.GROUPS)
        with pytest.raises(KeyError, match="baseline='greedy': the key greedy"):
            GradientStatistics(loss, unit="group", estimators=["greedy"])(batch)

    def test_a_cut_episode_is_refused(self):
        loss = ReinforceLoss(make_categorical_actor())
        batch = _grouped(self.LENGTHS, self.GROUPS)
        batch["next", "done"][0] = False
        with pytest.raises(ValueError, match="compares whole episodes"):
            GradientStatistics(loss, unit="group", estimators=["leave_one_out"])(batch)

    def test_every_group_baseline_is_measured(self):
        assert {b for b in GROUP_BASELINES} <= set(GROUP_ESTIMATORS) <= set(ESTIMATORS)
