"""rl_pg.ReinforceLoss as a drop-in for torchrl.objectives.ReinforceLoss.

The scenarios of TorchRL 0.14.1's own ReinforceLoss tests (value networks and
estimators, delayed values, functional or not, keys, separate losses, calls without
a TensorDict, reductions, value clipping) run against both classes, and on the same
modules and data both give the same numbers.
"""

from __future__ import annotations

import pytest
import torch
import torchrl.objectives
from conftest import make_critic, make_gaussian_actor
from tensordict import TensorDict
from tensordict.nn import (
    NormalParamExtractor,
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictSequential,
)
from torchrl.modules import MLP, TanhNormal
from torchrl.objectives import ValueEstimators
from torchrl.objectives.value import GAE, TD1Estimator, TDLambdaEstimator

import rl_pg

N_OBS, N_ACT, BATCH = 3, 5, 4
IMPLEMENTATIONS = {
    "torchrl": torchrl.objectives.ReinforceLoss,
    "rl_pg": rl_pg.ReinforceLoss,
}


@pytest.fixture(params=list(IMPLEMENTATIONS))
def loss_class(request):
    return IMPLEMENTATIONS[request.param]


def _modules(seed: int = 0):
    torch.manual_seed(seed)
    return make_gaussian_actor(N_OBS, N_ACT), make_critic(N_OBS)


def _flat_batch(seed: int = 1) -> TensorDict:
    generator = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(BATCH, N_OBS, generator=generator),
            "next": {
                "observation": torch.randn(BATCH, N_OBS, generator=generator),
                "reward": torch.randn(BATCH, 1, generator=generator),
                "done": torch.zeros(BATCH, 1, dtype=torch.bool),
                "terminated": torch.zeros(BATCH, 1, dtype=torch.bool),
            },
            "action": torch.rand(BATCH, N_ACT, generator=generator) * 1.8 - 0.9,
        },
        [BATCH],
        names=["time"],
    )


def _shared_trunk_setup(seed: int = 0):
    """Actor and critic on a common trunk, with a [2, 10] batch."""
    torch.manual_seed(seed)
    common = TensorDictModule(
        MLP(in_features=N_OBS, out_features=2, num_cells=4, depth=3), ["obs"], ["hidden"]
    )
    actor = ProbabilisticTensorDictSequential(
        common,
        TensorDictModule(
            MLP(in_features=2, out_features=2 * N_ACT, num_cells=4, depth=2),
            ["hidden"],
            ["param"],
        ),
        TensorDictModule(NormalParamExtractor(), ["param"], ["loc", "scale"]),
        ProbabilisticTensorDictModule(
            in_keys=["loc", "scale"], out_keys=["action"], distribution_class=TanhNormal
        ),
    )
    critic = TensorDictSequential(
        common,
        TensorDictModule(
            MLP(in_features=2, out_features=1, num_cells=4, depth=2), ["hidden"], ["state_value"]
        ),
    )
    shape = (2, 10)
    data = TensorDict(
        {
            "obs": torch.randn(*shape, N_OBS),
            "action": torch.rand(*shape, N_ACT) * 1.8 - 0.9,
            "next": {
                "obs": torch.randn(*shape, N_OBS),
                "reward": torch.randn(*shape, 1),
                "done": torch.zeros(*shape, 1, dtype=torch.bool),
                "terminated": torch.zeros(*shape, 1, dtype=torch.bool),
            },
        },
        shape,
        names=[None, "time"],
    )
    return actor, critic, common, data


ESTIMATORS = [
    ValueEstimators.TD1,
    ValueEstimators.TD0,
    ValueEstimators.GAE,
    ValueEstimators.TDLambda,
    None,
]


