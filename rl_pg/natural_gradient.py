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
forming `F` (Schulman et al. 2015, TRPO; Wu et al. 2017, ACKTR use the same step). An
optional backtracking line search shrinks the step until the measured KL is within
``kl_tolerance · δ`` and the loss improves by a share of what the linear model
predicted. One step per batch: REINFORCE's on-policy gradient, not PPO's reuse.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictModule

from rl_pg._checks import check_bool, check_int, check_real
from rl_pg.loss import ReinforceLoss
from rl_pg.policy_kl import has_closed_form_kl, kl_per_step, log_prob_per_step, masked_mean

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
    batch after ``step``); it must not share parameters with the policy.

    Args:
        loss (ReinforceLoss): the loss whose policy is updated.

    Keyword Args:
        max_kl (float): `δ`, the KL divergence a step aims at. Defaults to ``0.01``.
        damping (float): added to the Fisher's diagonal (`F + λI`), which keeps the
            solve stable where the Fisher is singular (a softmax's logits can all
            shift together). Defaults to ``0.1``.
        cg_iters (int): conjugate-gradient iterations. Defaults to ``10``.
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
            the policy.

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
        objective = self._objective(tensordict, weights, valid)
        gradient = self._gradient(objective)
        product = self._fisher_product(tensordict, valid)
        return _conjugate_gradient(product, gradient, self.cg_iters), gradient

    def step(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One natural-gradient step on ``tensordict``: the policy's parameters move in
        place.

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
        weights, valid = loss.policy_weights(tensordict)
        before = loss.policy_loss(tensordict, weights, valid)
        objective = before["loss_actor"] + before.get("loss_entropy", 0.0)
        gradient = self._gradient(objective)
        product = self._fisher_product(tensordict, valid)
        direction = _conjugate_gradient(product, gradient, self.cg_iters)
        old = self._old_policy(tensordict)
        # The step is sized by the Fisher itself, without the damping, so that the
        # quadratic model of its KL divergence is max_kl.
        quadratic = float(direction @ product(direction) - self.damping * direction @ direction)
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
                after = loss.policy_loss(tensordict, weights, valid)
                gained = float(objective - after["loss_actor"] - after.get("loss_entropy", 0.0))
                moved = float(self._kl(old, tensordict, valid))
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

    def _objective(self, tensordict, weights, valid) -> torch.Tensor:
        terms = self.loss.policy_loss(tensordict, weights, valid)
        return terms["loss_actor"] + terms.get("loss_entropy", 0.0)

    def _gradient(self, objective: torch.Tensor) -> torch.Tensor:
        """The ascent direction of the policy objective (minus the loss's gradient)."""
        grads = torch.autograd.grad(objective, self.parameters, allow_unused=True)
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

    def _kl(self, old, tensordict: TensorDictBase, valid) -> torch.Tensor:
        kl = kl_per_step(old, self._dist(tensordict), tensordict, action_key=self._action_key)
        return masked_mean(kl, valid)

    @property
    def _action_key(self):
        return self.loss.tensor_keys.action

    def _fisher_product(self, tensordict: TensorDictBase, valid):
        """``v ↦ (F + λI) v`` for the policy's Fisher on (a share of) the batch's states."""
        steps = self._fisher_steps(tensordict, valid)
        actor = self.loss.actor_network
        head = actor.module[-1] if hasattr(actor, "get_dist_params") else None
        if isinstance(head, ProbabilisticTensorDictModule):
            with torch.no_grad():
                closed_form = has_closed_form_kl(actor.get_dist(steps[:1]))
            if closed_form:
                return self._gauss_newton_product(steps, actor, head)
        return self._score_product(steps)

    def _fisher_steps(self, tensordict: TensorDictBase, valid) -> TensorDictBase:
        """The steps the Fisher is taken on: every ``1 / fisher_fraction``-th step the
        loss learns from, in the batch's order (flat)."""
        flat = tensordict.reshape(-1)
        index = torch.arange(flat.numel(), device=flat.device)
        if valid is not None:
            index = index[valid.reshape(-1)]
        stride = max(1, round(1 / self.fisher_fraction))
        return flat[index[::stride]]

    def _gauss_newton_product(self, steps, actor, head):
        """The Fisher as ``J^T H J``: ``J`` the Jacobian of the distribution's
        parameters (logits; location and scale) with respect to the policy's, ``H``
        the Hessian of the KL divergence in those parameters, on each step. At the
        current policy this is the Hessian of the KL divergence in the policy's
        parameters itself, at the cost of two back-propagations through the network
        per product (``J v`` by the double-backward trick)."""
        params, damping = self.parameters, self.damping
        out = actor.get_dist_params(steps)
        keys = [key for key in actor.dist_params_keys if out.get(key, None) is not None]
        outputs = [out.get(key) for key in keys]
        leaves = [value.detach().requires_grad_() for value in outputs]
        at = out.clone(False)
        for key, value in zip(keys, (value.detach() for value in outputs), strict=True):
            at.set(key, value)
        old = head.get_dist(at)
        for key, leaf in zip(keys, leaves, strict=True):
            at.set(key, leaf)
        kl = kl_per_step(old, head.get_dist(at), steps).mean()
        grad_kl = _flat(torch.autograd.grad(kl, leaves, create_graph=True), leaves)
        dummies = [torch.zeros_like(value, requires_grad=True) for value in outputs]
        transposed = _flat(
            torch.autograd.grad(
                outputs, params, grad_outputs=dummies, create_graph=True, allow_unused=True
            ),
            params,
        )

        def product(v: torch.Tensor) -> torch.Tensor:
            jv = _flat(torch.autograd.grad(transposed @ v, dummies, retain_graph=True), dummies)
            hjv = torch.autograd.grad(grad_kl @ jv, leaves, retain_graph=True)
            fv = torch.autograd.grad(
                outputs, params, grad_outputs=hjv, retain_graph=True, allow_unused=True
            )
            return _flat(fv, params).detach() + damping * v

        return product

    def _score_product(self, steps):
        """Without a closed-form KL: the mean outer product of the stored actions'
        scores, ``F v = J^T (J v) / N`` with ``J`` the Jacobian of their
        log-probabilities (``J v`` by the double-backward trick)."""
        params, damping = self.parameters, self.damping
        new = self._dist(steps)
        log_prob = log_prob_per_step(new, steps.get(self._action_key), steps.batch_size)
        dummy = torch.zeros_like(log_prob, requires_grad=True)
        transposed = _flat(
            torch.autograd.grad(
                log_prob, params, grad_outputs=dummy, create_graph=True, allow_unused=True
            ),
            params,
        )

        def product(v: torch.Tensor) -> torch.Tensor:
            (jv,) = torch.autograd.grad(transposed @ v, dummy, retain_graph=True)
            fv = torch.autograd.grad(
                log_prob, params, grad_outputs=jv / log_prob.numel(), retain_graph=True,
                allow_unused=True,
            )  # fmt: skip
            return _flat(fv, params).detach() + damping * v

        return product

    def _assign(self, flat: torch.Tensor) -> None:
        with torch.no_grad():
            offset = 0
            for p in self.parameters:
                p.copy_(flat[offset : offset + p.numel()].view_as(p))
                offset += p.numel()


def _flat(grads, params) -> torch.Tensor:
    return torch.cat(
        [
            (g if g is not None else torch.zeros_like(p)).reshape(-1)
            for g, p in zip(grads, params, strict=True)
        ]
    )


def _conjugate_gradient(product, b: torch.Tensor, iters: int) -> torch.Tensor:
    """An approximate solution of ``product(x) = b`` (a symmetric positive-definite
    operator) after ``iters`` conjugate-gradient iterations from 0."""
    x = torch.zeros_like(b)
    residual, direction = b.clone(), b.clone()
    squared = residual @ residual
    for _ in range(iters):
        if squared <= 1e-20:
            break
        image = product(direction)
        curvature = direction @ image
        if curvature <= 0:  # no positive curvature left along it (rounding): stop
            break
        alpha = squared / curvature
        x = x + alpha * direction
        residual = residual - alpha * image
        new_squared = residual @ residual
        direction = residual + (new_squared / squared) * direction
        squared = new_squared
    return x


def _policy_parameters(loss: ReinforceLoss) -> list[torch.Tensor]:
    if loss.functional:
        return list(loss.actor_network_params.values(True, True))
    return list(loss.actor_network.parameters())


def _critic_parameters(loss: ReinforceLoss) -> list[torch.Tensor]:
    if loss.functional:
        return list(loss.critic_network_params.values(True, True))
    return list(loss.critic_network.parameters())
