"""How noisy the policy gradient is: per-unit gradients and the statistics of their spread.

REINFORCE estimates `∇J` by averaging independent units (whole episodes, or one
environment's segment each): unit `u` contributes `g_u = Σ_{t∈u} Ψ_t ∇ log π(a_t|s_t)`.
From `U` such gradients of one batch, at the parameters that collected it:

* ``trace_covariance``: `tr Σ`, the unbiased per-unit variance summed over parameters;
* ``grad_norm_sq``: an unbiased estimate of `|∇J|²`, `|ḡ|² − tr Σ / U` (it can come out
  negative when the batch cannot tell the signal from zero);
* ``noise_scale``: `B = tr Σ / |∇J|²`, the batch size (in units) at which noise and
  signal are equal (McCandlish et al., 2018); NaN when ``grad_norm_sq`` is not positive;
* ``snr``: `|∇J|² / (tr Σ / U) = U / B`, the signal-to-noise ratio of the batch's mean
  gradient at the batch size used;
* ``half_cosine``: the cosine between the mean gradients of two disjoint halves of the
  units (even and odd), near 1 when the batch is large enough to agree with itself.

[`GradientStatistics`][rl_pg.gradient_statistics.GradientStatistics] measures them for
the loss's own `Ψ` and, on the same batch at the same parameters, for every other
return estimator, so that estimators are compared on identical data.
[`noise_statistics`][rl_pg.gradient_statistics.noise_statistics] is the pure function on
a ``[U, P]`` tensor of unit gradients.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives.value import GAE

from rl_pg._checks import check_real
from rl_pg.estimators import DiscountedReturn, RewardToGo

__all__ = ["ESTIMATORS", "GradientStatistics", "noise_statistics", "unit_index"]

ESTIMATORS = (
    "loss",
    "episode_return",
    "reward_to_go",
    "reward_to_go_minus_mean",
    "reward_to_go_minus_value",
    "gae",
)
"""The `Ψ` that [`GradientStatistics`][rl_pg.gradient_statistics.GradientStatistics]
compares: the loss's own (its estimator, baseline and normalisation as it trains); the
whole-episode return `R(τ)`; the reward-to-go `G_t`; `G_t` minus a scalar baseline; `G_t`
minus the critic's `V(s_t)`; and GAE(λ) with the critic. The last two need a critic."""
_NEED_CRITIC = frozenset({"reward_to_go_minus_value", "gae"})
_UNITS = ("episode", "row")


def noise_statistics(unit_gradients: torch.Tensor) -> TensorDict:
    """The spread of ``U`` independent unit gradients ``[U, P]`` (module docstring).

    Args:
        unit_gradients (torch.Tensor): one flattened gradient per unit, ``[U, P]``,
            ``U >= 2``.

    Returns:
        A ``TensorDict(batch_size=[])`` with ``mean_gradient`` (``[P]``), ``units``,
        ``mean_grad_norm_sq`` (`|ḡ|²`), ``grad_norm_sq``, ``trace_covariance``,
        ``noise_scale``, ``snr`` and ``half_cosine``.

    Raises:
        ValueError: not a 2-D tensor with at least two rows, or non-finite entries.

    Examples:
        >>> import torch
        >>> from rl_pg.gradient_statistics import noise_statistics
        >>> g = torch.tensor([[1.0, 0.0], [3.0, 0.0], [1.0, 2.0], [3.0, -2.0]])
        >>> stats = noise_statistics(g)
        >>> stats["mean_gradient"], stats["trace_covariance"].item()
        (tensor([2., 0.]), 4.0)
        >>> stats["grad_norm_sq"].item(), stats["noise_scale"].item(), stats["snr"].item()
        (3.0, 1.3333333730697632, 3.0)
    """
    if not isinstance(unit_gradients, torch.Tensor) or unit_gradients.ndim != 2:
        raise ValueError(
            f"unit_gradients must be a [units, parameters] tensor, got "
            f"{getattr(unit_gradients, 'shape', type(unit_gradients).__name__)}."
        )
    units = unit_gradients.shape[0]
    if units < 2:
        raise ValueError(
            f"The spread of gradients needs at least 2 independent units, got {units}: "
            f"collect more episodes (or environments) per batch."
        )
    if not bool(torch.isfinite(unit_gradients).all()):
        raise ValueError("unit_gradients holds NaN/inf: check the returns and the policy.")
    mean = unit_gradients.mean(0)
    trace = (unit_gradients - mean).pow(2).sum() / (units - 1)
    mean_norm_sq = mean.pow(2).sum()
    norm_sq = mean_norm_sq - trace / units
    halves = unit_gradients[0::2].mean(0), unit_gradients[1::2].mean(0)
    cosine = torch.nn.functional.cosine_similarity(*halves, dim=0, eps=1e-30)
    return TensorDict(
        {
            "mean_gradient": mean,
            "units": torch.tensor(units),
            "mean_grad_norm_sq": mean_norm_sq,
            "grad_norm_sq": norm_sq,
            "trace_covariance": trace,
            "noise_scale": torch.where(norm_sq > 0, trace / norm_sq, torch.nan),
            "snr": norm_sq / (trace / units).clamp_min(torch.finfo(trace.dtype).tiny),
            "half_cosine": cosine,
        },
        batch_size=[],
    )


