"""Categorical actors with less Python around each call: the same actions from the same
random stream, and the same distributions, faster. A collector calls its policy at every
step ([`lean_policy`][rl_pg.lean.lean_policy]), a loss builds the distribution once per
batch ([`LeanCategoricalActor`][rl_pg.lean.LeanCategoricalActor], what
[`mlp_actor`][rl_pg.models.mlp_actor] builds for discrete actions)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import (
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
)
from torch.nn.modules import module as _torch_module
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator

__all__ = [
    "DirectSequential",
    "LeanCategoricalActor",
    "LeanCategoricalPolicy",
    "direct_network",
    "hooked",
    "hooked_globally",
    "lean_policy",
    "plain_layers",
    "run_plain",
    "sample_categorical",
]


def lean_policy(actor: TensorDictModuleBase) -> TensorDictModuleBase:
    """``actor`` for collection: the same actions, with less Python around each call.

    A collector calls its policy at every step, and for a small network most of that
    call is TensorDict-module and distribution bookkeeping rather than arithmetic. When
    ``actor`` is a categorical policy made of plain ``TensorDictModule`` s (what
    [`mlp_actor`][rl_pg.models.mlp_actor] builds for discrete actions, or a shared
    trunk followed by a head), this returns a
    [`LeanCategoricalPolicy`][rl_pg.lean.LeanCategoricalPolicy] over the same
    modules (and so the same parameters); any other actor is returned unchanged.

    Examples:
        >>> import torch
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.lean import lean_policy
        >>> from rl_pg.models import mlp_actor
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> env = GridWorldEnv(batch_size=8)
        >>> actor = mlp_actor(env)
        >>> lean = lean_policy(actor)
        >>> type(lean).__name__
        'LeanCategoricalPolicy'
        >>> td = env.reset()
        >>> with set_exploration_type(ExplorationType.RANDOM):  # what collectors do
        ...     _ = torch.manual_seed(0); a = actor(td.clone())["action"]
        ...     _ = torch.manual_seed(0); b = lean(td.clone())["action"]
        >>> torch.equal(a, b)
        True
    """
    if LeanCategoricalPolicy.supports(actor):
        return LeanCategoricalPolicy(actor)
    return actor


class LeanCategoricalPolicy(TensorDictModuleBase):
    """Samples a categorical ``ProbabilisticTensorDictSequential`` as it would, faster.

    Runs each ``TensorDictModule`` 's network directly on its inputs, then draws the
    action as ``torch.distributions.Categorical(logits=...).sample()`` does (the same
    operations on the same random stream, hence the same actions; the last one by
    [`sample_categorical`][rl_pg.lean.sample_categorical]), writing the same entries as
    the actor. Outside random interaction (e.g. greedy evaluation
    under ``set_exploration_type(DETERMINISTIC)``) it defers to the actor itself.

    Args:
        actor (ProbabilisticTensorDictSequential): a policy for which
            ``LeanCategoricalPolicy.supports(actor)`` is true (see
            [`lean_policy`][rl_pg.lean.lean_policy], which checks).
    """

    def __init__(self, actor: ProbabilisticTensorDictSequential) -> None:
        if not self.supports(actor):
            raise TypeError(
                f"LeanCategoricalPolicy needs a categorical ProbabilisticTensorDictSequential "
                f"of plain TensorDictModules, got {type(actor).__name__}: use "
                f"rl_pg.lean.lean_policy(actor), which keeps other actors as they are."
            )
        super().__init__()
        self.actor = actor
        self.in_keys, self.out_keys = actor.in_keys, actor.out_keys
        *modules, head = actor.module
        self._layers = [
            (direct_network(m.module), list(m.in_keys), m.out_keys[0]) for m in _plain(modules)
        ]
        self._logits_key = head.in_keys[0]
        self._action_key = head.out_keys[0]
        self._default = head.default_interaction_type

    @property
    def action_key(self):
        """The key the policy writes its action to (its actor's)."""
        return self._action_key

    @staticmethod
    def supports(actor) -> bool:
        """Whether ``actor`` has the structure this policy reproduces exactly."""
        if not isinstance(actor, ProbabilisticTensorDictSequential) or len(actor.module) < 2:
            return False
        *modules, head = actor.module
        return (
            _plain(modules) is not None
            and isinstance(head, ProbabilisticTensorDictModule)
            and head.distribution_class is torch.distributions.Categorical
            and not head.distribution_kwargs
            and not head.return_log_prob
            and list(head.in_keys) == ["logits"]
            and len(head.out_keys) == 1
            and not getattr(head, "safe", False)
        )

    def get_dist(self, tensordict: TensorDictBase) -> torch.distributions.Categorical:
        """The actor's action distribution at ``tensordict`` (what ``actor.get_dist``
        returns, gradients included), writing the networks' outputs into it."""
        return torch.distributions.Categorical(logits=self._logits(tensordict))

    def _logits(self, tensordict: TensorDictBase) -> torch.Tensor:
        for module, in_keys, out_key in self._layers:
            tensordict.set(out_key, module(*(tensordict.get(key) for key in in_keys)))
        return tensordict.get(self._logits_key)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self._samples():
            return self.actor(tensordict)
        tensordict.set(self._action_key, _sample(self._logits(tensordict)))
        return tensordict

    def acts_on(self, keys) -> bool:
        """Whether [`act`][rl_pg.lean.LeanCategoricalPolicy.act] can run on a dict of
        tensors at ``keys`` alone: every network reads one of them, or an earlier
        network's output."""
        known = set(keys)
        for _, in_keys, out_key in self._layers:
            if not known.issuperset(in_keys):
                return False
            known.add(out_key)
        return True

    def act(self, values: dict) -> dict | None:
        """``forward`` on a dict of tensors instead of a TensorDict, for a caller that
        builds its batch itself (a [`SegmentCollector`][rl_pg.collectors.SegmentCollector]):
        adds to ``values`` what ``forward`` writes, each network's output and the sampled
        action (the same operations on the same random stream), and returns it. Returns
        None outside random interaction, where ``forward`` defers to the actor: call the
        policy on a TensorDict then.

        Args:
            values (dict): the inputs, keyed as the actor reads them (see
                [`acts_on`][rl_pg.lean.LeanCategoricalPolicy.acts_on]).
        """
        if not self._samples():
            return None
        run_plain(self._layers, values)
        values[self._action_key] = _sample(values[self._logits_key])
        return values

    def _samples(self) -> bool:
        return (exploration_type() or self._default) == ExplorationType.RANDOM


def _sample(logits: torch.Tensor) -> torch.Tensor:
    """``Categorical(logits=logits).sample()``: its probabilities, operation for
    operation, then its draw (see ``sample_categorical``)."""
    logits = logits - logits.logsumexp(dim=-1, keepdim=True)
    return sample_categorical(torch.softmax(logits, dim=-1))


def sample_categorical(probs: torch.Tensor) -> torch.Tensor:
    """One draw per row of ``probs`` (categorical distributions over the last dimension):
    ``torch.multinomial(probs, 1, replacement=True)``, which ``Categorical.sample`` calls,
    without the checks that cost that call most of its time.

    For one sample ``torch.multinomial`` draws ``q ~ Exp(1)`` of ``probs`` ' shape and
    returns ``argmax(probs / q)`` (the Gumbel-max trick in exponential form). The same
    operations on the same generator give the same actions and leave the random stream
    where it leaves it (``tests/test_models.py`` checks both against the installed
    PyTorch). Of its checks, the one a softmax's output can fail is kept: NaN
    probabilities (a diverged network, or NaN in its inputs) raise a ``ValueError``
    instead of an action.

    Args:
        probs (torch.Tensor): probabilities, ``[..., num_actions]``, each row summing to 1.

    Returns:
        torch.Tensor: the sampled indices, shape ``probs.shape[:-1]``, int64.
    """
    ratios = probs / torch.empty_like(probs).exponential_(1)
    if bool(probs.isnan().any()):
        raise ValueError(
            f"The policy's action probabilities hold {int(probs.isnan().sum())} NaN value(s): "
            f"its network's outputs are NaN or +inf. Its parameters diverged (lower the "
            f"learning rate or clip gradients) or its inputs hold NaN or inf."
        )
    return ratios.argmax(dim=-1)


class LeanCategoricalActor(ProbabilisticActor):
    """A ``ProbabilisticActor`` whose ``get_dist`` builds its categorical distribution
    as [`LeanCategoricalPolicy`][rl_pg.lean.LeanCategoricalPolicy] does: the same
    distribution (gradients included) and the same entries written, with less Python.

    It takes ``ProbabilisticActor`` 's arguments and holds the same modules (so the same
    parameter names in a ``state_dict``); an actor whose structure the shortcut does not
    reproduce (see ``LeanCategoricalPolicy.supports``) builds its distribution as
    ``ProbabilisticActor`` does. Anything holding the actor gets the shortcut, a
    ``ReinforceLoss`` included, without knowing of it.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.lean import LeanCategoricalActor
        >>> env = GridWorldEnv(batch_size=4)
        >>> actor = LeanCategoricalActor(
        ...     TensorDictModule(torch.nn.Linear(16, 4), ["observation"], ["logits"]),
        ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
        ... )
        >>> td = env.reset()
        >>> torch.equal(actor.get_dist(td.clone()).logits,
        ...             torch.distributions.Categorical(logits=actor(td)["logits"]).logits)
        True
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # Kept out of the module tree: its modules are this actor's own.
        self.__dict__["_lean"] = (
            LeanCategoricalPolicy(self) if LeanCategoricalPolicy.supports(self) else None
        )

    def get_dist(self, tensordict: TensorDictBase, tensordict_out=None, **kwargs):
        if self._lean is None or tensordict_out is not None or kwargs:
            return super().get_dist(tensordict, tensordict_out, **kwargs)
        return self._lean.get_dist(tensordict)


def _plain(modules) -> list[TensorDictModule] | None:
    """The ``TensorDictModule`` s that ``modules`` runs in order (nested sequences
    flattened), or None if one of them does more than call its network on its inputs."""
    layers = []
    for m in modules:
        if type(m) is TensorDictSequential:
            inner = _plain(m.module)
            if inner is None or set(m.out_keys) != {k for i in inner for k in i.out_keys}:
                return None  # e.g. selected_out_keys: not every output is written
            layers += inner
        elif (
            type(m) in (TensorDictModule, ValueOperator)  # ValueOperator only sets keys
            and m.method is None
            and not m.method_kwargs
            and m._kwargs is None
            and len(m.out_keys) == 1
            and not (m._forward_hooks or m._forward_pre_hooks)
        ):
            layers.append(m)
        else:
            return None
    return layers


def plain_layers(module) -> list[tuple[torch.nn.Module, list, object]] | None:
    """``(network, in_keys, out_key)`` for each ``TensorDictModule`` that ``module`` runs
    in order, when each only calls its network on its inputs (a ``ValueOperator``, an
    ``MLP`` wrapped with its keys, a sequence of such); None otherwise."""
    layers = _plain([module])
    if layers is None:
        return None
    return [(direct_network(m.module), list(m.in_keys), m.out_keys[0]) for m in layers]


def run_plain(layers, values: dict) -> dict:
    """Runs ``plain_layers``' networks on the tensors of ``values`` (keyed as the
    modules' keys), adding each output: what the modules would write into a
    TensorDict, without one."""
    for network, in_keys, out_key in layers:
        values[out_key] = network(*(values[key] for key in in_keys))
    return values


def direct_network(network: torch.nn.Module):
    """``network``, or for a plain stack of layers (an ``nn.Sequential``, or TorchRL's
    ``MLP``) a callable that computes exactly what it does with less Python: see
    [`DirectSequential`][rl_pg.lean.DirectSequential]."""
    if type(network) is torch.nn.Sequential or (
        type(network) is MLP and getattr(network, "_reshape_out", True) is False
    ):
        return DirectSequential(network)
    return network


class DirectSequential:
    """Calls a stack of layers as its ``forward`` does, without ``nn.Module``'s call
    machinery around each layer.

    For the recipes' small MLPs over a few environments that machinery is a sizeable
    share of each call, paid at every step of collection: each ``Linear`` runs here as
    ``F.linear`` on the layer's current weight and bias (read at every call, so swapped
    or updated parameters are used as the module would use them) and ``Tanh``, ``ReLU``
    and ``Sigmoid`` as their functions, which is what their ``forward`` does: the same
    operations, the same outputs and the same autograd graph. Any other layer, a layer
    or network with a hook, a global module hook, or several inputs are left to
    ``nn.Module``.

    Args:
        network (torch.nn.Sequential): the layers (an ``MLP`` whose output is not
            reshaped is one).
    """

    def __init__(self, network: torch.nn.Sequential) -> None:
        self.network = network

    def __call__(self, *inputs: torch.Tensor) -> torch.Tensor:
        network = self.network
        if len(inputs) != 1 or hooked(network) or hooked_globally():
            return network(*inputs)
        out = inputs[0]
        for layer in network._modules.values():  # read at each call: layers may be replaced
            function = _direct_function(layer)
            if function is None or hooked(layer):
                out = layer(out)
            elif function is F.linear:
                out = F.linear(out, layer.weight, layer.bias)
            else:
                out = function(out)
        return out


def _direct_function(layer: torch.nn.Module):
    """The function a layer's ``forward`` applies, for the kinds run directly."""
    kind = type(layer)
    if kind is torch.nn.Linear:
        return F.linear
    if kind is torch.nn.Tanh:
        return torch.tanh
    if kind is torch.nn.Sigmoid:
        return torch.sigmoid
    if kind is torch.nn.ReLU and not layer.inplace:
        return torch.relu
    return None


def hooked(module: torch.nn.Module) -> bool:
    """Whether ``module`` has hooks of its own (forward or backward), which a direct
    call of its layers would skip."""
    return bool(
        module._forward_hooks
        or module._forward_pre_hooks
        or module._backward_hooks
        or module._backward_pre_hooks
    )


def hooked_globally() -> bool:
    """Whether torch has global module hooks registered, which every module's call runs
    (and a direct call of the layers would skip)."""
    return bool(
        _torch_module._global_forward_hooks
        or _torch_module._global_forward_pre_hooks
        or _torch_module._global_backward_hooks
        or _torch_module._global_backward_pre_hooks
    )
