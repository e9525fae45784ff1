"""Policy and value networks sized from an environment's specs."""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import partial
from typing import Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import (
    AddStateIndependentNormalScale,
    NormalParamExtractor,
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
)
from torch import nn
from torchrl.data import Bounded, Categorical, OneHot
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import (
    MLP,
    IndependentNormal,
    OneHotCategorical,
    PopArtValueNorm,
    ProbabilisticActor,
    RunningValueNorm,
    TanhNormal,
    ValueNorm,
    ValueOperator,
)

from rl_pg._checks import check_int
from rl_pg.distributions import BetaConcentrations, BoundedBeta

__all__ = [
    "LeanCategoricalPolicy",
    "PopArt",
    "RunningNorm",
    "lean_policy",
    "mlp_actor",
    "mlp_actor_critic",
    "mlp_critic",
    "popart_output",
    "update_running_norms",
]


class RunningNorm(nn.Module):
    """Standardises an observation with running statistics the learner keeps.

    ``(x - mean) / std`` per feature, clipped to ``[-clip, clip]``, with the mean and
    variance of every observation passed to [`update`][rl_pg.models.RunningNorm.update]
    (TorchRL's ``RunningValueNorm``, Welford's algorithm); the identity until the first
    update. Features of small spread (MetaDrive's heading and lane position vary by
    about 0.04 around 0.5) then weigh as much as the others from the first layer on.

    The statistics are buffers: they are saved with the model, reach collector workers
    with the weights, and change only when ``update`` is called (the training loop calls
    it after each optimiser step, on the batch's observations, see
    [`update_running_norms`][rl_pg.models.update_running_norms]), never while acting.

    Args:
        shape (int or tuple of int): the shape of one observation.

    Keyword Args:
        key (str): the batch entry ``update_running_norms`` reads. Defaults to
            ``"observation"``.
        clip (float): bound of the standardised values. Defaults to ``5.0``.
        min_std (float): floor of the standard deviation (a constant feature is not
            blown up). Defaults to ``1e-2``.

    Examples:
        >>> import torch
        >>> from rl_pg.models import RunningNorm
        >>> norm = RunningNorm(2)
        >>> x = torch.tensor([[0.5, 10.0], [0.6, 30.0]])
        >>> torch.equal(norm(x), x)  # no statistics yet
        True
        >>> norm.update(x)
        >>> norm(x)
        tensor([[-1., -1.],
                [ 1.,  1.]])
    """

    def __init__(
        self,
        shape: int | Sequence[int],
        *,
        key: str = "observation",
        clip: float = 5.0,
        min_std: float = 1e-2,
    ) -> None:
        super().__init__()
        self.stats = RunningValueNorm(shape=shape, epsilon=min_std**2)
        self.key = key
        self.clip = clip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        normalised = self.stats.normalize(x).clamp(-self.clip, self.clip)
        return torch.where(self.stats.count > 0, normalised, x)

    def update(self, x: torch.Tensor) -> None:
        """Adds the observations ``x`` (``[*batch, *shape]``) to the statistics."""
        self.stats.update(x.detach().to(self.stats.mean.dtype))


def update_running_norms(module: nn.Module, batch) -> None:
    """Updates every [`RunningNorm`][rl_pg.models.RunningNorm] inside ``module`` (each
    once, shared or not) with the batch's observations at its ``key``."""
    seen = set()
    for norm in module.modules():
        if isinstance(norm, RunningNorm) and id(norm) not in seen:
            seen.add(id(norm))
            norm.update(batch.get(norm.key))


