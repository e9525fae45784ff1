"""A policy's Fisher information, for natural-gradient steps: its products with a
vector (the Gauss-Newton form where the KL divergence has a closed form, the scores'
outer product otherwise), conjugate gradient on them, and K-FAC's Kronecker factors of
each linear layer, inverted in closed form."""

from __future__ import annotations

import contextlib
import math

import torch
from tensordict.nn import ProbabilisticTensorDictModule
from torch import nn

from rl_pg.policy_kl import has_closed_form_kl, kl_per_step, log_prob_per_step

__all__ = [
    "cholesky",
    "conjugate_gradient",
    "fisher_product",
    "flat",
    "gauss_newton_product",
    "kfac_solve",
    "kronecker_factors",
    "linear_layers",
    "recording",
    "score_product",
]


def fisher_product(steps, actor, action_key, params, damping: float):
    """``v ↦ (F + λI) v`` (λ the ``damping``) for the Fisher of ``actor``'s policy on
    the flat batch ``steps``, in the flat parameters ``params``: by the Gauss-Newton
    form where the distribution's KL divergence has a closed form, by the stored
    actions' scores otherwise."""
    head = actor.module[-1] if hasattr(actor, "get_dist_params") else None
    if isinstance(head, ProbabilisticTensorDictModule):
        with torch.no_grad():
            closed_form = has_closed_form_kl(actor.get_dist(steps[:1]))
        if closed_form:
            return gauss_newton_product(steps, actor, head, params, damping)
    return score_product(steps, actor, action_key, params, damping)


def gauss_newton_product(steps, actor, head, params, damping: float):
    """The Fisher as ``J^T H J``: ``J`` the Jacobian of the distribution's
    parameters (logits; location and scale) with respect to the policy's, ``H``
    the Hessian of the KL divergence in those parameters, on each step. At the
    current policy this is the Hessian of the KL divergence in the policy's
    parameters itself, at the cost of two back-propagations through the network
    per product (``J v`` by the double-backward trick)."""
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
    grad_kl = flat(torch.autograd.grad(kl, leaves, create_graph=True), leaves)
    dummies = [torch.zeros_like(value, requires_grad=True) for value in outputs]
    transposed = flat(
        torch.autograd.grad(
            outputs, params, grad_outputs=dummies, create_graph=True, allow_unused=True
        ),
        params,
    )

    def product(v: torch.Tensor) -> torch.Tensor:
        jv = flat(torch.autograd.grad(transposed @ v, dummies, retain_graph=True), dummies)
        hjv = torch.autograd.grad(grad_kl @ jv, leaves, retain_graph=True)
        fv = torch.autograd.grad(
            outputs, params, grad_outputs=hjv, retain_graph=True, allow_unused=True
        )
        return flat(fv, params).detach() + damping * v

    return product