class TestTorchRLScenarios:
    @pytest.mark.parametrize("gradient_mode", [True, False])
    @pytest.mark.parametrize("advantage", ["gae", "td", "td_lambda", None])
    @pytest.mark.parametrize("td_est", ESTIMATORS)
    @pytest.mark.parametrize(
        ("delay_value", "functional"), [(False, True), (False, False), (True, True)]
    )
    def test_value_net(self, loss_class, advantage, gradient_mode, delay_value, td_est, functional):
        actor, critic = _modules()
        estimators = {
            "gae": lambda: GAE(
                gamma=0.9, lmbda=0.9, value_network=critic, differentiable=gradient_mode
            ),
            "td": lambda: TD1Estimator(
                gamma=0.9, value_network=critic, differentiable=gradient_mode
            ),
            "td_lambda": lambda: TDLambdaEstimator(
                gamma=0.9, lmbda=0.9, value_network=critic, differentiable=gradient_mode
            ),
        }
        loss_fn = loss_class(actor, critic, delay_value=delay_value, functional=functional)
        data = _flat_batch()
        if advantage is not None:
            target = loss_fn.target_critic_network_params if delay_value else None
            estimators[advantage]()(
                data, params=TensorDict.from_module(critic), target_params=target
            )
        elif td_est is not None:
            loss_fn.make_value_estimator(td_est)
        out = loss_fn(data)
        actor_params, critic_params = list(actor.parameters()), list(critic.parameters())
        torch.autograd.grad(out["loss_actor"], actor_params, retain_graph=True)
        torch.autograd.grad(out["loss_value"], critic_params, retain_graph=True)
        with pytest.raises(RuntimeError, match="used in the graph"):
            torch.autograd.grad(out["loss_actor"], critic_params, retain_graph=True)
        with pytest.raises(RuntimeError, match="used in the graph"):
            torch.autograd.grad(out["loss_value"], actor_params, retain_graph=True)

    @pytest.mark.parametrize("td_est", ESTIMATORS[:-1])
    def test_keys_reach_the_value_estimator(self, loss_class, td_est):
        actor, critic = _modules()
        loss_fn = loss_class(actor, critic)
        loss_fn.make_value_estimator(td_est)
        mapping = {
            "advantage": "advantage_test",
            "value_target": "value_target_test",
            "reward": "reward_test",
            "done": ("done", "test"),
            "terminated": ("terminated", "test"),
        }
        loss_fn.set_keys(**mapping)
        for name, key in mapping.items():
            assert getattr(loss_fn.value_estimator.tensor_keys, name) == key
        defaults = {
            "advantage": "advantage",
            "value_target": "value_target",
            "value": "state_value",
            "sample_log_prob": "action_log_prob",
            "reward": "reward",
            "done": "done",
            "terminated": "terminated",
        }
        for name, key in defaults.items():
            assert getattr(loss_class(actor, critic).tensor_keys, name) == key

    @pytest.mark.parametrize("separate_losses", [False, True])
    def test_separate_losses(self, loss_class, separate_losses):
        actor, critic, common, data = _shared_trunk_setup()
        loss_fn = loss_class(actor, critic, separate_losses=separate_losses)
        out = loss_fn(data)
        out["loss_value"].backward()
        n_common = len(list(common.parameters()))
        critic_grads = [p.grad for p in loss_fn.critic_network_params.values(True, True)]
        trunk_has_grad = any(g is not None and (g != 0).any() for g in critic_grads[:n_common])
        assert trunk_has_grad != separate_losses
        assert all(g is not None and (g != 0).any() for g in critic_grads[n_common:])

    @pytest.mark.parametrize("action_key", ["action", "action2"])
    @pytest.mark.parametrize("reward_key", ["reward", "reward2"])
    @pytest.mark.parametrize("done_key", ["done", "done2"])
    def test_call_without_tensordict(self, loss_class, action_key, reward_key, done_key):
        actor, critic = _modules()
        loss_fn = loss_class(actor_network=actor, critic_network=critic)
        loss_fn.set_keys(reward=reward_key, done=done_key, action=action_key)
        data = _flat_batch()
        kwargs = {
            action_key: data["action"],
            "observation": data["observation"],
            f"next_{reward_key}": data["next", "reward"],
            f"next_{done_key}": data["next", "done"],
            "next_terminated": data["next", "terminated"],
            "next_observation": data["next", "observation"],
        }
        loss_actor, loss_value = loss_fn(**kwargs)
        out = loss_fn(TensorDict(kwargs, [BATCH]).unflatten_keys("_"))
        torch.testing.assert_close(out["loss_actor"], loss_actor)
        torch.testing.assert_close(out["loss_value"], loss_value)
        loss_fn.select_out_keys("loss_actor")
        assert loss_fn(**kwargs) == out["loss_actor"]

    @pytest.mark.parametrize("reduction", [None, "none", "mean", "sum"])
    def test_reduction(self, loss_class, reduction):
        actor, critic, _, data = _shared_trunk_setup()
        out = loss_class(actor, critic, reduction=reduction)(data)
        for key in ("loss_actor", "loss_value"):
            expected = data.shape if reduction == "none" else torch.Size([])
            assert out[key].shape == expected

    @pytest.mark.parametrize("clip_value", [None, 0.5, torch.tensor(0.5)])
    def test_value_clipping(self, loss_class, clip_value):
        actor, critic, _, data = _shared_trunk_setup()
        GAE(gamma=0.9, lmbda=0.9, value_network=critic)(data)
        out = loss_class(actor, critic, clip_value=clip_value)(data)
        assert ("value_clip_fraction" in out.keys()) == (clip_value is not None)

    def test_value_clipping_rejects_a_bool(self, loss_class):
        actor, critic = _modules()
        with pytest.raises(ValueError, match="clip_value must be a float or a scalar tensor"):
            loss_class(actor, critic, clip_value=True)


class TestParityWithTorchRL:
    @pytest.mark.parametrize("td_est", ESTIMATORS)
    @pytest.mark.parametrize("reduction", ["none", "mean", "sum"])
    @pytest.mark.parametrize(("delay_value", "functional"), [(False, True), (False, False)])
    def test_same_losses_and_gradients(self, td_est, reduction, delay_value, functional):
        results = []
        for cls in IMPLEMENTATIONS.values():
            actor, critic, _, data = _shared_trunk_setup(seed=3)
            loss_fn = cls(
                actor, critic, reduction=reduction, delay_value=delay_value, functional=functional
            )
            if td_est is not None:
                loss_fn.make_value_estimator(td_est)
            out = loss_fn(data)
            total = sum(out[k].sum() for k in ("loss_actor", "loss_value"))
            grads = torch.autograd.grad(total, list(loss_fn.parameters()), allow_unused=True)
            results.append((out.select("loss_actor", "loss_value"), grads))
        (ours, our_grads), (theirs, their_grads) = results[1], results[0]
        torch.testing.assert_close(ours.to_dict(), theirs.to_dict())
        for mine, reference in zip(our_grads, their_grads, strict=True):
            torch.testing.assert_close(mine, reference)

    def test_rl_pg_loss_is_a_torchrl_reinforce_loss(self):
        actor, critic = _modules()
        assert isinstance(rl_pg.ReinforceLoss(actor, critic), torchrl.objectives.ReinforceLoss)
