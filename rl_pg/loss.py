"""REINFORCE as a TorchRL ``LossModule``: a drop-in superset of TorchRL's own."""

from __future__ import annotations

import contextlib

import torch
from tensordict import TensorDict, TensorDictBase, is_tensor_collection
from tensordict.nn import (
    CompositeDistribution,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    dispatch,
)
from torchrl.objectives import LossModule
from torchrl.objectives import ReinforceLoss as TorchRLReinforceLoss
from torchrl.objectives.utils import (
    _GAMMA_LMBDA_DEPREC_ERROR,
    _sum_td_features,
    dispatch_value_estimator,
)
from torchrl.objectives.value import ValueEstimatorBase

from rl_pg.baselines import BASELINES, make_baseline
from rl_pg.estimators import _MonteCarloReturn

__all__ = ["ReinforceLoss"]

_BASELINE_CHOICES = ("none", "critic", *BASELINES)


class ReinforceLoss(TorchRLReinforceLoss):
    """REINFORCE: the surrogate `−(1/N) Σ_t Ψ_t log π_θ(a_t|s_t)`.

    A subclass of `torchrl.objectives.ReinforceLoss` with the same constructor,
    defaults, keys and outputs, so TorchRL code keeps working when only the import
    changes. On top of it:

    * ``critic_network`` is optional. Without it there is no ``loss_value`` and the
      default value estimator is [`RewardToGo`][rl_pg.RewardToGo] (``gamma=0.99``).
    * ``baseline`` chooses what is subtracted from the return `Ψ_t`:
      ``"none"``, ``"batch_mean"``, ``"running_mean"`` (of every episode return seen),
      ``"ema"`` (rate ``baseline_rate``) or ``"critic"`` (the estimator's
      ``advantage``, TorchRL's behaviour). Its state is a buffer in ``state_dict``.
    * ``entropy_coeff`` adds ``loss_entropy`` `= −β H(π(·|s))` and
      a detached ``entropy``.
    * ``normalize_advantage`` standardises `Ψ` over the batch.
    * Detached diagnostics: ``advantage_mean``, ``advantage_std``, ``baseline`` (scalar
      baselines) and ``explained_variance`` (with a critic whose values are in the data).
    * Non-finite log-probabilities, empty batches and missing keys raise clear errors.

    The stored action is scored, never resampled. ``loss_actor`` sends no gradient into
    the critic (`Ψ` is detached) and ``loss_value`` none into the actor.
    For a policy over several independent action dimensions whose distribution reports
    one log-probability per dimension (e.g. ``torch.distributions.Normal``), the
    log-probabilities are summed over those dimensions: the joint log-probability is
    what the policy gradient needs.

    Args:
        actor_network (ProbabilisticTensorDictSequential): the policy, e.g. a
            `torchrl.modules.ProbabilisticActor`.
        critic_network (TensorDictModule, optional): a state-value network writing
            ``"state_value"``. Defaults to ``None``.

    Keyword Args:
        delay_value (bool): keep target parameters for the critic. Defaults to ``False``.
        loss_critic_type (str): ``"l1"``, ``"l2"`` or ``"smooth_l1"``. Defaults to
            ``"smooth_l1"``.
        gamma (float): removed in TorchRL; passing it raises (use ``make_value_estimator``).
        advantage_key (str): deprecated in TorchRL; use ``set_keys``.
        value_target_key (str): deprecated in TorchRL; use ``set_keys``.
        separate_losses (bool): shared actor/critic parameters get gradients from the
            actor loss only. Defaults to ``False``.
        functional (bool): functionalise the modules. Defaults to ``True``.
        actor (ProbabilisticTensorDictSequential): alias of ``actor_network``.
        critic (TensorDictModule): alias of ``critic_network``.
        reduction (str, optional): ``"none"``, ``"mean"`` or ``"sum"``. Defaults to
            ``"mean"``.
        clip_value (float, optional): clip the value prediction around the stored one.
            Defaults to ``None``.
        baseline (str, optional): one of ``"none"``, ``"batch_mean"``,
            ``"running_mean"``, ``"ema"``, ``"critic"``. Defaults to ``"critic"`` with a
            critic, ``"none"`` without.
        baseline_rate (float): the rate `α` of the ``"ema"`` baseline.
            Defaults to ``0.01``.
        entropy_coeff (float, optional): the entropy bonus `β ≥ 0`.
            Defaults to ``None``: no entropy term (TorchRL's outputs).
        normalize_advantage (bool): standardise `Ψ` (zero mean, unit
            standard deviation over the batch). Defaults to ``False``.
        critic_coeff (float): weight carried by ``loss_value``, so that the losses can be
            summed as they are. Defaults to ``1.0``.

    Raises:
        ValueError: for an unknown ``baseline``, ``baseline="critic"`` without a critic,
            a negative ``entropy_coeff``; and in ``forward`` for an empty batch,
            non-finite log-probabilities, or log-probabilities whose shape does not
            match the returns.
        KeyError: in ``forward`` when a key it reads is missing (the message names it).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> from rl_pg import ReinforceLoss
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> actor = ProbabilisticActor(
        ...     TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"]),
        ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
        ... )
        >>> loss = ReinforceLoss(actor, baseline="running_mean", entropy_coeff=0.01)
        >>> data = TensorDict({
        ...     "observation": torch.randn(4, 3),
        ...     "action": torch.tensor([0, 1, 1, 0]),
        ...     "next": {"reward": torch.ones(4, 1),
        ...              "done": torch.tensor([[False], [True], [False], [True]])},
        ... }, batch_size=[4])
        >>> out = loss(data)
        >>> sorted(out.keys())  # doctest: +NORMALIZE_WHITESPACE
        ['advantage_mean', 'advantage_std', 'baseline', 'entropy', 'loss_actor',
         'loss_entropy']
        >>> data["value_target"].squeeze(-1)  # reward-to-go, gamma=0.99
        tensor([1.9900, 1.0000, 1.9900, 1.0000])
        >>> (out["loss_actor"] + out["loss_entropy"]).backward()
    """

    SUPPORTED_VALUE_ESTIMATORS = (
        *TorchRLReinforceLoss.SUPPORTED_VALUE_ESTIMATORS,
        "reward_to_go",
        "discounted_return",
    )

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential | None = None,
        critic_network: TensorDictModule | None = None,
        *,
        delay_value: bool = False,
        loss_critic_type: str = "smooth_l1",
        gamma: float | None = None,
        advantage_key: str | None = None,
        value_target_key: str | None = None,
        separate_losses: bool = False,
        functional: bool = True,
        actor: ProbabilisticTensorDictSequential | None = None,
        critic: TensorDictModule | None = None,
        reduction: str | None = None,
        clip_value: float | torch.Tensor | None = None,
        baseline: str | None = None,
        baseline_rate: float = 0.01,
        entropy_coeff: float | None = None,
        normalize_advantage: bool = False,
        critic_coeff: float = 1.0,
    ) -> None:
        actor_network = actor if actor is not None else actor_network
        critic_network = critic if critic is not None else critic_network
        if actor_network is None:
            raise TypeError("ReinforceLoss needs an actor_network (a probabilistic policy).")
        if not functional and delay_value:
            raise RuntimeError(
                "delay_value and ~functional are incompatible, as delayed value currently "
                "relies on functional calls."
            )
        if gamma is not None:
            raise TypeError(_GAMMA_LMBDA_DEPREC_ERROR)
        if baseline is None:
            baseline = "critic" if critic_network is not None else "none"
        if baseline not in _BASELINE_CHOICES:
            raise ValueError(f"baseline must be one of {_BASELINE_CHOICES}, got {baseline!r}.")
        if baseline == "critic" and critic_network is None:
            raise ValueError(
                "baseline='critic' needs a critic_network; pass one, or pick a scalar "
                "baseline such as 'running_mean'."
            )
        if entropy_coeff is not None and not (
            isinstance(entropy_coeff, (int, float)) and entropy_coeff >= 0
        ):
            raise ValueError(f"entropy_coeff must be a number >= 0 or None, got {entropy_coeff!r}.")

        self._functional = functional
        # TorchRL's constructor insists on a critic; everything else it does is below.
        LossModule.__init__(self)
        self.in_keys = None
        self._set_deprecated_ctor_keys(advantage=advantage_key, value_target=value_target_key)
        self.delay_value = delay_value
        self.loss_critic_type = loss_critic_type
        self.reduction = "mean" if reduction is None else reduction
        self.has_critic = critic_network is not None

        if functional:
            self.convert_to_functional(actor_network, "actor_network", create_target_params=False)
        else:
            self.actor_network = actor_network
        if critic_network is not None:
            policy_params = list(actor_network.parameters()) if separate_losses else None
            if functional:
                self.convert_to_functional(
                    critic_network,
                    "critic_network",
                    create_target_params=delay_value,
                    compare_against=policy_params,
                )
            else:
                self.critic_network = critic_network
                self.target_critic_network_params = None
        else:
            self.critic_network_params = None
            self.target_critic_network_params = None

        if clip_value is not None:
            if isinstance(clip_value, float):
                clip_value = torch.tensor(clip_value)
            elif not isinstance(clip_value, torch.Tensor) or clip_value.numel() != 1:
                raise ValueError(
                    f"clip_value must be a float or a scalar tensor, got {clip_value}."
                )
        self.register_buffer("clip_value", clip_value)

        self.baseline = baseline
        self.baseline_module = (
            make_baseline(baseline, rate=baseline_rate) if baseline in BASELINES else None
        )
        self.entropy_coeff = None if entropy_coeff is None else float(entropy_coeff)
        self.normalize_advantage = normalize_advantage
        if not isinstance(critic_coeff, (int, float)) or critic_coeff < 0:
            raise ValueError(f"critic_coeff must be a number >= 0, got {critic_coeff!r}.")
        self.critic_coeff = float(critic_coeff)
        out_keys = ["loss_actor"]
        if self.has_critic:
            out_keys.append("loss_value")
        if self.entropy_coeff is not None:
            out_keys.append("loss_entropy")
        self.out_keys = out_keys
        # Eagerly, unlike TorchRL: the estimator's buffers (gamma) are then in
        # state_dict from the start, so a checkpoint loads into a freshly built loss.
        self._default_value_estimator()

    def _set_in_keys(self):
        keys = [
            self.tensor_keys.action,
            ("next", self.tensor_keys.reward),
            ("next", self.tensor_keys.done),
            ("next", self.tensor_keys.terminated),
            *self.actor_network.in_keys,
            *[("next", key) for key in self.actor_network.in_keys],
        ]
        if self.has_critic:
            keys += self.critic_network.in_keys
        self._in_keys = list(dict.fromkeys(keys))

    def _default_value_estimator(self):
        default = self.default_value_estimator if self.has_critic else "reward_to_go"
        self.make_value_estimator(default, device=self._default_device)

    def make_value_estimator(self, value_type=None, **hyperparams):
        """Builds the value estimator that computes returns when the data has none.

        Takes everything TorchRL's ``make_value_estimator`` takes, plus ``"reward_to_go"``
        and ``"discounted_return"`` (or the classes [`RewardToGo`][rl_pg.RewardToGo] /
        [`DiscountedReturn`][rl_pg.DiscountedReturn], which receive the critic as value network).

        Examples:
            >>> import torch
            >>> from tensordict.nn import TensorDictModule
            >>> from torchrl.modules import ProbabilisticActor
            >>> from rl_pg import DiscountedReturn, ReinforceLoss
            >>> actor = ProbabilisticActor(
            ...     TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"]),
            ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
            ... )
            >>> loss = ReinforceLoss(actor)
            >>> _ = loss.make_value_estimator("discounted_return", gamma=0.9)
            >>> type(loss.value_estimator).__name__, loss.value_estimator.gamma.item()
            ('DiscountedReturn', 0.9)
        """
        if value_type is None:
            self._default_value_estimator()
            return self
        if isinstance(value_type, type) and issubclass(value_type, _MonteCarloReturn):
            hyperparams.setdefault("value_network", self._critic_or_none())
        if isinstance(value_type, ValueEstimatorBase) or (
            isinstance(value_type, type) and issubclass(value_type, ValueEstimatorBase)
        ):
            LossModule.make_value_estimator(self, value_type, **hyperparams)
        else:
            dispatch_value_estimator(
                self,
                value_type,
                supported=self.SUPPORTED_VALUE_ESTIMATORS,
                **hyperparams,
            )
        self._forward_value_estimator_keys()
        return self

    def _critic_or_none(self):
        return self.critic_network if self.has_critic else None

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.numel() == 0:
            raise ValueError(
                f"ReinforceLoss got an empty batch (batch_size={tuple(tensordict.batch_size)})."
            )
        weights, diagnostics = self._policy_weights(tensordict)
        dist = self._policy(tensordict)
        log_prob = self._log_prob(dist, tensordict, weights)
        td_out = TensorDict({"loss_actor": -log_prob * weights}, batch_size=[])
        if self.entropy_coeff is not None:
            entropy = _per_step(self._entropy(dist), log_prob.shape, "entropies")
            td_out.set("loss_entropy", -self.entropy_coeff * entropy)
            td_out.set("entropy", entropy.detach().mean())
        if self.has_critic:
            loss_value, value_clip_fraction = self.loss_critic(tensordict)
            td_out.set("loss_value", self.critic_coeff * loss_value)
            if value_clip_fraction is not None:
                td_out.set("value_clip_fraction", value_clip_fraction)
        td_out.update(diagnostics)
        td_out = td_out.named_apply(
            lambda name, value: (
                self._reduce_loss(value, tensordict).squeeze(-1)
                if name.startswith("loss_")
                else value
            ),
        )
        self._clear_weakrefs(
            tensordict,
            td_out,
            "actor_network_params",
            "critic_network_params",
            "target_actor_network_params",
            "target_critic_network_params",
        )
        return td_out

    def _run_value_estimator(self, tensordict: TensorDictBase) -> None:
        functional_critic = self.functional and self.has_critic
        self.value_estimator(
            tensordict,
            params=self.critic_network_params.detach() if functional_critic else None,
            target_params=self.target_critic_network_params if functional_critic else None,
        )

    def _policy_weights(self, tensordict: TensorDictBase):
        """The detached `Ψ_t` that weights ``log pi``, and diagnostics."""
        key = (
            self.tensor_keys.advantage
            if self.baseline == "critic"
            else self.tensor_keys.value_target
        )
        psi = tensordict.get(key, None)
        if psi is None:
            self._run_value_estimator(tensordict)
            psi = tensordict.get(key, None)
            if psi is None:
                raise KeyError(
                    f"The value estimator {type(self.value_estimator).__name__} did not write "
                    f"{key!r}; align the keys with loss.set_keys(...)."
                )
        psi = psi.detach()
        valid = self._valid_steps(tensordict, psi)
        diagnostics = {}
        if self.baseline_module is not None:
            baseline = self.baseline_module(self._episode_returns(tensordict, psi, valid))
            psi = psi - baseline
            diagnostics["baseline"] = baseline
        valid_psi = psi if valid is None else psi[valid]
        diagnostics["advantage_mean"] = valid_psi.mean()
        diagnostics["advantage_std"] = valid_psi.std(unbiased=False)
        if self.has_critic:
            explained = self._explained_variance(tensordict, valid)
            if explained is not None:
                diagnostics["explained_variance"] = explained
        if self.normalize_advantage:
            psi = (psi - diagnostics["advantage_mean"]) / (diagnostics["advantage_std"] + 1e-8)
        return psi, diagnostics

    def _valid_steps(self, tensordict: TensorDictBase, like: torch.Tensor):
        """The padding mask (e.g. ``("collector", "mask")``) shaped like ``like``, or None."""
        for key in self._loss_mask_keys():
            mask = tensordict.get(key, None)
            if mask is not None:
                while mask.ndim < like.ndim:
                    mask = mask.unsqueeze(-1)
                return mask.expand_as(like)
        return None

    def _episode_returns(
        self, tensordict: TensorDictBase, returns: torch.Tensor, valid: torch.Tensor | None
    ) -> torch.Tensor:
        """The returns at the first step of each episode (or of each row's first segment)."""
        done = tensordict.get(("next", self.tensor_keys.done), None)
        if done is None or done.shape != returns.shape:
            return returns if valid is None else returns[valid]
        time_dim = tensordict.ndim - 1
        if tensordict._has_names() and "time" in tensordict.names:
            time_dim = tensordict.names.index("time")
        starts = torch.zeros_like(done)
        length = done.shape[time_dim]
        starts.narrow(time_dim, 1, length - 1).copy_(done.narrow(time_dim, 0, length - 1))
        starts.narrow(time_dim, 0, 1).fill_(True)
        if valid is not None:
            starts &= valid
        return returns[starts]

    def _explained_variance(self, tensordict: TensorDictBase, valid) -> torch.Tensor | None:
        value = tensordict.get(self.tensor_keys.value, None)
        target = tensordict.get(self.tensor_keys.value_target, None)
        if value is None or target is None or value.shape != target.shape:
            return None
        error = (target - value).detach()
        target = target.detach()
        if valid is not None:
            error, target = error[valid], target[valid]
        variance = target.var(unbiased=False)
        return 1 - error.var(unbiased=False) / variance.clamp_min(1e-8)

    def _policy(self, tensordict: TensorDictBase):
        with (
            self.actor_network_params.to_module(self.actor_network, preserve_module_state=False)
            if self.functional
            else contextlib.nullcontext()
        ):
            return self.actor_network.get_dist(tensordict)

    def _log_prob(self, dist, tensordict: TensorDictBase, weights: torch.Tensor) -> torch.Tensor:
        if isinstance(dist, CompositeDistribution):
            action = tensordict
        else:
            action = tensordict.get(self.tensor_keys.action, None)
            if action is None:
                raise KeyError(
                    f"The input tensordict has no action entry {self.tensor_keys.action!r}; "
                    f"collect it or rename the key with loss.set_keys(action=...)."
                )
        log_prob = dist.log_prob(action)
        if is_tensor_collection(log_prob):
            log_prob = _sum_td_features(log_prob)
        log_prob = _per_step(log_prob, weights.shape, "log-probabilities")
        if not bool(torch.isfinite(log_prob).all()):
            raise ValueError(
                f"The policy gave {int((~torch.isfinite(log_prob)).sum())} non-finite "
                "log-probabilities for the stored actions: an action outside the "
                "distribution's support (e.g. out of the bounds of a TanhNormal), or NaN "
                "in the policy's output."
            )
        return log_prob

    def _entropy(self, dist) -> torch.Tensor:
        try:
            entropy = dist.entropy()
        except NotImplementedError:
            # No closed form (e.g. TanhNormal): a one-sample Monte-Carlo estimate.
            sample = dist.rsample() if dist.has_rsample else dist.sample()
            entropy = -dist.log_prob(sample)
        if is_tensor_collection(entropy):
            entropy = _sum_td_features(entropy)
        return entropy


def _per_step(values: torch.Tensor, shape: torch.Size, what: str) -> torch.Tensor:
    """Brings per-step policy quantities to the ``[*B, 1]`` shape of the returns."""
    batch_shape = shape[:-1]
    if values.shape == batch_shape:
        values = values.unsqueeze(-1)
    elif values.shape[: len(batch_shape)] == batch_shape and values.ndim > len(batch_shape):
        # One number per independent action dimension: the joint is their sum.
        values = values.flatten(len(batch_shape)).sum(-1, keepdim=True)
    if values.shape == shape:
        return values
    raise ValueError(
        f"The policy's {what} have shape {tuple(values.shape)} but the returns have shape "
        f"{tuple(shape)}: there must be one action per step."
    )
