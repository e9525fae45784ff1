"""REINFORCE as a TorchRL ``LossModule``: a drop-in superset of TorchRL's own."""

from __future__ import annotations

import contextlib
import numbers
from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase, is_tensor_collection
from tensordict.nn import (
    CompositeDistribution,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictModuleBase,
    dispatch,
)
from torchrl.modules import ValueNorm
from torchrl.objectives import LossModule
from torchrl.objectives import ReinforceLoss as TorchRLReinforceLoss
from torchrl.objectives.utils import (
    _GAMMA_LMBDA_DEPREC_ERROR,
    _clip_value_loss,
    dispatch_value_estimator,
    distance_loss,
)
from torchrl.objectives.value import ValueEstimatorBase

from rl_pg._checks import check_bool, check_key, check_real
from rl_pg.baselines import BASELINES, make_baseline
from rl_pg.estimators import DiscountedReturn, MonteCarloReturn
from rl_pg.groups import GROUP_BASELINES, batch_group_advantage, greedy_flags
from rl_pg.loss_checks import (
    check_action_shape,
    check_not_empty,
    check_support,
    declares_bounds,
    per_step,
    required,
    step_column,
)

__all__ = ["ReinforceLoss"]

_BASELINE_CHOICES = ("none", "critic", *BASELINES, *GROUP_BASELINES)
_LOSS_CRITIC_TYPES = ("l1", "l2", "smooth_l1")
_REDUCTIONS = (None, "none", "mean", "sum")


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
      Or a group baseline over episodes played from the same start (see
      [`rl_pg.groups`][rl_pg.groups]): ``"leave_one_out"`` (the mean of the group's
      other episodes), ``"group_mean"`` (the whole group's mean) or ``"greedy"`` (the
      group's greedy episode, whose steps are left out of every loss term). The
      group of each step is read at the ``group`` key (``set_keys(group=...)``), the
      greedy flags at ``greedy``; the episodes must be whole (each ends on ``done``).
      A reward-to-go is compared step by step with the others' at the same step of
      their episode, a whole-episode return episode by episode.
    * ``entropy_coeff`` adds ``loss_entropy`` `= −β H(π(·|s))` and
      a detached ``entropy``. The attribute may be reassigned between updates, as a
      schedule does; a negative value there penalises entropy.
    * ``normalize_advantage`` standardises `Ψ` over the batch.
    * ``value_norm`` (a TorchRL ``ValueNorm``, as ``MAPPOLoss`` takes) makes the
      critic regress on standardised targets; a [`PopArt`][rl_pg.normalization.PopArt]
      output layer also lets the critic learn at that scale.
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
            ``"running_mean"``, ``"ema"``, ``"critic"``, ``"leave_one_out"``,
            ``"group_mean"``, ``"greedy"``. Defaults to ``"critic"`` with a critic,
            ``"none"`` without.
        baseline_rate (float): the rate `α` of the ``"ema"`` baseline.
            Defaults to ``0.01``.
        entropy_coeff (float, optional): the entropy bonus `β ≥ 0`.
            Defaults to ``None``: no entropy term (TorchRL's outputs).
        normalize_advantage (bool): standardise `Ψ` (zero mean, unit
            standard deviation over the batch). Defaults to ``False``.
        group_scale (bool): with a group baseline, divide each advantage by the
            standard deviation of its group's returns (GRPO's normalisation; it biases
            the gradient, see [`rl_pg.groups`][rl_pg.groups]). Defaults to ``False``.
        critic_coeff (float): weight carried by ``loss_value``, so that the losses can be
            summed as they are. Defaults to ``1.0``.
        value_norm (ValueNorm, optional): running statistics of the value targets
            (``torchrl.modules.ValueNorm``). Each ``forward`` updates them once with
            the batch's targets (padding excluded), then ``loss_value`` compares
            ``normalize(target)`` with ``normalize(V)``, and ``clip_value`` is in those
            units. Give the critic's [`PopArt`][rl_pg.normalization.PopArt] output layer to
            have the critic predict standardised values (its outputs are preserved
            when the statistics move); any other ``ValueNorm`` only rescales the loss.
            Advantages and returns stay at the rewards' scale. Defaults to ``None``.

    Raises:
        ValueError: for an unknown ``baseline``, ``baseline="critic"`` without a critic,
            a negative ``entropy_coeff``, ``group_scale`` without a group baseline; and
            in ``forward`` for an empty batch, non-finite log-probabilities,
            log-probabilities whose shape does not match the returns, or (group
            baselines) an episode cut by the batch, a group of too few episodes or a
            step whose group differs from its episode's.
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
    # TorchRL's class declares ``out_keys`` as a list that tensordict turns into a
    # property only when that class is first instantiated; declared here, the property
    # exists from the start and ``select_out_keys`` works in any order.
    out_keys = TensorDictModuleBase.out_keys

    @dataclass
    class _AcceptedKeys(TorchRLReinforceLoss._AcceptedKeys):
        """TorchRL's keys, and those of the group baselines.

        Attributes:
            group (NestedKey): the integer group of each step (its episode's start).
                Defaults to ``"group"``.
            greedy (NestedKey): ``True`` on the steps of a group's greedy episode.
                Defaults to ``"greedy"``.
        """

        group: NestedKey = "group"
        greedy: NestedKey = "greedy"

    default_keys = _AcceptedKeys

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
        group_scale: bool = False,
        critic_coeff: float = 1.0,
        value_norm: ValueNorm | None = None,
    ) -> None:
        actor_network = actor if actor is not None else actor_network
        critic_network = critic if critic is not None else critic_network
        if actor_network is None:
            raise TypeError("ReinforceLoss needs an actor_network (a probabilistic policy).")
        if not hasattr(actor_network, "get_dist"):
            raise TypeError(
                f"actor_network must be a probabilistic policy with get_dist() (e.g. "
                f"torchrl.modules.ProbabilisticActor), got {type(actor_network).__name__}."
            )
        if critic_network is not None and not isinstance(critic_network, TensorDictModuleBase):
            raise TypeError(
                f"critic_network must be a TensorDictModule writing the state value (e.g. "
                f"torchrl.modules.ValueOperator), got {type(critic_network).__name__}."
            )
        delay_value = check_bool("delay_value", delay_value)
        functional = check_bool("functional", functional)
        separate_losses = check_bool("separate_losses", separate_losses)
        normalize_advantage = check_bool("normalize_advantage", normalize_advantage)
        group_scale = check_bool("group_scale", group_scale)
        if not functional and delay_value:
            raise RuntimeError(
                "delay_value and ~functional are incompatible, as delayed value currently "
                "relies on functional calls."
            )
        if gamma is not None:
            raise TypeError(_GAMMA_LMBDA_DEPREC_ERROR)
        if loss_critic_type not in _LOSS_CRITIC_TYPES:
            raise ValueError(
                f"loss_critic_type must be one of {_LOSS_CRITIC_TYPES}, got {loss_critic_type!r}."
            )
        if reduction not in _REDUCTIONS:
            raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}.")
        if baseline is None:
            baseline = "critic" if critic_network is not None else "none"
        if baseline not in _BASELINE_CHOICES:
            raise ValueError(f"baseline must be one of {_BASELINE_CHOICES}, got {baseline!r}.")
        if baseline == "critic" and critic_network is None:
            raise ValueError(
                "baseline='critic' needs a critic_network; pass one, or pick a scalar "
                "baseline such as 'running_mean'."
            )
        if group_scale and baseline not in GROUP_BASELINES:
            raise ValueError(
                f"group_scale divides a group baseline's advantages by the group's standard "
                f"deviation, but baseline={baseline!r}: pick one of {GROUP_BASELINES}, or "
                f"use normalize_advantage for the whole batch."
            )
        if value_norm is not None:
            if not isinstance(value_norm, ValueNorm):
                raise TypeError(
                    f"value_norm must be a torchrl.modules.ValueNorm (e.g. the critic's "
                    f"rl_pg.normalization.PopArt layer), got {type(value_norm).__name__}."
                )
            if critic_network is None:
                raise ValueError(
                    "value_norm normalises the critic's targets, but there is no "
                    "critic_network: pass one, or drop value_norm."
                )
        entropy_coeff = check_real("entropy_coeff", entropy_coeff, low=0, optional=True)
        critic_coeff = check_real("critic_coeff", critic_coeff, low=0)
        baseline_rate = check_real("baseline_rate", baseline_rate, low=0, low_open=True, high=1)

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
            if isinstance(clip_value, bool) or not (
                isinstance(clip_value, numbers.Real)
                or (isinstance(clip_value, torch.Tensor) and clip_value.numel() == 1)
            ):
                # TorchRL's wording, which its own tests match.
                raise ValueError(
                    f"clip_value must be a float or a scalar tensor, got {clip_value}."
                )
            check_real("clip_value", clip_value, low=0, low_open=True)
            if not isinstance(clip_value, torch.Tensor):
                clip_value = torch.tensor(float(clip_value))
        self.register_buffer("clip_value", clip_value)

        self.baseline = baseline
        self.baseline_module = (
            make_baseline(baseline, rate=baseline_rate) if baseline in BASELINES else None
        )
        self.entropy_coeff = entropy_coeff
        self.normalize_advantage = normalize_advantage
        self.group_scale = group_scale
        self.critic_coeff = critic_coeff
        self.value_norm = value_norm
        self._deferred_key_error: KeyError | None = None
        self._declares_bounds = declares_bounds(actor_network)
        out_keys = ["loss_actor"]
        if self.has_critic:
            out_keys.append("loss_value")
        if self.entropy_coeff is not None:
            out_keys.append("loss_entropy")
        self.out_keys = out_keys
        # Eagerly, unlike TorchRL: the estimator's buffers (gamma) are then in
        # state_dict from the start, so a checkpoint loads into a freshly built loss.
        self._default_value_estimator()

    def set_keys(self, **kwargs) -> None:
        """Renames the entries the loss reads (TorchRL's ``set_keys``; ``None`` restores
        a default). Unknown names raise ``ValueError``; a key that is neither a string
        nor a tuple of strings raises ``TypeError``."""
        for name, key in kwargs.items():
            if key is not None:
                check_key(f"set_keys({name}=...)", key)
        super().set_keys(**kwargs)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # TorchRL builds its estimator at the first forward, so set_keys never meets one
        # and a value key the critic does not write only fails when returns are needed.
        # This estimator exists from the start: the same check waits for the same moment.
        try:
            super()._forward_value_estimator_keys(**kwargs)
        except KeyError as err:
            self._deferred_key_error = err
            self._set_in_keys()
        else:
            self._deferred_key_error = None

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
        if self.baseline in GROUP_BASELINES:
            keys.append(self.tensor_keys.group)
        if self.baseline == "greedy":
            keys.append(self.tensor_keys.greedy)
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
        if isinstance(value_type, type) and issubclass(value_type, MonteCarloReturn):
            hyperparams.setdefault("value_network", self._critic_or_none())
        if isinstance(value_type, ValueEstimatorBase) or (
            isinstance(value_type, type) and issubclass(value_type, ValueEstimatorBase)
        ):
            LossModule.make_value_estimator(self, value_type, **hyperparams)
        else:
            try:
                dispatch_value_estimator(
                    self,
                    value_type,
                    supported=self.SUPPORTED_VALUE_ESTIMATORS,
                    **hyperparams,
                )
            except KeyError as err:  # TorchRL's type for an unknown name; kept for callers
                names = [getattr(v, "name", v).lower() for v in self.SUPPORTED_VALUE_ESTIMATORS]
                raise KeyError(
                    f"Unknown value estimator {value_type!r}: ReinforceLoss takes one of "
                    f"{names}, a ValueEstimators member, or a ValueEstimatorBase class or "
                    f"instance."
                ) from err
        self._forward_value_estimator_keys()
        return self

    def _critic_or_none(self):
        return self.critic_network if self.has_critic else None

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # ``TensorDict.numel()`` is 1 for a batch of zero rows: count the batch itself.
        weights, diagnostics, state_value, valid = self._take_in(tensordict)
        out = self._policy_terms(tensordict, weights, valid)
        if self.has_critic:
            if state_value is not None:  # the estimator's pass, still in the graph
                loss_value = self._critic_distance(
                    tensordict.get(self.tensor_keys.value_target), state_value
                )
                value_clip_fraction = None
            else:
                loss_value, value_clip_fraction = self.loss_critic(tensordict)
            out["loss_value"] = self.critic_coeff * loss_value
            if value_clip_fraction is not None:
                out["value_clip_fraction"] = value_clip_fraction
        out.update(diagnostics)
        for name, value in out.items():
            if name.startswith("loss_"):
                out[name] = self._reduce_steps(value, tensordict, valid).squeeze(-1)
        # Every entry is a tensor computed here: nothing for TensorDict to validate.
        td_out = TensorDict._new_unsafe(out, batch_size=torch.Size([]))
        self._clear_weakrefs(
            tensordict,
            td_out,
            "actor_network_params",
            "critic_network_params",
            "target_actor_network_params",
            "target_critic_network_params",
        )
        return td_out

    def policy_weights(
        self, tensordict: TensorDictBase, *, keep_value: bool = False
    ) -> (
        tuple[torch.Tensor, torch.Tensor | None]
        | tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]
    ):
        """The weights `Ψ_t` of this batch's steps, as ``forward`` weights ``log π``.

        Computes the returns when the batch has none (written into it, as ``forward``
        does) and takes the batch into the loss's state once: a running baseline's
        statistics, ``value_norm``'s. With [`policy_loss`][rl_pg.ReinforceLoss.policy_loss]
        it is ``forward``'s policy part in two steps, for updates that evaluate the
        policy loss at several parameters on one batch (a line search, a trust region).

        With ``keep_value=True`` it also gives the critic's ``V(s_t)`` as the value
        estimator computed it here, still attached to the critic's parameters (None
        when it was not computed in one plain pass: returns already in the batch,
        ``clip_value``, ``value_norm``, a functional loss): hand it to
        [`value_loss`][rl_pg.ReinforceLoss.value_loss] (``value=``) and the critic is
        not called again for its first step on the batch.

        Returns:
            ``(weights, valid)``: the detached weights, ``[*B, 1]``, and the steps to
            learn from (``[*B, 1]`` booleans: padding and greedy episodes left out), or
            ``None`` when every step counts; with ``keep_value``, ``(weights, valid,
            value)``.

        Examples:
            >>> import torch
            >>> from tensordict import TensorDict
            >>> from tensordict.nn import TensorDictModule
            >>> from torchrl.modules import ProbabilisticActor
            >>> from rl_pg import ReinforceLoss
            >>> actor = ProbabilisticActor(
            ...     TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"]),
            ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
            ... )
            >>> loss = ReinforceLoss(actor, baseline="batch_mean")
            >>> data = TensorDict({
            ...     "observation": torch.randn(4, 3),
            ...     "action": torch.tensor([0, 1, 1, 0]),
            ...     "next": {"reward": torch.tensor([[1.0], [0.0], [3.0], [0.0]]),
            ...              "done": torch.tensor([[True], [True], [True], [True]])},
            ... }, batch_size=[4])
            >>> weights, valid = loss.policy_weights(data)
            >>> weights.squeeze(-1), valid
            (tensor([ 0., -1.,  2., -1.]), None)
            >>> terms = loss.policy_loss(data, weights, valid)
            >>> bool(terms["loss_actor"] == loss(data)["loss_actor"])
            True
        """
        weights, _, value, valid = self._take_in(tensordict)
        return (weights, valid, value) if keep_value else (weights, valid)

    def weights_as_they_are(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The weights `Ψ_t` that [`policy_weights`][rl_pg.ReinforceLoss.policy_weights]
        would give this batch, detached, ``[*B, 1]``, without taking the batch in: a
        running baseline answers with its state as it is, and ``value_norm`` keeps its
        statistics. For measurements that must leave the loss as they found it (the
        gradient statistics). Computes the returns when the batch has none, written
        into it as ``forward`` does."""
        check_not_empty(tensordict)
        baseline = self.baseline_module
        training = baseline.training if baseline is not None else False
        if baseline is not None:
            baseline.eval()  # answers without taking in the batch
        try:
            psi, *_ = self._policy_weights(tensordict)
        finally:
            if baseline is not None:
                baseline.train(training)
        return psi.detach()

    def log_prob(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``log π(a_t|s_t)`` of the batch's stored actions under the current policy
        parameters, ``[*B, 1]``, with the graph to them: the term the weights multiply.
        Refuses what ``forward`` refuses (an action outside the policy's support, a
        non-finite log-probability). A composite action's is the sum of its parts'."""
        like = torch.zeros(*tensordict.batch_size, 1, device=tensordict.device)
        with (
            self.actor_network_params.to_module(self.actor_network)
            if self.functional
            else contextlib.nullcontext()
        ):
            return self._log_prob(self._policy(tensordict), tensordict, like)

    def valid_steps(
        self, tensordict: TensorDictBase, *, greedy: bool = False
    ) -> torch.Tensor | None:
        """The steps the loss learns from, ``[*B, 1]`` booleans, or None when every
        step counts: those the padding mask (``("collector", "mask")``) keeps, less
        the greedy episodes' steps of ``baseline="greedy"`` (``greedy=True`` keeps
        them: the padding alone)."""
        like = torch.zeros(*tensordict.batch_size, 1, dtype=torch.bool)
        padding = self._padding_mask(tensordict, like)
        return padding if greedy else self._valid_steps(tensordict, like, padding)

    def episode_returns(
        self, tensordict: TensorDictBase, returns: torch.Tensor, valid: torch.Tensor | None
    ) -> torch.Tensor:
        """``returns`` (``[*B, 1]``) at the first step of each episode of the batch, or
        of each row's first segment, among the ``valid`` steps: one per episode, what a
        scalar baseline averages."""
        return self._episode_returns(tensordict, returns, valid)

    def policy_loss(
        self,
        tensordict: TensorDictBase,
        weights: torch.Tensor,
        valid: torch.Tensor | None = None,
        *,
        dist: torch.distributions.Distribution | None = None,
    ) -> TensorDictBase:
        """``loss_actor`` (and ``loss_entropy``, ``entropy``) under the current policy
        parameters, for the ``weights`` and ``valid`` steps that
        [`policy_weights`][rl_pg.ReinforceLoss.policy_weights] gave for this batch.
        Reduced as ``forward`` reduces them; changes no state, so it may be called as
        often as needed. ``dist``: the policy's distribution on this batch under the
        current parameters, when the caller has built it already (it is then not
        built again).

        Returns:
            A ``TensorDict`` of batch size ``[]``.
        """
        out = self._policy_terms(tensordict, weights, valid, dist)
        for name, value in out.items():
            if name.startswith("loss_"):
                out[name] = self._reduce_steps(value, tensordict, valid).squeeze(-1)
        return TensorDict._new_unsafe(out, batch_size=torch.Size([]))

    def _take_in(self, tensordict: TensorDictBase):
        """``_policy_weights``, once per batch: the checks, the returns, the baselines'
        and ``value_norm``'s statistics."""
        check_not_empty(tensordict)
        taken = self._policy_weights(tensordict)
        if self.value_norm is not None:
            self._update_value_norm(tensordict)
        return taken

    def _policy_terms(
        self,
        tensordict: TensorDictBase,
        weights: torch.Tensor,
        valid: torch.Tensor | None,
        dist: torch.distributions.Distribution | None = None,
    ) -> dict:
        """The per-step policy loss terms (unreduced) and the mean entropy."""
        if dist is None:
            dist = self._policy(tensordict)
        log_prob = self._log_prob(dist, tensordict, weights)
        out = {"loss_actor": -log_prob * weights}
        if self.entropy_coeff is not None:
            entropy = per_step(self._entropy(dist), log_prob.shape, "entropies")
            out["loss_entropy"] = -self.entropy_coeff * entropy
            entropy = entropy.detach()
            out["entropy"] = (entropy if valid is None else entropy[valid]).mean()
        return out

    def _reduce_steps(
        self, value: torch.Tensor, tensordict: TensorDictBase, valid: torch.Tensor | None
    ) -> torch.Tensor:
        """Reduces a per-step loss term over the steps to learn from (``valid``)."""
        if self.baseline == "greedy":
            # The greedy episodes are no samples of the policy: they only give the
            # baseline. Masked by the caller's mask (reduction "none" drops them).
            return self._reduce_loss(value, mask=valid)
        # The padding mask, if the batch has one, was found already: without one there
        # is nothing for the reduction to look up in the batch again, term after term.
        return self._reduce_loss(value, tensordict if valid is not None else None)

    def _run_value_estimator(self, tensordict: TensorDictBase) -> torch.Tensor | None:
        """Writes the returns; gives back the critic's ``V(s_t)`` still attached to its
        parameters when the estimator called this loss's critic in a plain pass (the
        critic loss then regresses it instead of calling the critic again), else None."""
        if self._deferred_key_error is not None:
            self._forward_value_estimator_keys()  # the keys may have been fixed since
            if self._deferred_key_error is not None:
                raise KeyError(
                    f"The value estimator cannot use the keys set with loss.set_keys(...): "
                    f"{self._deferred_key_error.args[0]} Set value= to a key the critic "
                    f"writes, or build the critic with that out_key."
                ) from self._deferred_key_error
        if self._shares_critic_pass():
            return self.value_estimator.estimate(tensordict, value_graph=True)
        functional_critic = self.functional and self.has_critic
        self.value_estimator(
            tensordict,
            params=self.critic_network_params.detach() if functional_critic else None,
            target_params=self.target_critic_network_params if functional_critic else None,
        )
        return None

    def _shares_critic_pass(self) -> bool:
        estimator = self.value_estimator
        return (
            self.has_critic
            and not self.functional
            and self.clip_value is None
            and self.value_norm is None  # its update comes between the two passes
            and isinstance(estimator, MonteCarloReturn)
            and estimator.value_network is self.critic_network
            and not estimator.differentiable
        )

    def _policy_weights(self, tensordict: TensorDictBase):
        """The detached `Ψ_t` that weights ``log pi``, diagnostics, the critic's
        ``V(s_t)`` with its graph when the estimator computed it here (else None), and
        the padding mask shaped like `Ψ_t` (None when the batch has none)."""
        key = (
            self.tensor_keys.advantage
            if self.baseline == "critic"
            else self.tensor_keys.value_target
        )
        psi = tensordict.get(key, None)
        estimated_here = psi is None
        state_value = None
        if estimated_here:
            state_value = self._run_value_estimator(tensordict)
            psi = tensordict.get(key, None)
            if psi is None:
                raise KeyError(
                    f"The value estimator {type(self.value_estimator).__name__} did not write "
                    f"{key!r}; align the keys with loss.set_keys(...)."
                )
        psi = step_column(psi.detach(), tensordict.batch_size, key)
        padding = self._padding_mask(tensordict, psi)
        valid = self._valid_steps(tensordict, psi, padding)
        if valid is not None and not bool(valid.any()):
            raise ValueError(
                "Every step of the batch is masked out as padding: there is no step to learn "
                "from. Collect at least one valid step."
            )
        finite = torch.isfinite(psi) if padding is None else torch.isfinite(psi) | ~padding
        if not bool(finite.all()):
            reward = tensordict.get(("next", self.tensor_keys.reward), None)
            if isinstance(reward, torch.Tensor) and not bool(torch.isfinite(reward).all()):
                cause = f"('next', {self.tensor_keys.reward!r}) holds NaN/inf: check the rewards."
            elif estimated_here:
                cause = (
                    f"{type(self.value_estimator).__name__} computed it from finite rewards, so "
                    f"the value network gave NaN/inf: check its inputs and learning rate."
                )
            else:
                cause = (
                    "It was in the batch already: recompute it, or delete the entry and let "
                    "the loss's value estimator compute it."
                )
            raise ValueError(
                f"{key!r} holds {int((~finite).sum())} non-finite value(s): the policy "
                f"gradient would be NaN. {cause}"
            )
        diagnostics = {}
        if self.baseline in GROUP_BASELINES:
            keys = self.tensor_keys
            psi = batch_group_advantage(
                tensordict,
                psi,
                baseline=self.baseline,
                scale=self.group_scale,
                per_episode=isinstance(self.value_estimator, DiscountedReturn),
                group_key=keys.group,
                greedy_key=keys.greedy,
                done_key=("next", keys.done),
                mask=padding,
            )
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
        return psi, diagnostics, state_value, valid

    def _valid_steps(
        self, tensordict: TensorDictBase, like: torch.Tensor, padding: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        """The steps to learn from, shaped like ``like`` (None: all of them): those the
        padding mask keeps, less the greedy episodes' steps of ``baseline="greedy"``."""
        if padding is None:
            padding = self._padding_mask(tensordict, like)
        if self.baseline != "greedy":
            return padding
        sampled = ~greedy_flags(tensordict, self.tensor_keys.greedy).expand_as(like)
        return sampled if padding is None else sampled & padding

    def _padding_mask(self, tensordict: TensorDictBase, like: torch.Tensor):
        """The padding mask (e.g. ``("collector", "mask")``) shaped like ``like``, or None."""
        for key in self._loss_mask_keys():
            mask = tensordict.get(key, None)
            if mask is None:
                continue
            if mask.dtype != torch.bool:
                raise TypeError(
                    f"The padding mask {key!r} must be boolean (True on the steps to learn "
                    f"from), got dtype {mask.dtype}. Pass mask.bool()."
                )
            batch = tensordict.batch_size
            if mask.shape[: len(batch)] != batch or mask[(0,) * len(batch)].numel() != 1:
                raise ValueError(
                    f"The padding mask {key!r} has shape {tuple(mask.shape)}; it needs one "
                    f"value per step of the batch {tuple(batch)}."
                )
            mask = mask.reshape(batch)
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
        if "time" in tensordict.names:
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
        error = target - value
        # The estimator writes them detached; a batch may hold them otherwise.
        if error.requires_grad:
            error, target = error.detach(), target.detach()
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
            try:
                return self.actor_network.get_dist(tensordict)
            except ValueError as err:
                # torch.distributions validates its parameters (NaN logits or scales).
                first_line = str(err).splitlines()[0]  # torch appends the whole tensor
                raise ValueError(
                    f"The policy built an invalid distribution from this batch "
                    f"({first_line}). "
                    f"{self._why_not_finite(tensordict)}"
                ) from err

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
            check_action_shape(dist, action, self.tensor_keys.action, tensordict.batch_size)
            check_support(dist, action, self.tensor_keys.action, self._declares_bounds)
        if type(dist) is torch.distributions.Categorical and not action.is_floating_point():
            # What Categorical.log_prob computes, without broadcasting the actions
            # against the logits first (their shapes match) or re-checking the support.
            log_prob = dist.logits.gather(-1, action.long().unsqueeze(-1)).squeeze(-1)
        else:
            log_prob = dist.log_prob(action)
        if is_tensor_collection(log_prob):
            log_prob = log_prob.sum(dim="feature", reduce=True)  # over the action's entries
        log_prob = per_step(log_prob, weights.shape, "log-probabilities")
        if not bool(torch.isfinite(log_prob).all()):
            raise ValueError(
                f"The policy gave {int((~torch.isfinite(log_prob)).sum())} non-finite "
                f"log-probabilities for the stored actions. {self._why_not_finite(tensordict)}"
            )
        return log_prob

    def _why_not_finite(self, tensordict: TensorDictBase) -> str:
        for key in self.actor_network.in_keys:
            value = tensordict.get(key, None)
            if isinstance(value, torch.Tensor) and not bool(torch.isfinite(value).all()):
                return (
                    f"The policy's input {key!r} holds {int((~torch.isfinite(value)).sum())} "
                    f"NaN/inf value(s): check the observations (or their normalisation)."
                )
        return (
            "Either an action has (near) zero probability under the policy (e.g. on the "
            "bounds of a TanhNormal that was not declared), or the policy's output is "
            "NaN because its weights diverged: lower the learning rate or clip gradients."
        )

    def loss_critic(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor | None]:
        target = required(
            tensordict,
            self.tensor_keys.value_target,
            "Make sure you provided the right key and the value_target (i.e. the target "
            "return) has been retrieved accordingly.",
        )
        if not bool(torch.isfinite(target).all()):
            raise ValueError(
                f"{self.tensor_keys.value_target!r} holds non-finite values: the critic would "
                f"regress on NaN. Check the rewards and the value network that computed it."
            )
        old_value = None
        if self.clip_value is not None:
            old_value = required(
                tensordict,
                self.tensor_keys.value,
                "Make sure that the value_key passed to Reinforce exists in the input tensordict.",
                lead=f"clip_value is set to {self.clip_value}, but ",
            ).clone()
        inputs = tensordict.select(*self.critic_network.in_keys, strict=False)
        with (
            self.critic_network_params.to_module(self.critic_network, preserve_module_state=False)
            if self.functional
            else contextlib.nullcontext()
        ):
            state_value = self.critic_network(inputs).get(self.tensor_keys.value)
        if self.value_norm is not None:  # the regression, and the clip, in its units
            normalize = self.value_norm.normalize
            target, state_value = normalize(target.detach()), normalize(state_value)
            if old_value is not None:
                old_value = normalize(old_value)
        loss_value = self._critic_distance(target, state_value)
        clip_fraction = None
        if self.clip_value is not None:
            loss_value, clip_fraction = _clip_value_loss(
                old_value,
                state_value,
                self.clip_value.to(state_value.device),
                target,
                loss_value,
                self.loss_critic_type,
            )
        return loss_value, clip_fraction

    def _critic_distance(self, target: torch.Tensor, state_value: torch.Tensor) -> torch.Tensor:
        """The per-step critic loss (a clear error for values shaped unlike targets)."""
        try:
            return distance_loss(target, state_value, loss_function=self.loss_critic_type)
        except RuntimeError as err:
            if "incompatible" not in str(err):  # distance_loss on unequal shapes
                raise
            raise ValueError(
                f"The critic's {self.tensor_keys.value!r} does not have the shape of "
                f"{self.tensor_keys.value_target!r} ({err}). Make the critic write one value "
                f"per step, shaped like the reward ([*B, 1])."
            ) from err

    def _update_value_norm(self, tensordict: TensorDictBase) -> None:
        """Folds the batch's value targets (padding excluded) into ``value_norm``."""
        target = tensordict.get(self.tensor_keys.value_target)
        valid = self._valid_steps(tensordict, target)
        if valid is not None:
            target = target[valid].reshape(-1, *self.value_norm.shape)
        self.value_norm.update(target.detach())

    def value_loss(
        self, tensordict: TensorDictBase, *, value: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``loss_value`` alone, on a batch whose value targets ``forward`` already wrote.

        Fits the critic with more gradient steps per batch than the policy takes (the
        value-function iterations of "vanilla" policy gradient): each call evaluates
        the critic afresh, while the targets stay those of the batch. Reduced (and
        masked) as ``forward`` reduces ``loss_value``, and weighted by ``critic_coeff``.
        ``value``: the critic's ``V(s_t)`` on this batch, still attached to its current
        parameters, as ``policy_weights(batch, keep_value=True)`` gave it (the critic
        is then not called; None calls it).

        Raises:
            ValueError: the loss has no critic; ``value`` detached from the critic, or
                given with ``clip_value`` or ``value_norm``.
            KeyError: the batch has no value target yet; call ``forward`` (or the
                value estimator) on it first.

        Examples:
            >>> import torch
            >>> from tensordict import TensorDict
            >>> from tensordict.nn import TensorDictModule
            >>> from torchrl.modules import ProbabilisticActor, ValueOperator
            >>> from rl_pg import ReinforceLoss
            >>> actor = ProbabilisticActor(
            ...     TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"]),
            ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
            ... )
            >>> loss = ReinforceLoss(actor, ValueOperator(torch.nn.Linear(3, 1), ["observation"]))
            >>> data = TensorDict({
            ...     "observation": torch.randn(4, 3),
            ...     "action": torch.tensor([0, 1, 1, 0]),
            ...     "next": {"observation": torch.randn(4, 3), "reward": torch.ones(4, 1),
            ...              "done": torch.tensor([[False], [True], [False], [True]]),
            ...              "terminated": torch.tensor([[False], [True], [False], [True]])},
            ... }, batch_size=[4])
            >>> out = loss(data)
            >>> bool(loss.value_loss(data) == out["loss_value"])
            True
        """
        if not self.has_critic:
            raise ValueError("This ReinforceLoss has no critic: value_loss needs a critic_network.")
        if tensordict.get(self.tensor_keys.value_target, None) is None:
            raise KeyError(
                f"The batch has no value target {self.tensor_keys.value_target!r} yet: call "
                f"the loss (or its value estimator) on it before value_loss."
            )
        if value is None:
            loss_value, _ = self.loss_critic(tensordict)
        else:
            if self.clip_value is not None or self.value_norm is not None:
                raise ValueError(
                    "value_loss(value=...) regresses the given values as they are, which "
                    "skips clip_value's and value_norm's treatment: leave value=None "
                    "with them (policy_weights gives None for them anyway)."
                )
            if not value.requires_grad:
                raise ValueError(
                    "value_loss(value=...) got a value detached from the critic: its loss "
                    "would train nothing. Pass the value policy_weights(batch, "
                    "keep_value=True) gave, under torch.enable_grad(), or leave value=None."
                )
            target = tensordict.get(self.tensor_keys.value_target)
            loss_value = self._critic_distance(target, value)
        valid = self._valid_steps(tensordict, loss_value)
        return self._reduce_steps(self.critic_coeff * loss_value, tensordict, valid).squeeze(-1)

    def _entropy(self, dist) -> torch.Tensor:
        try:
            entropy = dist.entropy()
        except NotImplementedError:
            # No closed form (e.g. TanhNormal): a one-sample Monte-Carlo estimate.
            sample = dist.rsample() if dist.has_rsample else dist.sample()
            entropy = -dist.log_prob(sample)
        if is_tensor_collection(entropy):
            entropy = entropy.sum(dim="feature", reduce=True)
        return entropy