def score_product(steps, actor, action_key, params, damping: float):
    """Without a closed-form KL: the mean outer product of the stored actions'
    scores, ``F v = J^T (J v) / N`` with ``J`` the Jacobian of their
    log-probabilities (``J v`` by the double-backward trick)."""
    new = actor.get_dist(steps)
    log_prob = log_prob_per_step(new, steps.get(action_key), steps.batch_size)
    dummy = torch.zeros_like(log_prob, requires_grad=True)
    transposed = flat(
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
        return flat(fv, params).detach() + damping * v

    return product


def flat(grads, params) -> torch.Tensor:
    return torch.cat(
        [
            (g if g is not None else torch.zeros_like(p)).reshape(-1)
            for g, p in zip(grads, params, strict=True)
        ]
    )


def linear_layers(actor, parameters: list[torch.Tensor]) -> list[tuple[nn.Linear, int, int | None]]:
    """The policy's ``nn.Linear`` layers with the offsets of their weight and bias in the
    flat parameter vector of ``parameters``; raises if a parameter is outside them."""
    offsets, offset = {}, 0
    for p in parameters:
        offsets[p.data_ptr()] = offset
        offset += p.numel()
    layers, covered = [], set()
    for module in actor.modules():
        if isinstance(module, nn.Linear) and module.weight.data_ptr() in offsets:
            bias = module.bias
            has_bias = bias is not None and bias.data_ptr() in offsets
            layers.append((module, offsets[module.weight.data_ptr()],
                           offsets[bias.data_ptr()] if has_bias else None))  # fmt: skip
            covered |= {module.weight.data_ptr()} | ({bias.data_ptr()} if has_bias else set())
    left = [tuple(p.shape) for p in parameters if p.data_ptr() not in covered]
    if left:
        raise ValueError(
            f"fisher='kfac' factors the Fisher of nn.Linear layers only, and the policy has "
            f"parameters of shapes {left} outside them (a Gaussian's learned scale, a "
            f"convolution, ...): use fisher='exact', which takes any policy."
        )
    return layers


@contextlib.contextmanager
def recording(layers):
    """Records each layer's input (detached) and output (in the graph) of the forward
    passes inside, in ``seen[layer]``."""
    seen: dict[nn.Linear, tuple[torch.Tensor, torch.Tensor]] = {}

    def keep(module, inputs, output):
        seen[module] = (inputs[0].detach(), output)

    hooks = [layer.register_forward_hook(keep) for layer, _, _ in layers]
    try:
        yield seen
    finally:
        for hook in hooks:
            hook.remove()


def kronecker_factors(layers, seen, dist, batch_size: torch.Size, rows: torch.Tensor | slice):
    """Each layer's ``A`` (second moment of its inputs, a 1 appended for a bias) and ``G``
    (of the gradient of ``log π(ã|s)`` at its outputs, ``ã`` sampled from ``dist``,
    one per step) over the flat batch's ``rows``, from the forward pass ``seen``
    recorded."""
    with torch.no_grad():
        sampled = dist.sample()
    scores = log_prob_per_step(dist, sampled, batch_size).reshape(-1)[rows]
    count = len(scores)
    score = scores.sum()
    outputs = [seen[layer][1] for layer, _, _ in layers]
    grads = torch.autograd.grad(score, outputs, allow_unused=True)
    factors = []
    for (layer, _, bias), output, grad in zip(layers, outputs, grads, strict=True):
        inputs = seen[layer][0].reshape(-1, layer.in_features)[rows]
        a = inputs.T @ inputs
        if bias is not None:  # the bias's input is a constant 1
            total = inputs.sum(0, keepdim=True)
            corner = total.new_full((1, 1), float(count))
            a = torch.cat([torch.cat([a, total.T], 1), torch.cat([total, corner], 1)], 0)
        grad = torch.zeros_like(output) if grad is None else grad
        grad = grad.detach().reshape(-1, layer.out_features)[rows]
        factors.append((a / count, grad.T @ grad / count))
    return factors


def kfac_solve(
    factors, layers, gradient: torch.Tensor, damping: float
) -> tuple[torch.Tensor, float]:
    """The damped K-FAC direction layer by layer, ``(G + γ_G I)⁻¹ ∇W (A + γ_A I)⁻¹``
    (the inverse of ``(A + γ_A I) ⊗ (G + γ_G I)``, whose damping terms stand for
    ``damping · I``) with ``γ_A γ_G = damping`` split by the factors' mean
    eigenvalues, and the
    direction's undamped quadratic ``Σ tr(Δᵀ G Δ A)``."""
    direction = torch.zeros_like(gradient)
    quadratic = gradient.new_zeros(())
    for (a, g), (layer, weight, bias) in zip(factors, layers, strict=True):
        size = layer.weight.numel()
        grad = gradient[weight : weight + size].view(layer.out_features, layer.in_features)
        if bias is not None:
            grad = torch.cat([grad, gradient[bias : bias + layer.out_features, None]], -1)
        split = math.sqrt(
            max(float(a.trace()) / len(a), 1e-30) / max(float(g.trace()) / len(g), 1e-30)
        )
        eye_a = torch.eye(len(a), dtype=a.dtype, device=a.device)
        eye_g = torch.eye(len(g), dtype=g.dtype, device=g.device)
        left = torch.cholesky_solve(grad, cholesky(g + math.sqrt(damping) / split * eye_g))
        step = torch.cholesky_solve(left.T, cholesky(a + math.sqrt(damping) * split * eye_a)).T
        quadratic = quadratic + (step * (g @ step @ a)).sum()
        direction[weight : weight + size] = step[:, : layer.in_features].reshape(-1)
        if bias is not None:
            direction[bias : bias + layer.out_features] = step[:, -1]
    return direction, float(quadratic)


def cholesky(matrix: torch.Tensor) -> torch.Tensor:
    factor, info = torch.linalg.cholesky_ex(matrix)
    if int(info):
        raise ValueError(
            "A Kronecker factor of the Fisher is not positive definite even with the "
            "damping (non-finite inputs or scores?): raise damping, or check the batch."
        )
    return factor


def conjugate_gradient(product, b: torch.Tensor, iters: int) -> torch.Tensor:
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
