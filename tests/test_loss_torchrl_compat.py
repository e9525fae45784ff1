"""rl_pg.ReinforceLoss as a drop-in for torchrl.objectives.ReinforceLoss.

Every path that TorchRL 0.14's own ``TestReinforce`` (pytorch/rl,
``test/objectives/test_ppo.py``) exercises runs here against both classes: value
networks and estimators given or made by the loss, delayed values, functional or not,
parameter resets, default and renamed keys (before and after the estimator is made),
separate losses, keyword calls without a TensorDict (``dispatch``) and
``select_out_keys``, reductions and value clipping. TorchRL's data conventions are kept
on purpose: ``randn`` actions under a ``TanhNormal`` whose bounds the actor never
declares. On the same modules and data both classes give the same numbers.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

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
from torch import nn
from torchrl.modules import MLP, TanhNormal, ValueOperator
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
            # Outside TanhNormal's [-1, 1] at times, as in TorchRL's tests: the actor
            # declares no bounds (unbounded spec), so the loss must score them.
            "action": torch.randn(BATCH, N_ACT, generator=generator),
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
            "action": torch.randn(*shape, N_ACT),
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


RENAMED = {
    "advantage": "advantage_test",
    "value_target": "value_target_test",
    "value": "state_value_test",
    "reward": "reward_test",
    "done": ("done", "test"),
    "terminated": ("terminated", "test"),
}


_FRESH_SELECT_OUT_KEYS = textwrap.dedent(
    """
    import torch
    from conftest import make_critic, make_gaussian_actor
    from test_loss_torchrl_compat import IMPLEMENTATIONS, _flat_batch
    loss_fn = IMPLEMENTATIONS[{name!r}](make_gaussian_actor(3, 5), make_critic(3))
    loss_fn.select_out_keys("loss_actor")
    data = _flat_batch()
    out = loss_fn(
        action=data["action"], observation=data["observation"],
        next_reward=data["next", "reward"], next_done=data["next", "done"],
        next_terminated=data["next", "terminated"],
        next_observation=data["next", "observation"],
    )
    assert isinstance(out, torch.Tensor) and out.shape == (), out
    """
)


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

    def test_reset_parameters_recursive(self, loss_class):
        actor, critic = _modules()
        loss_fn = loss_class(actor, critic)
        params = loss_fn.named_parameters()
        with torch.no_grad():
            for _, param in params:
                param += 1000
        shifted = {name: param.clone() for name, param in loss_fn.named_parameters()}
        loss_fn.reset_parameters_recursive()
        for name, param in loss_fn.named_parameters():
            assert (param != shifted[name]).any(), name

    def test_default_keys(self, loss_class):
        actor, critic = _modules()
        keys = loss_class(actor, critic).tensor_keys
        assert (keys.advantage, keys.value_target, keys.value) == (
            "advantage",
            "value_target",
            "state_value",
        )
        assert (keys.sample_log_prob, keys.action) == ("action_log_prob", "action")
        assert (keys.reward, keys.done, keys.terminated) == ("reward", "done", "terminated")

    def test_unknown_key_is_refused(self, loss_class):
        actor, critic = _modules()
        with pytest.raises(ValueError, match="not an accepted tensordict key"):
            loss_class(actor, critic).set_keys(unknown_key="x")

    @pytest.mark.parametrize("one_at_a_time", [True, False])
    def test_any_key_can_be_renamed_before_returns_are_needed(self, loss_class, one_at_a_time):
        # Renaming value to a key the critic does not write is accepted until the loss
        # needs returns (TorchRL makes its estimator only then).
        actor, critic = _modules()
        loss_fn = loss_class(actor, critic)
        names = ("advantage", "value_target", "value", "sample_log_prob")
        names += ("reward", "done", "terminated")
        if one_at_a_time:
            for name in names:
                loss_fn.set_keys(**{name: "test1"})
                assert getattr(loss_fn.tensor_keys, name) == "test1"
        else:
            loss_fn.set_keys(**dict.fromkeys(names, "test1"))
        assert all(getattr(loss_fn.tensor_keys, name) == "test1" for name in names)

    def test_a_value_key_the_critic_does_not_write_fails_when_returns_are_needed(self, loss_class):
        actor, critic = _modules()
        loss_fn = loss_class(actor, critic)
        loss_fn.set_keys(value="test1")
        with pytest.raises(KeyError, match="test1"):
            loss_fn(_flat_batch())

    def test_renaming_the_value_key_back_repairs_the_loss(self, loss_class):
        actor, critic = _modules()
        loss_fn = loss_class(actor, critic)
        loss_fn.set_keys(value="test1")
        loss_fn.set_keys(value="state_value")
        assert torch.isfinite(loss_fn(_flat_batch())["loss_actor"])

    @pytest.mark.parametrize("td_est", ESTIMATORS[:-1])
    def test_renamed_keys_reach_the_estimator_made_after(self, loss_class, td_est):
        torch.manual_seed(0)
        actor = make_gaussian_actor(N_OBS, N_ACT)
        critic = ValueOperator(nn.Linear(N_OBS, 1), ["observation"], ["state_value_test"])
        loss_fn = loss_class(actor, critic)
        loss_fn.set_keys(**RENAMED)
        loss_fn.make_value_estimator(td_est)
        for name, key in RENAMED.items():
            assert getattr(loss_fn.value_estimator.tensor_keys, name) == key

    @pytest.mark.parametrize("td_est", ESTIMATORS[:-1])
    def test_renamed_keys_reach_the_estimator_made_before(self, loss_class, td_est):
        # The value key must name what the critic writes when the estimator is made, so
        # only the other keys can move afterwards.
        actor, critic = _modules()
        loss_fn = loss_class(actor, critic)
        loss_fn.make_value_estimator(td_est)
        renamed = {k: v for k, v in RENAMED.items() if k != "value"}
        loss_fn.set_keys(**renamed)
        for name, key in renamed.items():
            assert getattr(loss_fn.value_estimator.tensor_keys, name) == key

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
    @pytest.mark.parametrize("observation_key", ["observation", "observation2"])
    @pytest.mark.parametrize("reward_key", ["reward", "reward2"])
    @pytest.mark.parametrize("done_key", ["done", "done2"])
    @pytest.mark.parametrize("terminated_key", ["terminated", "terminated2"])
    def test_call_without_tensordict(
        self, loss_class, action_key, observation_key, reward_key, done_key, terminated_key
    ):
        torch.manual_seed(0)
        actor = make_gaussian_actor(N_OBS, N_ACT, observation_key=observation_key)
        critic = ValueOperator(nn.Linear(N_OBS, 1), in_keys=[observation_key])
        loss_fn = loss_class(actor_network=actor, critic_network=critic)
        loss_fn.set_keys(
            reward=reward_key, done=done_key, action=action_key, terminated=terminated_key
        )
        data = _flat_batch()
        kwargs = {
            action_key: data["action"],
            observation_key: data["observation"],
            f"next_{reward_key}": data["next", "reward"],
            f"next_{done_key}": data["next", "done"],
            f"next_{terminated_key}": data["next", "terminated"],
            f"next_{observation_key}": data["next", "observation"],
        }
        loss_actor, loss_value = loss_fn(**kwargs)
        out = loss_fn(TensorDict(kwargs, [BATCH]).unflatten_keys("_"))
        torch.testing.assert_close(out["loss_actor"], loss_actor)
        torch.testing.assert_close(out["loss_value"], loss_value)
        loss_fn.select_out_keys("loss_actor")
        assert loss_fn(**kwargs) == out["loss_actor"]

    def test_select_out_keys_in_a_fresh_interpreter(self):
        # tensordict turns a class-level ``out_keys`` list into a property only when that
        # class is first instantiated: this must work before TorchRL's class ever is.
        # One fresh interpreter per implementation, both at once.
        # The rl_pg under test (the checkout's, or a mutated copy's) before the installed one.
        tests_dir = str(Path(__file__).parent)
        package = str(Path(rl_pg.__file__).parents[1])
        path = os.pathsep.join([tests_dir, package])
        env = {**os.environ, "PYTHONPATH": path, "PYTHONDONTWRITEBYTECODE": "1"}
        processes = {
            name: subprocess.Popen(
                [sys.executable, "-c", _FRESH_SELECT_OUT_KEYS.format(name=name)],
                cwd=tests_dir,
                env=env,
                stderr=subprocess.PIPE,
                text=True,
            )
            for name in IMPLEMENTATIONS
        }
        for name, process in processes.items():
            _, stderr = process.communicate(timeout=300)
            assert process.returncode == 0, f"{name}:\n{stderr}"

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
        loss_fn = loss_class(actor, critic, clip_value=clip_value)
        value = data.pop("state_value")
        if clip_value is not None:
            with pytest.raises(KeyError, match=r"clip_value is set to .* state_value was not"):
                loss_fn(data)
        data["state_value"] = value
        out = loss_fn(data)
        assert ("value_clip_fraction" in out.keys()) == (clip_value is not None)
        assert "loss_value" in out.keys()

    @pytest.mark.parametrize("clip_value", [True, torch.tensor([0.5, 1.0])])
    def test_value_clipping_rejects_what_is_not_one_number(self, loss_class, clip_value):
        actor, critic = _modules()
        with pytest.raises(ValueError, match="clip_value must be a float or a scalar tensor"):
            loss_class(actor, critic, clip_value=clip_value)


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

    @pytest.mark.parametrize(("delay_value", "functional"), [(False, True), (True, True),
                                                             (False, False)])  # fmt: skip
    def test_the_state_of_either_loads_into_the_other(self, delay_value, functional):
        actor, critic = _modules()
        kwargs = {"delay_value": delay_value, "functional": functional}
        ours = rl_pg.ReinforceLoss(actor, critic, **kwargs)
        theirs = torchrl.objectives.ReinforceLoss(actor, critic, **kwargs)
        ours(_flat_batch()), theirs(_flat_batch())  # as in training: the estimators made
        assert ours.state_dict().keys() == theirs.state_dict().keys()
        theirs.load_state_dict(ours.state_dict())
        ours.load_state_dict(theirs.state_dict())

    def test_rl_pg_loss_is_a_torchrl_reinforce_loss(self):
        actor, critic = _modules()
        assert isinstance(rl_pg.ReinforceLoss(actor, critic), torchrl.objectives.ReinforceLoss)
