"""Natural-gradient steps for a REINFORCE policy: TRPO's update without sample reuse.

A plain gradient step of size η moves the parameters by η, whatever that does to the
policy; near a confident softmax the same parameter step barely changes the
probabilities, elsewhere it changes them a lot. The natural gradient (Kakade 2001)
measures the step by how much the *policy* changes instead: it preconditions the
REINFORCE gradient `g` with the inverse of the policy's Fisher information `F` (the
Hessian of the KL divergence between the old and new policy on the batch's states),

    Δθ = sqrt(2 δ / xᵀ F x) · x,   x = F⁻¹ g,

so that the quadratic model of the KL divergence after the step is the target ``δ``
(``max_kl``). `x` is found by conjugate gradient on Fisher-vector products, never
forming `F` (Schulman et al. 2015, TRPO), or, with ``fisher="kfac"``, from a
Kronecker-factored approximation of `F` that is inverted layer by layer in closed form
(Martens & Grosse 2015, K-FAC; Wu et al. 2017, ACKTR): cheaper by the ten or so
Fisher-vector products it does without, approximate where the exact solve is not. An
optional backtracking line search shrinks the step until the measured KL is within
``kl_tolerance · δ`` and the loss improves by a share of what the linear model
predicted. One step per batch: REINFORCE's on-policy gradient, not PPO's reuse.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase

from rl_pg._checks import check_bool, check_choice, check_int, check_real
from rl_pg.fisher import (
    conjugate_gradient,
    fisher_product,
    kfac_solve,
    kronecker_factors,
    linear_layers,
    recording,
)
from rl_pg.loss import ReinforceLoss
from rl_pg.policy_kl import kl_per_step, masked_mean

__all__ = ["NaturalGradient"]


class NaturalGradient:
    """Updates a [`ReinforceLoss`][rl_pg.ReinforceLoss]'s policy by natural-gradient
    steps of a set KL divergence, one per batch.

    ``step(batch)`` computes the loss's weights `Ψ` once, the gradient `g` of its
    policy terms (``loss_actor`` and ``loss_entropy``), the natural direction
    `x = F⁻¹ g` by ``cg_iters`` conjugate-gradient iterations on Fisher-vector
    products, and moves the policy's parameters in place by the step whose quadratic
    KL model is ``max_kl``. The Fisher is the Hessian of the closed-form KL where torch
    has it (categorical, normal, beta policies; taken as ``J^T H J`` through the
    distribution's parameters), else the mean outer product of the stored actions'
    scores (e.g. a ``TanhNormal``). The critic is not touched: train it with
    its own optimiser on ``loss.value_loss(batch)`` (the value targets are in the
    batch after ``step``); it must not share parameters with the policy. To call the
    critic once per batch, take ``weights, valid, value = loss.policy_weights(batch,
    keep_value=True)``, then ``step(batch, weights, valid)`` and
    ``loss.value_loss(batch, value=value)``.

    With ``fisher="kfac"`` each ``nn.Linear`` layer's block of the Fisher is taken as
    the Kronecker product ``A ⊗ G`` of the second moments of its inputs (``A``, with a
    1 appended for the bias) and of the score's gradients at its outputs (``G``, for
    actions sampled from the policy on each step, one per step), and the other blocks
    as 0. The direction is then ``(G + γ_G I)⁻¹ ∇W (A + γ_A I)⁻¹`` per layer, where
    ``γ_A γ_G = damping`` is split by the factors' mean eigenvalues (Martens & Grosse's
    π-damping), and the step's length is set by the same approximation's quadratic.
    Exact for a single layer on one input (a bandit's logits); an approximation
    otherwise (states whose inputs and policies differ share one ``G``). Every policy
    parameter must be a ``nn.Linear``'s weight or bias.

    Args:
        loss (ReinforceLoss): the loss whose policy is updated.

    Keyword Args:
        max_kl (float): `δ`, the KL divergence a step aims at. Defaults to ``0.01``.
        damping (float): added to the Fisher's diagonal (`F + λI`), which keeps the
            solve stable where the Fisher is singular (a softmax's logits can all
            shift together). Defaults to ``0.1``.
        cg_iters (int): conjugate-gradient iterations (``fisher="exact"``). Defaults
            to ``10``.
        fisher (str): ``"exact"`` (conjugate gradient on Fisher-vector products) or
            ``"kfac"`` (the Kronecker-factored Fisher, inverted in closed form).
            Defaults to ``"exact"``.
        fisher_fraction (float): the share of the batch's steps the Fisher is taken
            on (every ``1 / fisher_fraction``-th step; TRPO implementations subsample
            likewise): the products cost in proportion, the gradient still uses every
            step. Defaults to ``1.0``.
        line_search (bool): backtrack until the measured KL is at most
            ``kl_tolerance · max_kl`` and the loss improves by at least
            ``accept_ratio`` of the linear prediction; a step that no backtrack
            accepts is not taken. Defaults to ``True``.
        backtracks (int): line-search trials. Defaults to ``10``.
        backtrack_ratio (float): the step's shrink per trial. Defaults to ``0.8``.
        accept_ratio (float): the share of the predicted improvement required.
            Defaults to ``0.1``.
        kl_tolerance (float): how far above ``max_kl`` a measured KL may be.
            Defaults to ``1.5``.

    Raises:
        TypeError: ``loss`` is not a ``ReinforceLoss``.
        ValueError: an argument out of range; a critic that shares parameters with
            the policy; with ``fisher="kfac"``, a policy parameter outside every
            ``nn.Linear`` layer.

    Examples:
        >>> import torch
        >>> from rl_pg import ReinforceLoss
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor
        >>> from rl_pg.natural_gradient import NaturalGradient
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> env = GridWorldEnv(batch_size=8, max_steps=20)
        >>> actor = mlp_actor(env, hidden=(16,))
        >>> loss = ReinforceLoss(actor)
        >>> update = NaturalGradient(loss, max_kl=0.01)
        >>> batch = env.rollout(20, actor, break_when_all_done=True)
        >>> out = update.step(batch)
        >>> bool(0 < out["kl"] <= 1.5 * 0.01), bool(out["improvement"] > 0)
        (True, True)
    """

    def __init__(
        self,
        loss: ReinforceLoss,
        *,
        max_kl: float = 0.01,
        damping: float = 0.1,
        cg_iters: int = 10,
        fisher: Literal["exact", "kfac"] = "exact",
        fisher_fraction: float = 1.0,
        line_search: bool = True,
        backtracks: int = 10,
        backtrack_ratio: float = 0.8,
        accept_ratio: float = 0.1,
        kl_tolerance: float = 1.5,
    ) -> None:
        if not isinstance(loss, ReinforceLoss):
            raise TypeError(
                f"NaturalGradient updates the policy of an rl_pg.ReinforceLoss, got "
                f"{type(loss).__name__}."
            )
        self.loss = loss
        self.max_kl = check_real("max_kl", max_kl, low=0, low_open=True)
        self.damping = check_real("damping", damping, low=0)
        self.cg_iters = check_int("cg_iters", cg_iters, low=1)
        self.fisher = check_choice("fisher", fisher, ("exact", "kfac"))
        if fisher == "kfac" and damping == 0:
            raise ValueError(
                "fisher='kfac' needs damping > 0: its factors are inverted, and a "
                "softmax's are singular (its logits can all shift together)."
            )
        self.fisher_fraction = check_real(
            "fisher_fraction", fisher_fraction, low=0, low_open=True, high=1
        )
        self.line_search = check_bool("line_search", line_search)
        self.backtracks = check_int("backtracks", backtracks, low=1)
        self.backtrack_ratio = check_real(
            "backtrack_ratio", backtrack_ratio, low=0, low_open=True, high=1, high_open=True
        )
        self.accept_ratio = check_real("accept_ratio", accept_ratio, low=0, high=1)
        self.kl_tolerance = check_real("kl_tolerance", kl_tolerance, low=1)
        self.parameters = [p for p in _policy_parameters(loss) if p.requires_grad]
        if loss.has_critic:
            shared = {p.data_ptr() for p in self.parameters} & {
                p.data_ptr() for p in _critic_parameters(loss)
            }
            if shared:
                raise ValueError(
                    f"The critic shares {len(shared)} parameter tensor(s) with the policy: a "
                    f"natural step moves the policy alone, and would move the critic with "
                    f"it. Give the critic its own network (rl_pg.models.mlp_actor_critic "
                    f"builds two), or update both with an ordinary optimiser."
                )
        self._layers = (
            linear_layers(loss.actor_network, self.parameters) if fisher == "kfac" else None
        )

    def direction(
        self,
        tensordict: TensorDictBase,
        weights: torch.Tensor | None = None,
        valid: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The natural gradient `F⁻¹ g` of this batch and the gradient `g` itself, flat
        (the parameters in ``self.parameters``' order), both ascent directions of the
        policy objective. ``weights`` and ``valid`` come from the loss's
        ``policy_weights`` (computed here when not given, which takes the batch into
        the loss's state)."""
        if weights is None:
            weights, valid = self.loss.policy_weights(tensordict)
        _, _, gradient, factors, _ = self._first_order(tensordict, weights, valid)
        direction, _ = self._solve(tensordict, valid, gradient, factors)
        return direction, gradient

    def _first_order(self, tensordict, weights, valid):
        """The policy terms before the step, their objective, its ascent gradient and,
        with K-FAC, the Kronecker factors and the policy's distribution, taken from the
        same forward pass."""
        dist = None
        if self.fisher == "kfac":
            with recording(self._layers) as seen:
                dist = self._dist(tensordict)
            terms = self.loss.policy_loss(tensordict, weights, valid, dist=dist)
        else:
            terms = self.loss.policy_loss(tensordict, weights, valid)
        objective = terms["loss_actor"] + terms.get("loss_entropy", 0.0)
        gradient = self._gradient(objective, keep_graph=self.fisher == "kfac")
        factors = None
        if self.fisher == "kfac":
            rows = self._fisher_rows(tensordict, valid)
            factors = kronecker_factors(self._layers, seen, dist, tensordict.batch_size, rows)
        return terms, objective, gradient, factors, dist

    def _solve(self, tensordict, valid, gradient, factors) -> tuple[torch.Tensor, float]:
        """The natural direction ``x`` and its quadratic ``xᵀ F x`` (undamped)."""
        if factors is not None:
            return kfac_solve(factors, self._layers, gradient, self.damping)
        product = self._fisher_product(tensordict, valid)
        direction = conjugate_gradient(product, gradient, self.cg_iters)
        return direction, float(
            direction @ product(direction) - self.damping * direction @ direction
        )

    def step(
        self,
        tensordict: TensorDictBase,
        weights: torch.Tensor | None = None,
        valid: torch.Tensor | None = None,
    ) -> TensorDictBase:
        """One natural-gradient step on ``tensordict``: the policy's parameters move in
        place. ``weights`` and ``valid``: the loss's ``policy_weights`` of this batch,
        when the caller took them already (with ``keep_value=True``, say, to fit the
        critic on the value they computed); computed here when not given.

        Returns:
            A ``TensorDict`` of batch size ``[]``: ``loss_actor`` (and ``loss_entropy``,
            ``entropy``) before the step, detached; ``kl``, the measured KL divergence
            between the policy before and after it (0 when no step was taken);
            ``step_fraction``, the share of the full step taken (0 when the line search
            refused every trial); ``expected_improvement`` and ``improvement``, of the
            policy loss, predicted by the linear model for the full step and measured
            for the step taken.
        """
        loss = self.loss
        if weights is None:
            if valid is not None:
                raise ValueError(
                    "NaturalGradient.step got valid without weights: pass both as "
                    "loss.policy_weights(batch) gave them, or neither."
                )
            weights, valid = loss.policy_weights(tensordict)
        elif valid is None and loss.valid_steps(tensordict) is not None:
            raise ValueError(
                "NaturalGradient.step got weights without valid for a batch with steps to "
                "leave out (padding, greedy episodes): pass the valid that "
                "loss.policy_weights(batch) gave with them."
            )
        before, objective, gradient, factors, old = self._first_order(tensordict, weights, valid)
        # The step is sized by the Fisher itself, without the damping, so that the
        # quadratic model of its KL divergence is max_kl.
        direction, quadratic = self._solve(tensordict, valid, gradient, factors)
        if old is None:  # (K-FAC's pass gave it: read without a graph below)
            old = self._old_policy(tensordict)
        out = {name: value.detach() for name, value in before.items()}
        start = torch.cat([p.detach().reshape(-1) for p in self.parameters])
        full = direction * math.sqrt(2 * self.max_kl / quadratic) if quadratic > 0 else None
        expected = float(gradient @ full) if full is not None else 0.0
        fraction, improvement, kl = 0.0, 0.0, 0.0
        trials = self.backtracks if self.line_search else 1
        for trial in range(trials if full is not None and expected > 0 else 0):
            candidate = self.backtrack_ratio**trial
            self._assign(start + candidate * full)
            with torch.no_grad():
                new = self._dist(tensordict)
                after = loss.policy_loss(tensordict, weights, valid, dist=new)
                gained = float(objective - after["loss_actor"] - after.get("loss_entropy", 0.0))
                moved = float(self._kl(old, new, tensordict, valid))
            if not self.line_search or (
                moved <= self.kl_tolerance * self.max_kl
                and gained >= self.accept_ratio * candidate * expected
            ):
                fraction, improvement, kl = candidate, gained, moved
                break
        else:
            self._assign(start)  # no trial was accepted: the policy stays where it was
        out.update(
            kl=torch.tensor(kl),
            step_fraction=torch.tensor(fraction),
            expected_improvement=torch.tensor(expected),
            improvement=torch.tensor(improvement),
        )
        return TensorDict(out, batch_size=[])

    def _gradient(self, objective: torch.Tensor, keep_graph: bool = False) -> torch.Tensor:
        """The ascent direction of the policy objective (minus the loss's gradient)."""
        grads = torch.autograd.grad(
            objective, self.parameters, allow_unused=True, retain_graph=keep_graph
        )
        return -torch.cat(
            [
                (g if g is not None else torch.zeros_like(p)).reshape(-1)
                for g, p in zip(grads, self.parameters, strict=True)
            ]
        )

    def _old_policy(self, tensordict: TensorDictBase):
        with torch.no_grad():
            return self._dist(tensordict)

    def _dist(self, tensordict: TensorDictBase):
        # The loss's actor network holds the parameters being moved (the same tensors as
        # the loss's functional parameters): its distribution follows them.
        return self.loss.actor_network.get_dist(tensordict)

    def _kl(self, old, new, tensordict: TensorDictBase, valid) -> torch.Tensor:
        kl = kl_per_step(old, new, tensordict, action_key=self._action_key)
        return masked_mean(kl, valid)

    @property
    def _action_key(self):
        return self.loss.tensor_keys.action

    def _fisher_product(self, tensordict: TensorDictBase, valid):
        """``v ↦ (F + λI) v`` for the policy's Fisher on (a share of) the batch's states."""
        steps = self._fisher_steps(tensordict, valid)
        return fisher_product(
            steps, self.loss.actor_network, self._action_key, self.parameters, self.damping
        )

    def _fisher_rows(self, tensordict: TensorDictBase, valid) -> torch.Tensor | slice:
        """The steps the Fisher is taken on, as an index into the flat batch: every
        ``1 / fisher_fraction``-th step the loss learns from, in the batch's order (a
        slice, which indexes without a copy, when every step counts)."""
        stride = max(1, round(1 / self.fisher_fraction))
        if valid is None:
            return slice(None, None, stride)
        index = torch.arange(tensordict.numel(), device=tensordict.device)
        return index[valid.reshape(-1)][::stride]

    def _fisher_steps(self, tensordict: TensorDictBase, valid) -> TensorDictBase:
        """The steps the Fisher is taken on (``_fisher_rows``), flat."""
        return tensordict.reshape(-1)[self._fisher_rows(tensordict, valid)]

    def _assign(self, flat: torch.Tensor) -> None:
        with torch.no_grad():
            offset = 0
            for p in self.parameters:
                p.copy_(flat[offset : offset + p.numel()].view_as(p))
                offset += p.numel()


def _policy_parameters(loss: ReinforceLoss) -> list[torch.Tensor]:
    if loss.functional:
        return list(loss.actor_network_params.values(True, True))
    return list(loss.actor_network.parameters())


def _critic_parameters(loss: ReinforceLoss) -> list[torch.Tensor]:
    if loss.functional:
        return list(loss.critic_network_params.values(True, True))
    return list(loss.critic_network.parameters())