class PopArt(ValueNorm):
    """A critic's output layer that learns in normalised units and answers in real ones.

    The layer ``linear`` predicts the standardised value `ν = (V − μ) / σ`; the module
    returns `V = σ ν + μ` with the running mean `μ` and scale `σ` of the value targets
    (PopArt: van Hasselt et al., 2016, "Learning values across many orders of
    magnitude"). Each [`update`][rl_pg.models.PopArt.update] moves `μ` and `σ` and
    rescales ``linear`` so that every output stays exactly what it was ("preserving
    outputs precisely"). Returns in the hundreds then cost the critic no more steps
    than returns near one: Adam moves each weight by about the learning rate, and the
    last layer's weights need only reach `ν`, of order one.

    A [`ReinforceLoss`][rl_pg.ReinforceLoss] given this module as ``value_norm``
    updates it once per batch, from the batch's value targets, and regresses `ν` on the
    standardised targets; advantages and bootstraps use `V`, at the rewards' scale.

    It is a TorchRL ``ValueNorm`` (``update``, ``normalize``, ``denormalize``,
    ``scale``); the statistics are those of ``stats``.

    Args:
        linear (nn.Linear): the output layer, one output per value (usually 1).

    Keyword Args:
        stats (ValueNorm, optional): the running statistics. Defaults to TorchRL's
            ``PopArtValueNorm(beta=0.99)``: an exponential average over about the last
            hundred batches, unbiased from the first.

    Examples:
        >>> import torch
        >>> from rl_pg.models import PopArt
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> head = PopArt(torch.nn.Linear(4, 1))
        >>> x = torch.randn(8, 4)
        >>> head.update(100 + 50 * torch.randn(256, 1))  # the first: no outputs to keep
        >>> before = head(x)
        >>> head.update(300 + 80 * torch.randn(256, 1))
        >>> torch.allclose(head(x), before, atol=1e-4)  # the outputs are preserved
        True
        >>> round(head.scale().item(), -1)  # σ of the targets seen so far
        120.0
    """

    def __init__(self, linear: nn.Linear, *, stats: ValueNorm | None = None) -> None:
        if not isinstance(linear, nn.Linear):
            raise TypeError(
                f"PopArt rescales an nn.Linear output layer, got {type(linear).__name__}."
            )
        if stats is None:
            stats = PopArtValueNorm(shape=linear.out_features, beta=0.99)
        if not isinstance(stats, ValueNorm):
            raise TypeError(
                f"stats must be a torchrl.modules.ValueNorm (e.g. PopArtValueNorm), got "
                f"{type(stats).__name__}."
            )
        if tuple(stats.shape) != (linear.out_features,):
            raise ValueError(
                f"stats has shape {tuple(stats.shape)} but the layer has "
                f"{linear.out_features} output(s): build stats with shape={linear.out_features}."
            )
        super().__init__(shape=stats.shape, epsilon=stats.epsilon)
        self.linear = linear
        self.stats = stats
        # denormalize(ν) = σ ν + μ, read from ``stats`` at each update: the identity until
        # the first, which has no trained outputs to preserve.
        self.register_buffer("mean", linear.weight.new_zeros(self.shape))
        self.register_buffer("std", linear.weight.new_ones(self.shape))
        self.register_buffer("updated", torch.zeros((), dtype=torch.bool))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.denormalize(self.linear(x))

    @torch.no_grad()
    def update(self, value_target: torch.Tensor) -> None:
        """Adds the targets ``value_target`` (``[*batch, out_features]``) to the
        statistics and rescales the layer so that its outputs do not change."""
        value_target = value_target.detach().to(self.mean.dtype)
        old_mean, old_std = self.mean.clone(), self.std.clone()
        self.stats.update(value_target)
        zero = torch.zeros_like(self.mean)
        self.mean.copy_(self.stats.denormalize(zero))
        self.std.copy_(self.stats.denormalize(zero + 1) - self.mean)
        if not bool(self.updated):
            self.updated.fill_(True)
            return
        self.linear.weight.mul_((old_std / self.std).unsqueeze(-1))
        if self.linear.bias is not None:
            self.linear.bias.mul_(old_std).add_(old_mean - self.mean).div_(self.std)

    def normalize(self, value_target: torch.Tensor) -> torch.Tensor:
        return (value_target - self.mean) / self.std

    def denormalize(self, normalised_value: torch.Tensor) -> torch.Tensor:
        return normalised_value * self.std + self.mean

    def scale(self) -> torch.Tensor:
        return self.std


