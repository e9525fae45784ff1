"""Per-unit policy gradients of every return estimator on the same batch, and their
noise ([`noise_statistics`][rl_pg.gradient_noise.noise_statistics])."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives.value import GAE

from rl_pg._checks import check_choice, check_int, check_real
from rl_pg.estimators import RewardToGo
from rl_pg.functional import discounted_return, reward_to_go
from rl_pg.gradient_noise import UNITS, noise_statistics, unit_index
from rl_pg.groups import batch_group_advantage, greedy_flags
from rl_pg.loss import ReinforceLoss
from rl_pg.step_log_prob import StepLogProb, actor_parameters

__all__ = ["ESTIMATORS", "GradientStatistics"]

ESTIMATORS = (
    "loss",
    "episode_return",
    "reward_to_go",
    "reward_to_go_minus_mean",
    "reward_to_go_minus_value",
    "gae",
    "leave_one_out",
    "group_mean",
    "group_mean_scaled",
    "greedy",
)
"""The `Ψ` that [`GradientStatistics`][rl_pg.gradient_statistics.GradientStatistics]
compares: the loss's own (its estimator, baseline and normalisation as it trains); the
whole-episode return `R(τ)`; the reward-to-go `G_t`; `G_t` minus a scalar baseline; `G_t`
minus the critic's `V(s_t)`; GAE(λ) with the critic; and `G_t` minus a group baseline
([`rl_pg.groups`][rl_pg.groups]): the mean of the group's other episodes, the whole
group's mean (also divided by the group's standard deviation), its greedy episode's.
Those with `V` need a critic; the group ones a grouped batch measured by group."""
_NEED_CRITIC = frozenset({"reward_to_go_minus_value", "gae"})
_GROUP = {
    "leave_one_out": ("leave_one_out", False),
    "group_mean": ("group_mean", False),
    "group_mean_scaled": ("group_mean", True),
    "greedy": ("greedy", False),
}
_METHODS = ("auto", "vmap", "backward")
_DENSE_UNITS = 8  # up to this many units in a chunk, the dense product is the faster


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
            the loss can compute (those with a critic only when it has one, the group
            ones with ``unit="group"``, ``"greedy"`` on batches with greedy episodes).
        unit (str): ``"episode"``, ``"row"`` or ``"group"`` (see
            [`unit_index`][rl_pg.gradient_noise.unit_index]). Defaults to
            ``"episode"``. Batches collected in groups (episodes that share a start)
            are measured by group: their episodes are not independent, and a group
            baseline couples them further. The group estimators need ``"group"``.
        gae_lambda (float, optional): GAE's `λ`. Defaults to the loss's own when its
            estimator is GAE, else ``0.95``.
        scalar_baseline (float, optional): the `b` of ``"reward_to_go_minus_mean"``.
            Defaults to ``None``: the mean return of the batch's episodes at their
            first step (which, using the batch itself, shrinks `E[ĝ]` by `1 − 1/U`).
        chunk (int, optional): steps whose gradients are held at once (memory against
            speed: ``chunk`` x the actor's parameter count numbers). Defaults to
            ``None``: about two million numbers.
        method (str): how the per-unit gradients are computed. ``"vmap"``: each step's
            gradient of ``log π`` with ``torch.func`` (``vmap`` of ``grad``), summed
            into units weighted by every estimator's `Ψ` (cost grows with steps x
            parameters); ``"backward"``: one batched backward pass per group of units
            through autograd (works for any policy autograd can differentiate, at a
            cost that grows with units x steps); ``"auto"``: ``"vmap"``, falling back to
            ``"backward"`` for a policy that ``torch.func`` cannot transform.
            Defaults to ``"auto"``.

    Raises:
        ValueError: an unknown estimator or unit, one that needs a critic the loss
            does not have, or a group estimator measured by another unit than groups.

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
        chunk: int | None = None,
        method: str = "auto",
    ) -> None:
        if not isinstance(loss, ReinforceLoss):
            raise TypeError(
                f"GradientStatistics measures an rl_pg.ReinforceLoss's policy term, got "
                f"{type(loss).__name__}: build the loss with rl_pg.ReinforceLoss (the same "
                f"arguments as TorchRL's)."
            )
        has_critic = loss.has_critic
        self._default = estimators is None
        if estimators is None:
            estimators = [
                e
                for e in ESTIMATORS
                if (has_critic or e not in _NEED_CRITIC) and (unit == "group" or e not in _GROUP)
            ]
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
        check_choice("unit", unit, UNITS)
        grouped = [e for e in estimators if e in _GROUP]
        if grouped and unit != "group":
            raise ValueError(
                f"The estimators {grouped} weigh each episode against the others of its "
                f"group, which makes them dependent: measure them with unit='group' (on "
                f"batches collected in groups), not unit={unit!r}."
            )
        chunk = check_int("chunk", chunk, low=1, optional=True)
        self.method = check_choice("method", method, _METHODS)
        estimator = loss.value_estimator
        gamma = float(estimator.gamma)
        if gae_lambda is None:
            gae_lambda = float(estimator.lmbda) if isinstance(estimator, GAE) else 0.95
        self.loss, self.estimators, self.unit, self.chunk = loss, estimators, unit, chunk
        self.gae_lambda = check_real("gae_lambda", gae_lambda, low=0, high=1)
        self.scalar_baseline = check_real("scalar_baseline", scalar_baseline, optional=True)
        critic = loss.critic_network if has_critic else None
        keys = loss.tensor_keys
        self._gamma = gamma
        self._reward_to_go = RewardToGo(gamma=gamma, value_network=critic)
        self._reward_to_go.set_keys(
            reward=keys.reward, done=keys.done, terminated=keys.terminated, value=keys.value
        )

    def weights(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """Each estimator's detached `Ψ_t`, shaped ``[*batch_size]`` (0 on padding).

        The critic runs once: its `V(s_t)` and `V(s_{t+1})` bootstrap every return, as
        rl_pg's estimators do, and GAE is the reward-to-go of the TD errors
        `δ_t = r_t + γ V(s_{t+1}) − V(s_t)` discounted by `γλ` (TorchRL's GAE).
        """
        loss, names = self.loss, self._estimators(batch)
        wanted = set(names)
        keys = loss.tensor_keys
        psi = {}
        with torch.no_grad():
            if "loss" in wanted:
                psi["loss"] = self._loss_weights(batch)
            data = batch.copy()
            self._reward_to_go(data)  # writes the values it bootstraps from, if any
            to_go = data.get("value_target")
            reward = data.get(("next", keys.reward))
            done = data.get(("next", keys.done))
            terminated = data.get(("next", keys.terminated), None)
            value = data.get(keys.value, None) if loss.has_critic else None
            next_value = data.get(("next", keys.value), None) if loss.has_critic else None
            time_dim = self._time_dim(data)
            gamma = self._gamma
            if "episode_return" in wanted:
                psi["episode_return"] = discounted_return(
                    reward, done, gamma, time_dim=time_dim, terminated=terminated,
                    next_value=next_value,
                )  # fmt: skip
            if "reward_to_go" in wanted:
                psi["reward_to_go"] = to_go
            if "reward_to_go_minus_mean" in wanted:
                baseline = self.scalar_baseline
                if baseline is None:
                    valid = loss.valid_steps(data)
                    baseline = loss.episode_returns(data, to_go, valid).mean()
                psi["reward_to_go_minus_mean"] = to_go - baseline
            if "reward_to_go_minus_value" in wanted:
                psi["reward_to_go_minus_value"] = to_go - value
            if "gae" in wanted:
                ended = done if terminated is None else terminated
                delta = reward + gamma * next_value * ~ended.bool() - value
                psi["gae"] = reward_to_go(delta, done, gamma * self.gae_lambda, time_dim=time_dim)
            valid = padding = loss.valid_steps(batch, greedy=True)
            if padding is not None:
                valid = padding = padding.squeeze(-1)
            if keys.greedy in batch.keys(True):  # greedy episodes are no samples of the policy
                sampled = ~greedy_flags(batch, keys.greedy).reshape(batch.batch_size)
                valid = sampled if valid is None else valid & sampled
            for name in wanted & _GROUP.keys():
                baseline, scale = _GROUP[name]
                # The greedy baseline reads the greedy episodes; the others must not.
                mask = padding if baseline == "greedy" else valid
                psi[name] = batch_group_advantage(
                    batch,
                    to_go.reshape(*batch.batch_size, 1),
                    baseline=baseline,
                    scale=scale,
                    group_key=keys.group,
                    greedy_key=keys.greedy,
                    done_key=("next", keys.done),
                    mask=None if mask is None else mask.unsqueeze(-1),
                )
        out = {}
        for name in names:
            value = psi[name].reshape(batch.batch_size)
            if valid is not None:
                value = value.masked_fill(~valid, 0.0)
            out[name] = value
        return out

    def _estimators(self, batch: TensorDictBase) -> list[str]:
        """The estimators measured on ``batch``: by default, ``"greedy"`` only where
        the batch has greedy episodes."""
        if self._default and self.loss.tensor_keys.greedy not in batch.keys(True):
            return [e for e in self.estimators if e != "greedy"]
        return list(self.estimators)

    @staticmethod
    def _time_dim(data: TensorDictBase) -> int:
        """The time dimension of a ``[*B, T, 1]`` per-step entry, counted from the end."""
        names = list(data.names)
        dim = names.index("time") if "time" in names else data.batch_dims - 1
        return dim - data.batch_dims - 1

    def _loss_weights(self, batch: TensorDictBase) -> torch.Tensor:
        """The `Ψ` the loss itself weights ``log π`` with, its state left as it is."""
        data = batch.copy()
        for key in (self.loss.tensor_keys.advantage, self.loss.tensor_keys.value_target):
            data.pop(key, None)
        return self.loss.weights_as_they_are(data)

    def unit_gradients(
        self, batch: TensorDictBase, weights: dict[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """Each estimator's ``[U, P]`` unit gradients `Σ_{t∈u} Ψ_t ∇ log π(a_t|s_t)`,
        the actor's parameters flattened in its ``named_parameters`` order."""
        loss = self.loss
        keys = loss.tensor_keys
        index, units = unit_index(
            batch, unit=self.unit, done_key=("next", keys.done), group_key=keys.group
        )
        names = list(weights)
        time_dim = self._time_dim(batch) + batch.batch_dims + 1
        if time_dim != batch.batch_dims - 1:  # time last: each unit's steps are contiguous
            order = [d for d in range(batch.batch_dims) if d != time_dim] + [time_dim]
            batch, index = batch.permute(*order).contiguous(), index.permute(*order)
            weights = {name: value.permute(*order) for name, value in weights.items()}
        steps = batch.reshape(-1)
        index = index.reshape(-1)
        psi = torch.stack([weights[n].reshape(-1) for n in names])  # [E, N]
        if self.unit == "group":  # each group's steps together, as for the others
            order = torch.argsort(index, stable=True)
            steps, index, psi = steps[order], index[order], psi[:, order]
        with torch.no_grad():  # refuses actions the policy cannot have taken, as the loss does
            self._log_prob(steps)
        params = actor_parameters(loss)
        if self.method != "backward":
            try:
                flat = self._by_steps(steps, index, units, psi, params)
            except RuntimeError:
                if self.method == "vmap":
                    raise
                self.method = "backward"  # this policy stays on autograd from now on
        if self.method == "backward":
            flat = self._by_units(steps, index, units, psi, params)
        return {name: flat[i] for i, name in enumerate(names)}

    def _by_steps(self, steps, index, units, psi, params) -> torch.Tensor:
        """Per-step gradients (``vmap`` of ``grad``), summed into units by each `Ψ`.

        Steps go in chunks of about two million gradient numbers (``chunk`` steps when
        given): larger blocks cost more in fresh memory than they save in calls. A
        unit's steps are contiguous, so each chunk's units form a range; a product of
        the matrix of `Ψ` on each (estimator, unit)'s own steps with the chunk's
        gradients sums them: dense for a few units (BLAS), sparse for many (it then
        does only the multiplications that count).
        """
        one_step = StepLogProb(self.loss)
        detached = {f"actor.{name}": p.detach() for name, p in params.items()}

        def log_prob(values, step):
            return torch.func.functional_call(one_step, values, (step,), strict=True)

        per_step = torch.func.vmap(torch.func.grad(log_prob), in_dims=(None, 0))
        size = sum(p.numel() for p in detached.values())
        chunk = self.chunk or max(1, 2**21 // size)
        estimators = psi.shape[0]
        out = torch.zeros(estimators, units, size, dtype=psi.dtype, device=psi.device)
        for start in range(0, steps.numel(), chunk):
            stop = min(steps.numel(), start + chunk)
            grads = per_step(detached, one_step.inputs(steps[start:stop]))
            where = index[start:stop].to(psi.device)
            first, last = int(where.min()), int(where.max()) + 1
            span = last - first
            if span <= _DENSE_UNITS:  # [E, units, steps]: Ψ on each unit's own steps
                local = torch.nn.functional.one_hot(where - first, span).T.to(psi)
                weights = psi[:, start:stop].unsqueeze(1) * local
            else:  # the same matrix as [E * units, steps], sparse: one Ψ per step
                rows = torch.arange(estimators, device=psi.device).unsqueeze(1) * span
                rows = (rows + where - first).reshape(-1)
                cols = torch.arange(stop - start, device=psi.device).repeat(estimators)
                weights = torch.sparse_coo_tensor(
                    torch.stack([rows, cols]),
                    psi[:, start:stop].reshape(-1),
                    (estimators * span, stop - start),
                    check_invariants=False,  # built valid: every index is in range
                )
            offset = 0
            for grad in grads.values():
                width = grad[0].numel()
                flat = grad.reshape(stop - start, width).to(psi)
                summed = weights @ flat if span <= _DENSE_UNITS else torch.sparse.mm(weights, flat)
                out[:, first:last, offset : offset + width] += summed.reshape(
                    estimators, span, width
                )
                offset += width
        return out

    def _by_units(self, steps, index, units, psi, params) -> torch.Tensor:
        """Groups of units through one batched backward pass each."""
        params = list(params.values())
        per_group = max(1, (self.chunk or 256) // (4 * psi.shape[0]))
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
            grads.append(flat.reshape(psi.shape[0], last - first, -1).detach())
        return torch.cat(grads, dim=1)

    def _log_prob(self, steps: TensorDictBase) -> torch.Tensor:
        """``log π(a_t|s_t)`` of a flat batch of steps, through the loss's own policy."""
        return self.loss.log_prob(steps).reshape(-1)

    def __call__(self, batch: TensorDictBase) -> TensorDict:
        """The statistics of every estimator on ``batch``: a ``TensorDict`` keyed by
        estimator name, each holding the entries of
        [`noise_statistics`][rl_pg.gradient_noise.noise_statistics].

        Raises:
            ValueError: fewer than two units in the batch.
        """
        gradients = self.unit_gradients(batch, self.weights(batch))
        stats = noise_statistics(torch.stack(list(gradients.values())))
        return TensorDict({name: stats[i] for i, name in enumerate(gradients)}, batch_size=[])
