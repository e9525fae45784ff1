"""Policy and value networks sized from an environment's specs."""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import partial
from typing import Literal

import torch
from tensordict.nn import (
    AddStateIndependentNormalScale,
    NormalParamExtractor,
    TensorDictModule,
)
from torch import nn
from torchrl.data import Bounded, Categorical, OneHot
from torchrl.envs import EnvBase
from torchrl.modules import (
    MLP,
    IndependentNormal,
    OneHotCategorical,
    ProbabilisticActor,
    TanhNormal,
    ValueOperator,
)

from rl_pg._checks import check_int
from rl_pg.distributions import BetaConcentrations, BoundedBeta
from rl_pg.lean import LeanCategoricalActor
from rl_pg.normalization import RunningNorm

__all__ = ["mlp_actor", "mlp_actor_critic", "mlp_critic"]


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
            [`RunningNorm`][rl_pg.normalization.RunningNorm] (``True``: a new one; a
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
        return LeanCategoricalActor(  # a ProbabilisticActor, faster to build a distribution
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
            [`RunningNorm`][rl_pg.normalization.RunningNorm] (``True``: a new one; a
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
    ``normalize=True``, one [`RunningNorm`][rl_pg.normalization.RunningNorm] for both).

    See [`mlp_actor`][rl_pg.models.mlp_actor] (which also takes
    ``bounded``, ``state_independent_scale`` and ``init_scale``) and
    [`mlp_critic`][rl_pg.models.mlp_critic].

    Examples:
        >>> from torchrl.modules import ProbabilisticActor
        >>> from rl_pg.envs import BanditEnv
        >>> from rl_pg.models import mlp_actor_critic
        >>> actor, critic = mlp_actor_critic(BanditEnv(num_arms=3), hidden=(8,))
        >>> isinstance(actor, ProbabilisticActor), type(critic).__name__
        (True, 'ValueOperator')
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