def popart_output(critic: nn.Module) -> PopArt:
    """Makes the critic's output layer a [`PopArt`][rl_pg.models.PopArt] one, in place.

    The last ``nn.Linear`` in ``critic`` (its output layer, in any critic built from
    TorchRL's ``MLP`` or ``nn.Sequential``) is wrapped with its current weights; a
    critic whose output layer is already ``PopArt`` is left as it is. Give the result to
    [`ReinforceLoss`][rl_pg.ReinforceLoss] as ``value_norm``. Wrap a critic before it
    trains: the first update sets the statistics without preserving the outputs (a
    fresh critic's are noise near 0, and preserving them would leave its normalised
    output as far from the targets as the raw one was).

    Raises:
        ValueError: the critic has no ``nn.Linear`` layer.

    Examples:
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_critic, popart_output
        >>> critic = mlp_critic(GridWorldEnv(), hidden=(8,))
        >>> head = popart_output(critic)
        >>> head is popart_output(critic), type(head).__name__
        (True, 'PopArt')
    """
    existing = [module for module in critic.modules() if isinstance(module, PopArt)]
    if existing:
        return existing[-1]
    last = None
    for name, module in critic.named_modules():
        if isinstance(module, nn.Linear):
            last = name
    if last is None:
        raise ValueError(
            f"popart_output needs a critic whose output layer is an nn.Linear; "
            f"{type(critic).__name__} has none."
        )
    parent_name, _, child = last.rpartition(".")
    parent = critic.get_submodule(parent_name)
    head = PopArt(getattr(parent, child))
    setattr(parent, child, head)
    return head


def _running_norm(normalize, obs_shape, key: str) -> RunningNorm | None:
    if isinstance(normalize, RunningNorm):
        return normalize
    if normalize is True:
        return RunningNorm(tuple(obs_shape), key=key)
    if normalize is False:
        return None
    raise TypeError(f"normalize must be True, False or a RunningNorm, got {normalize!r}.")


def _trunk(
    env: EnvBase,
    out_features: int,
    hidden: Sequence[int],
    activation,
    key: str,
    normalize: bool | RunningNorm = False,
):
    hidden = _check_hidden(hidden)
    if key not in env.observation_spec.keys(True, True):
        raise KeyError(
            f"The environment has no observation {key!r}; its observations are "
            f"{list(env.observation_spec.keys(True, True))}. Pass observation_key=..."
        )
    spec = env.observation_spec[key]
    obs_shape = spec.shape[len(env.batch_size) :]
    norm = _running_norm(normalize, obs_shape, key)
    layers: list[nn.Module] = []
    if norm is not None:
        if tuple(norm.stats.shape) != tuple(obs_shape) or norm.key != key:
            raise ValueError(
                f"The RunningNorm passed as normalize= standardises {norm.key!r} of shape "
                f"{tuple(norm.stats.shape)}, but the observation is {key!r} of shape "
                f"{tuple(obs_shape)}: pass normalize=True to build a matching one."
            )
        layers.append(norm)
    if len(obs_shape) > 1:  # e.g. highway's [vehicles, features] table
        layers.append(nn.Flatten(start_dim=-len(obs_shape)))
    layers.append(
        MLP(
            in_features=math.prod(obs_shape),
            out_features=out_features,
            num_cells=list(hidden),
            activation_class=activation,
        )
    )
    return nn.Sequential(*layers) if len(layers) > 1 else layers[0]