def unit_index(
    batch: TensorDictBase, *, unit: str = "episode", done_key=("next", "done"), time_dim=None
) -> tuple[torch.Tensor, int]:
    """The independent unit of every step of ``batch``: its episode, or its row.

    Args:
        batch (TensorDictBase): ``[T]`` (episodes laid end to end) or ``[*B, T]``.

    Keyword Args:
        unit (str): ``"episode"``: each episode is a unit (one cut by the batch's edge
            too); ``"row"``: each row along the time dimension (one environment's
            segment). Defaults to ``"episode"``.
        done_key (NestedKey): the end-of-episode flags. Defaults to ``("next", "done")``.
        time_dim (int, optional): the time dimension. Defaults to the one named
            ``"time"``, else the last.

    Returns:
        ``(index, units)``: a ``long`` tensor of ``batch``'s shape numbering the units
        ``0 … units − 1`` in order of appearance along each row.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rl_pg.gradient_statistics import unit_index
        >>> done = torch.tensor([[False, True, False], [True, False, False]])
        >>> batch = TensorDict({"next": {"done": done.unsqueeze(-1)}}, [2, 3])
        >>> unit_index(batch)
        (tensor([[0, 0, 1],
                [2, 3, 3]]), 4)
        >>> unit_index(batch, unit="row")[0].tolist()
        [[0, 0, 0], [1, 1, 1]]
    """
    if unit not in _UNITS:
        raise ValueError(f"unit must be one of {_UNITS}, got {unit!r}.")
    if batch.batch_dims < 1:
        raise ValueError(
            f"unit_index needs a batch with a time dimension, got batch_size "
            f"{tuple(batch.batch_size)}."
        )
    if time_dim is None:
        names = batch.names if batch._has_names() else []
        time_dim = names.index("time") if "time" in names else batch.batch_dims - 1
    shape = batch.batch_size
    rows = torch.arange(shape.numel() // shape[time_dim])
    rows = rows.reshape((*shape[:time_dim], *shape[time_dim + 1 :]))
    index = rows.unsqueeze(time_dim).expand(shape)
    if unit == "episode":
        done = batch.get(done_key, None)
        if done is None:
            raise KeyError(f"unit='episode' reads the episode ends at {done_key!r}: not found.")
        done = done.reshape(*shape, -1).any(-1).movedim(time_dim, -1)
        # Episodes started before step t of its row: the ends strictly before it.
        started = done.long().cumsum(-1) - done.long()
        width = done.shape[-1]  # at most one episode per step in a row
        index = (index.movedim(time_dim, -1) * width + started).movedim(-1, time_dim)
    _, index = torch.unique(index.reshape(-1), sorted=True, return_inverse=True)
    return index.reshape(shape), int(index.max()) + 1


class GradientStatistics:
    """Gradient noise of a [`ReinforceLoss`][rl_pg.ReinforceLoss]'s policy term, for
    each return estimator, on one batch at the current parameters.

    Only the actor's parameters and the policy term `Ψ_t log π` count (not the critic,
    not the entropy bonus). The loss's state (a running baseline, value statistics)
    is left untouched, and no random number is drawn.

    Args:
        loss (ReinforceLoss): the loss; its actor, critic, keys, `γ` (and GAE's `λ`, when
            its estimator is GAE) are used.

    Keyword Args:
        estimators (sequence of str, optional): names from
            [`ESTIMATORS`][rl_pg.gradient_statistics.ESTIMATORS]. Defaults to all those
            the loss can compute (those with a critic only when it has one).
        unit (str): ``"episode"`` or ``"row"`` (see
            [`unit_index`][rl_pg.gradient_statistics.unit_index]). Defaults to
            ``"episode"``.
        gae_lambda (float, optional): GAE's `λ`. Defaults to the loss's own when its
            estimator is GAE, else ``0.95``.
        scalar_baseline (float, optional): the `b` of ``"reward_to_go_minus_mean"``.
            Defaults to ``None``: the mean return of the batch's episodes at their
            first step (which, using the batch itself, shrinks `E[ĝ]` by `1 − 1/U`).
        chunk (int): unit gradients computed per batched backward pass (memory against
            speed). Defaults to ``64``.

    Raises:
        ValueError: an unknown estimator or unit, or one that needs a critic the loss
            does not have.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> from rl_pg import ReinforceLoss
        >>> from rl_pg.gradient_statistics import GradientStatistics
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> actor = ProbabilisticActor(
        ...     TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"]),
        ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
        ... )
        >>> loss = ReinforceLoss(actor)
        >>> done = torch.zeros(4, 5, 1, dtype=torch.bool)
        >>> done[:, -1] = True
        >>> batch = TensorDict({
        ...     "observation": torch.randn(4, 5, 3), "action": torch.randint(2, (4, 5)),
        ...     "next": {"reward": torch.randn(4, 5, 1), "done": done, "terminated": done},
        ... }, [4, 5])
        >>> stats = GradientStatistics(loss)(batch)
        >>> sorted(stats.keys())
        ['episode_return', 'loss', 'reward_to_go', 'reward_to_go_minus_mean']
        >>> stats["reward_to_go", "units"].item(), stats["loss", "mean_gradient"].shape
        (4, torch.Size([8]))
    """

    def __init__(
        self,
        loss,
        *,
        estimators: Sequence[str] | None = None,
        unit: str = "episode",
        gae_lambda: float | None = None,
        scalar_baseline: float | None = None,
        chunk: int = 64,
    ) -> None:
        has_critic = bool(getattr(loss, "has_critic", False))
        if estimators is None:
            estimators = [e for e in ESTIMATORS if has_critic or e not in _NEED_CRITIC]
        estimators = list(estimators)
        unknown = [e for e in estimators if e not in ESTIMATORS]
        if unknown or not estimators:
            raise ValueError(f"estimators must be names from {ESTIMATORS}, got {estimators}.")
        missing = [e for e in estimators if e in _NEED_CRITIC and not has_critic]
        if missing:
            raise ValueError(
                f"The estimators {missing} subtract the critic's V(s), but the loss has no "
                f"critic: drop them, or give the loss a critic_network."
            )
        if unit not in _UNITS:
            raise ValueError(f"unit must be one of {_UNITS}, got {unit!r}.")
        if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
            raise ValueError(f"chunk must be a positive integer, got {chunk!r}.")
        estimator = loss.value_estimator
        gamma = float(estimator.gamma)
        if gae_lambda is None:
            gae_lambda = float(estimator.lmbda) if isinstance(estimator, GAE) else 0.95
        self.loss, self.estimators, self.unit, self.chunk = loss, estimators, unit, chunk
        self.gae_lambda = check_real("gae_lambda", gae_lambda, low=0, high=1)
        self.scalar_baseline = check_real("scalar_baseline", scalar_baseline, optional=True)
        critic = loss.critic_network if has_critic else None
        keys = loss.tensor_keys
        self._returns = {
            "episode_return": DiscountedReturn(gamma=gamma, value_network=critic),
            "reward_to_go": RewardToGo(gamma=gamma, value_network=critic),
        }
        if has_critic:
            self._returns["gae"] = GAE(
                gamma=gamma, lmbda=self.gae_lambda, value_network=critic, average_gae=False
            )
        for module in self._returns.values():
            module.set_keys(
                reward=keys.reward, done=keys.done, terminated=keys.terminated, value=keys.value
            )

    def weights(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """Each estimator's detached `Ψ_t`, shaped ``[*batch_size]`` (0 on padding)."""
        loss = self.loss
        psi = {}
        with torch.no_grad():
            data = batch.copy()
            if "loss" in self.estimators:
                psi["loss"] = self._loss_weights(batch)
            wanted = set(self.estimators)
            computed = {}
            for name in ("episode_return", "reward_to_go", "gae"):
                if name in wanted or (
                    name == "reward_to_go"
                    and wanted & {"reward_to_go_minus_mean", "reward_to_go_minus_value"}
                ):
                    out = self._returns[name](data.copy())
                    computed[name] = out
            if "episode_return" in wanted:
                psi["episode_return"] = computed["episode_return"].get("value_target")
            if "reward_to_go" in wanted:
                psi["reward_to_go"] = computed["reward_to_go"].get("value_target")
            if "reward_to_go_minus_mean" in wanted:
                rtg = computed["reward_to_go"].get("value_target")
                baseline = self.scalar_baseline
                if baseline is None:
                    valid = loss._valid_steps(data, rtg)
                    baseline = loss._episode_returns(data, rtg, valid).mean()
                psi["reward_to_go_minus_mean"] = rtg - baseline
            if "reward_to_go_minus_value" in wanted:
                psi["reward_to_go_minus_value"] = computed["reward_to_go"].get("advantage")
            if "gae" in wanted:
                psi["gae"] = computed["gae"].get("advantage")
        valid = loss._valid_steps(batch, torch.zeros(batch.batch_size))
        out = {}
        for name in self.estimators:
            value = psi[name].reshape(batch.batch_size)
            if valid is not None:
                value = value.masked_fill(~valid, 0.0)
            out[name] = value
        return out

    def _loss_weights(self, batch: TensorDictBase) -> torch.Tensor:
        """The `Ψ` the loss itself weights ``log π`` with, its baseline's state kept."""
        loss = self.loss
        baseline = loss.baseline_module
        training = baseline.training if baseline is not None else False
        if baseline is not None:
            baseline.eval()  # answers without taking in the batch
        try:
            data = batch.copy()
            for key in (loss.tensor_keys.advantage, loss.tensor_keys.value_target):
                data.pop(key, None)
            psi, _, _ = loss._policy_weights(data)
        finally:
            if baseline is not None:
                baseline.train(training)
        return psi.detach()

    def unit_gradients(
        self, batch: TensorDictBase, weights: dict[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """Each estimator's ``[U, P]`` unit gradients `Σ_{t∈u} Ψ_t ∇ log π(a_t|s_t)`,
        the actor's parameters flattened in ``named_parameters`` order."""
        loss = self.loss
        index, units = unit_index(batch, unit=self.unit, done_key=("next", loss.tensor_keys.done))
        params = _actor_parameters(loss)
        names = list(weights)
        steps = batch.reshape(-1)
        index = index.reshape(-1)
        psi = torch.stack([weights[n].reshape(-1) for n in names])  # [E, N]
        # Units in groups of at most `chunk // E`: the policy runs once on each group's
        # steps, and one batched backward pass gives every (estimator, unit) gradient,
        # so the cost grows with the batch, not with units x steps.
        per_group = max(1, self.chunk // len(names))
        grads = []
        for first in range(0, units, per_group):
            last = min(units, first + per_group)
            where = ((index >= first) & (index < last)).nonzero().squeeze(-1)
            part = steps[where]
            with torch.enable_grad():
                log_prob = self._log_prob(part)
            local = torch.nn.functional.one_hot(index[where] - first, last - first).T
            cotangents = psi[:, where].to(log_prob).unsqueeze(1) * local.to(log_prob)
            cotangents = cotangents.reshape(-1, log_prob.numel())  # [E * group, steps]
            out = torch.autograd.grad(
                log_prob, params, grad_outputs=cotangents, is_grads_batched=True
            )
            flat = torch.cat([g.reshape(cotangents.shape[0], -1) for g in out], dim=1)
            grads.append(flat.reshape(len(names), last - first, -1).detach())
        flat = torch.cat(grads, dim=1)
        return {name: flat[i] for i, name in enumerate(names)}

    def _log_prob(self, steps: TensorDictBase) -> torch.Tensor:
        """``log π(a_t|s_t)`` of a flat batch of steps, through the loss's own policy."""
        loss = self.loss
        like = torch.zeros(steps.numel(), 1)
        if loss.functional:
            with loss.actor_network_params.to_module(loss.actor_network):
                return loss._log_prob(loss._policy(steps), steps, like).reshape(-1)
        return loss._log_prob(loss._policy(steps), steps, like).reshape(-1)

    def __call__(self, batch: TensorDictBase) -> TensorDict:
        """The statistics of every estimator on ``batch``: a ``TensorDict`` keyed by
        estimator name, each holding the entries of
        [`noise_statistics`][rl_pg.gradient_statistics.noise_statistics].

        Raises:
            ValueError: fewer than two units in the batch.
        """
        gradients = self.unit_gradients(batch, self.weights(batch))
        return TensorDict(
            {name: noise_statistics(g) for name, g in gradients.items()}, batch_size=[]
        )


def _actor_parameters(loss) -> list[torch.Tensor]:
    if loss.functional:
        values = loss.actor_network_params.values(True, True)
    else:
        values = loss.actor_network.parameters()
    seen, params = set(), []
    for p in values:
        if p.requires_grad and id(p) not in seen:
            seen.add(id(p))
            params.append(p)
    if not params:
        raise ValueError("The loss's actor has no trainable parameter: nothing to measure.")
    return params