def mlp_actor(
    env: EnvBase,
    *,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.Tanh,
    observation_key: str = "observation",
    normalize: bool | RunningNorm = False,
    bounded: Literal["tanh_normal", "normal", "beta"] = "tanh_normal",
    state_independent_scale: bool = False,
    init_scale: float = 1.0,
) -> ProbabilisticActor:
    """An MLP policy for ``env``'s action space.

    A categorical (index) action gets a softmax policy, a one-hot action a one-hot
    categorical, an unbounded continuous action an independent Normal. A bounded
    continuous action (whatever its per-dimension bounds, e.g. ``[-2, 2]`` for
    Pendulum) gets, as ``bounded`` says:

    - ``"tanh_normal"``: a ``TanhNormal`` squashed into the bounds;
    - ``"normal"``: an independent Normal whose samples the environment clips, as
      Stable-Baselines3's and CleanRL's on-policy agents do;
    - ``"beta"``: a [`BoundedBeta`][rl_pg.distributions.BoundedBeta] on the bounds.

    A policy-gradient loss recomputes the log-probability of the stored action. A
    ``TanhNormal`` whose mean drifted far past a bound would sample the bound itself in
    float32, and the loss would score that sample by a log-probability that is not its
    own: its mean is squashed into [-5, 5] before the tanh (TorchRL's ``tanh_loc``;
    ``tanh(5)`` is ``1 - 9e-5``). A clipped Normal whose mean drifts past a bound plays
    the bound whatever its noise, and learns no more there. A Beta has neither
    failure: on Pendulum it is the one that learns (see the recipe's page).
    Observations with several dimensions are flattened. A Gaussian's scale is an
    output of the network, as its mean is, or with ``state_independent_scale=True``
    one learned parameter per action dimension (tensordict's
    ``AddStateIndependentNormalScale``).

    Keyword Args:
        hidden (sequence of int): hidden layer widths. Defaults to ``(64, 64)``.
        activation (type): activation class. Defaults to ``nn.Tanh``.
        observation_key (str): the observation entry. Defaults to ``"observation"``.
        normalize (bool or RunningNorm): standardise the observation first with a
            [`RunningNorm`][rl_pg.models.RunningNorm] (``True``: a new one; a
            ``RunningNorm``: that one, to share it). Defaults to ``False``.
        bounded (str): the distribution of a bounded continuous action, above. With
            ``"normal"``, samples go to the environment as they are: gymnasium's
            Pendulum and LunarLanderContinuous clip them; for others append TorchRL's
            ``ClipTransform(in_keys_inv=["action"], ...)``. Defaults to
            ``"tanh_normal"``.
        state_independent_scale (bool): a Gaussian policy's scale is a learned
            parameter, the same in every state. Defaults to ``False``.
        init_scale (float): with ``state_independent_scale``, the scale at
            initialisation (before any squashing). Defaults to ``1.0``.

    Raises:
        ValueError: for a hidden width < 1, an action space bounded in some dimensions
            only, batched environments whose action bounds differ, an unknown
            ``bounded``, ``"beta"`` for an unbounded action, or a state-independent scale
            asked of a policy that is not Gaussian or with ``init_scale <= 0``.
        KeyError: when the environment has no ``observation_key``.

    Examples:
        >>> from rl_pg.envs import GridWorldEnv, gym_env
        >>> from rl_pg.models import mlp_actor
        >>> actor = mlp_actor(GridWorldEnv(batch_size=3), hidden=(32,))
        >>> actor(GridWorldEnv(batch_size=3).reset())["action"].shape
        torch.Size([3])
        >>> pendulums = gym_env("Pendulum-v1", num_envs=4)  # torque in [-2, 2]
        >>> action = mlp_actor(pendulums)(pendulums.reset())["action"]
        >>> action.shape, bool(action.abs().max() <= 2)
        (torch.Size([4, 1]), True)
        >>> beta = mlp_actor(pendulums, bounded="beta")
        >>> type(beta.get_dist(pendulums.reset())).__name__
        'BoundedBeta'
    """
    if bounded not in ("tanh_normal", "normal", "beta"):
        raise ValueError(f"bounded must be 'tanh_normal', 'normal' or 'beta', got {bounded!r}.")
    spec = env.action_spec
    n_act = spec.shape[-1] if spec.shape[len(env.batch_size) :] else 1
    if isinstance(spec, Categorical):
        n_act = spec.space.n
    discrete = isinstance(spec, (Categorical, OneHot))
    bounds = _action_bounds(spec, n_act) if isinstance(spec, Bounded) and not discrete else None
    if bounded == "beta" and bounds is None:
        raise ValueError(
            f"bounded='beta' needs a continuous action with finite bounds; this action "
            f"space is {type(spec).__name__}"
            + (" (discrete)." if discrete else " without bounds: use a Normal policy.")
        )
    if state_independent_scale and (discrete or (bounds is not None and bounded == "beta")):
        raise ValueError(
            "state_independent_scale=True sets the scale of a Gaussian policy, but this "
            + (
                f"action space is discrete ({type(spec).__name__})"
                if discrete
                else "policy is a Beta"
            )
            + ": leave it False."
        )
    trunk = partial(
        _trunk, env, hidden=hidden, activation=activation, key=observation_key, normalize=normalize
    )
    if discrete:
        distribution = (
            torch.distributions.Categorical if isinstance(spec, Categorical) else OneHotCategorical
        )
        return ProbabilisticActor(
            TensorDictModule(trunk(n_act), [observation_key], ["logits"]),
            in_keys=["logits"],
            spec=spec,
            distribution_class=distribution,
        )
    if bounds is not None and bounded == "beta":
        params = ["concentration1", "concentration0"]
        net = nn.Sequential(trunk(2 * n_act), BetaConcentrations())
        distribution, kwargs = BoundedBeta, {"low": bounds[0], "high": bounds[1]}
    else:
        params = ["loc", "scale"]
        if state_independent_scale:
            if not (math.isfinite(init_scale) and init_scale > 0):
                raise ValueError(f"init_scale must be a finite number > 0, got {init_scale!r}.")
            net = nn.Sequential(
                trunk(n_act), AddStateIndependentNormalScale(n_act, init_value=math.log(init_scale))
            )
        else:
            net = nn.Sequential(trunk(2 * n_act), NormalParamExtractor())
        distribution, kwargs = IndependentNormal, {}
        if bounds is not None and bounded == "tanh_normal":
            # tanh_loc: samples stay short of the bounds in float32 (see above).
            distribution = TanhNormal
            kwargs = {"low": bounds[0], "high": bounds[1], "tanh_loc": True}
    return ProbabilisticActor(
        TensorDictModule(net, [observation_key], params),
        in_keys=params,
        spec=spec,
        distribution_class=distribution,
        distribution_kwargs=kwargs,
    )


def _action_bounds(spec: Bounded, n_act: int) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Per-dimension ``(low, high)`` of one environment's action, or None if unbounded.

    A batched environment repeats its bounds along its batch dimensions; the policy's
    distribution needs them once, shaped like one action.
    """
    low = spec.space.low.reshape(-1, n_act)
    high = spec.space.high.reshape(-1, n_act)
    if not ((low == low[0]).all() and (high == high[0]).all()):
        raise ValueError(
            "The environments of this batch have different action bounds; mlp_actor builds "
            "one policy for all of them. Rescale their actions to common bounds first."
        )
    low, high = low[0], high[0]
    finite = torch.isfinite(low) & torch.isfinite(high)
    if not finite.any():
        return None  # a Box(-inf, inf): a plain Gaussian
    if not finite.all():
        raise ValueError(
            f"The action space is bounded in some dimensions and not in others (low="
            f"{low.tolist()}, high={high.tolist()}): give every dimension finite bounds "
            f"(e.g. with TorchRL's ClipTransform) or none."
        )
    return low, high


def _check_hidden(hidden: Sequence[int]) -> tuple[int, ...]:
    if (
        isinstance(hidden, str)
        or not hasattr(hidden, "__iter__")
        or getattr(hidden, "ndim", 1) != 1
    ):
        raise TypeError(
            f"hidden must be a sequence of layer widths such as (64, 64), got {hidden!r}."
        )
    return tuple(check_int(f"hidden[{i}]", width, low=1) for i, width in enumerate(hidden))


def mlp_critic(
    env: EnvBase,
    *,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.Tanh,
    observation_key: str = "observation",
    normalize: bool | RunningNorm = False,
) -> ValueOperator:
    """An MLP state-value network writing ``"state_value"``.

    Keyword Args:
        hidden (sequence of int): hidden layer widths. Defaults to ``(64, 64)``.
        activation (type): activation class. Defaults to ``nn.Tanh``.
        observation_key (str): the observation entry. Defaults to ``"observation"``.
        normalize (bool or RunningNorm): standardise the observation first with a
            [`RunningNorm`][rl_pg.models.RunningNorm] (``True``: a new one; a
            ``RunningNorm``: that one, to share it). Defaults to ``False``.

    Examples:
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_critic
        >>> env = GridWorldEnv()
        >>> mlp_critic(env)(env.reset())["state_value"].shape
        torch.Size([1])
    """
    return ValueOperator(
        _trunk(env, 1, hidden, activation, observation_key, normalize), in_keys=[observation_key]
    )


def mlp_actor_critic(
    env: EnvBase,
    *,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.Tanh,
    observation_key: str = "observation",
    normalize: bool = False,
    bounded: Literal["tanh_normal", "normal", "beta"] = "tanh_normal",
    state_independent_scale: bool = False,
    init_scale: float = 1.0,
) -> tuple[ProbabilisticActor, ValueOperator]:
    """An actor and a critic with the same layers (separate weights; with
    ``normalize=True``, one [`RunningNorm`][rl_pg.models.RunningNorm] for both).

    See [`mlp_actor`][rl_pg.models.mlp_actor] (which also takes
    ``bounded``, ``state_independent_scale`` and ``init_scale``) and
    [`mlp_critic`][rl_pg.models.mlp_critic].

    Examples:
        >>> from rl_pg.envs import BanditEnv
        >>> from rl_pg.models import mlp_actor_critic
        >>> actor, critic = mlp_actor_critic(BanditEnv(num_arms=3), hidden=(8,))
        >>> type(actor).__name__, type(critic).__name__
        ('ProbabilisticActor', 'ValueOperator')
    """
    kwargs = {"hidden": hidden, "activation": activation, "observation_key": observation_key}
    actor = mlp_actor(
        env,
        normalize=normalize,
        bounded=bounded,
        state_independent_scale=state_independent_scale,
        init_scale=init_scale,
        **kwargs,
    )
    if normalize is True:  # the critic shares the actor's statistics
        normalize = next(m for m in actor.modules() if isinstance(m, RunningNorm))
    return actor, mlp_critic(env, normalize=normalize, **kwargs)


def lean_policy(actor: TensorDictModuleBase) -> TensorDictModuleBase:
    """``actor`` for collection: the same actions, with less Python around each call.

    A collector calls its policy at every step, and for a small network most of that
    call is TensorDict-module and distribution bookkeeping rather than arithmetic. When
    ``actor`` is a categorical policy made of plain ``TensorDictModule`` s (what
    [`mlp_actor`][rl_pg.models.mlp_actor] builds for discrete actions, or a shared
    trunk followed by a head), this returns a
    [`LeanCategoricalPolicy`][rl_pg.models.LeanCategoricalPolicy] over the same
    modules (and so the same parameters); any other actor is returned unchanged.

    Examples:
        >>> import torch
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import lean_policy, mlp_actor
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
    action exactly as ``torch.distributions.Categorical(logits=...).sample()`` does (the
    same operations on the same random stream, hence the same actions), writing the
    same entries as the actor. Outside random interaction (e.g. greedy evaluation
    under ``set_exploration_type(DETERMINISTIC)``) it defers to the actor itself.

    Args:
        actor (ProbabilisticTensorDictSequential): a policy for which
            ``LeanCategoricalPolicy.supports(actor)`` is true (see
            [`lean_policy`][rl_pg.models.lean_policy], which checks).
    """

    def __init__(self, actor: ProbabilisticTensorDictSequential) -> None:
        if not self.supports(actor):
            raise TypeError(
                f"LeanCategoricalPolicy needs a categorical ProbabilisticTensorDictSequential "
                f"of plain TensorDictModules, got {type(actor).__name__}: use "
                f"rl_pg.models.lean_policy(actor), which keeps other actors as they are."
            )
        super().__init__()
        self.actor = actor
        self.in_keys, self.out_keys = actor.in_keys, actor.out_keys
        *modules, head = actor.module
        self._layers = [(m.module, list(m.in_keys), m.out_keys[0]) for m in _plain(modules)]
        self._logits_key = head.in_keys[0]
        self._action_key = head.out_keys[0]
        self._default = head.default_interaction_type

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
        kind = exploration_type() or self._default
        if kind != ExplorationType.RANDOM:
            return self.actor(tensordict)
        logits = self._logits(tensordict)
        # Categorical(logits=logits).sample(), operation for operation.
        logits = logits - logits.logsumexp(dim=-1, keepdim=True)
        probs = torch.softmax(logits, dim=-1)
        action = torch.multinomial(probs.reshape(-1, probs.shape[-1]), 1, True).T
        tensordict.set(self._action_key, action.reshape(probs.shape[:-1]))
        return tensordict


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
            type(m) is TensorDictModule
            and m.method is None
            and not m.method_kwargs
            and m._kwargs is None
            and len(m.out_keys) == 1
        ):
            layers.append(m)
        else:
            return None
    return layers
