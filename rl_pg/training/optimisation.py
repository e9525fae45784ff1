"""How the policy learns from a batch: the loss, the optimiser, one update."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from rl_pg.action_stats import means_beyond_bounds
from rl_pg.loss import ReinforceLoss
from rl_pg.natural_gradient import NaturalGradient
from rl_pg.normalization import popart_output, update_running_norms
from rl_pg.training.learning import LearningSettings, LossSettings, OptimiserSettings
from rl_pg.training.metrics import EpisodeReturns

__all__ = [
    "NaturalOptimiser",
    "TrainingDiverged",
    "entropy_coeff",
    "learning_rate",
    "make_loss",
    "make_optimizer",
    "scale_rewards",
    "update",
    "warm_up",
]


class TrainingDiverged(RuntimeError):
    """The loss or its gradient became non-finite; the last good checkpoint is kept."""


def make_loss(settings: LearningSettings, actor, critic) -> ReinforceLoss:
    """The run's loss; with ``value_norm='popart'`` the critic's output layer becomes a
    [`PopArt`][rl_pg.normalization.PopArt] one first (so build the critic, make the loss,
    then load weights)."""
    value_norm = None
    if settings.value_norm == "popart":
        if critic is None:
            raise ValueError(
                "--value-norm popart normalises a critic's values, but the recipe's models "
                "have no critic: drop --value-norm, or use a recipe with a critic."
            )
        value_norm = popart_output(critic)
    loss = ReinforceLoss(
        actor,
        critic,
        baseline=settings.baseline,
        baseline_rate=settings.baseline_rate,
        entropy_coeff=settings.entropy_coeff or None,
        critic_coeff=settings.critic_coeff,
        normalize_advantage=settings.normalize_advantage,
        group_scale=settings.group_scale,
        value_norm=value_norm,
        loss_critic_type="l2",
        # The collector runs the actor itself: keep one set of parameters.
        functional=False,
    )
    if settings.returns == "gae":
        loss.make_value_estimator("gae", gamma=settings.gamma, lmbda=settings.gae_lambda)
    else:
        loss.make_value_estimator(settings.returns, gamma=settings.gamma)
    return loss


def warm_up(loss: ReinforceLoss, env: EnvBase, device: torch.device) -> None:
    """Compiles (or loads from numba's cache) the numba kernels before the clock starts:
    the loss's return kernel and the training-episode returns' sums.

    The first calls cost up to a second; timing them would charge the training loop
    with set-up, as if timing ``import torch``.
    """
    fake = env.fake_tensordict()
    batch = torch.stack([fake, fake], dim=-1).to(device)
    with torch.no_grad():
        for _ in range(2):  # the second call still pays for thread-pool start-up
            loss.value_estimator(batch)
    EpisodeReturns.warm_up()


class NaturalOptimiser:
    """The run's optimiser with ``optimizer='natural'``: natural-gradient steps of KL
    ``max_kl`` for the policy, solved with the Fisher ``fisher`` names
    ([`NaturalGradient`][rl_pg.natural_gradient.NaturalGradient]), and Adam for the
    critic (if any), at the run's learning rate.

    ``param_groups``, ``state_dict`` and ``load_state_dict`` are the critic's Adam's
    (the natural step keeps no state between updates)."""

    def __init__(self, settings: OptimiserSettings, loss: ReinforceLoss) -> None:
        self.natural = NaturalGradient(loss, max_kl=settings.max_kl, fisher=settings.fisher)
        self.critic = None
        if loss.has_critic:
            params = [p for p in loss.critic_network.parameters() if p.requires_grad]
            fused = {"fused": True} if _fused_kernels(params) else {}
            self.critic = torch.optim.Adam(
                params, lr=settings.lr, betas=(settings.adam_beta1, 0.999),
                weight_decay=settings.weight_decay, **fused,
            )  # fmt: skip

    @property
    def param_groups(self) -> list[dict]:
        return self.critic.param_groups if self.critic is not None else []

    def zero_grad(self, set_to_none: bool = True) -> None:
        if self.critic is not None:
            self.critic.zero_grad(set_to_none=set_to_none)

    def step(self) -> None:
        """The critic's step (the policy's is taken by ``natural.step``)."""
        if self.critic is not None:
            self.critic.step()

    def state_dict(self) -> dict:
        return {"critic": self.critic.state_dict() if self.critic is not None else None}

    def load_state_dict(self, state: dict) -> None:
        if self.critic is not None:
            self.critic.load_state_dict(state["critic"])


def make_optimizer(settings: OptimiserSettings, loss: ReinforceLoss):
    """The run's optimiser: Adam or SGD on both networks, or a
    [`NaturalOptimiser`][rl_pg.training.optimisation.NaturalOptimiser]."""
    if settings.optimizer == "natural":
        return NaturalOptimiser(settings, loss)
    params = [p for p in loss.parameters() if p.requires_grad]
    fused = {"fused": True} if _fused_kernels(params) else {}
    if settings.scale_lr_factor != 1:
        params = _scale_apart(loss, params, settings.scale_lr_factor, settings.lr)
    if settings.optimizer == "sgd":
        return torch.optim.SGD(params, lr=settings.lr, weight_decay=settings.weight_decay, **fused)
    return torch.optim.Adam(
        params,
        lr=settings.lr,
        betas=(settings.adam_beta1, 0.999),
        weight_decay=settings.weight_decay,
        **fused,
    )


def _scale_apart(loss: ReinforceLoss, params: list, factor: float, lr: float) -> list[dict]:
    """Two parameter groups: the Gaussian's state-independent scales at ``factor``
    times ``lr`` (``lr_factor`` in the group, which ``_set_lr`` keeps), the rest."""
    scales = {
        id(module.state_independent_scale)
        for module in loss.actor_network.modules()
        if isinstance(getattr(module, "state_independent_scale", None), nn.Parameter)
    }
    if not scales:
        raise ValueError(
            f"--scale-lr-factor {factor} sets the learning rate of a Gaussian policy's "
            f"learned scale, one per action dimension, but this policy has none (a "
            f"categorical or Beta policy, or a scale output by the network): drop the "
            f"flag, or build a Gaussian policy with a state-independent scale."
        )
    rest = [p for p in params if id(p) not in scales]
    scale = [p for p in params if id(p) in scales]
    return [{"params": rest}, {"params": scale, "lr": factor * lr, "lr_factor": factor}]


def learning_rate(settings: OptimiserSettings, frames: int, total_frames: int) -> float | None:
    """The learning rate of the update that follows ``frames`` of ``total_frames``
    environment steps, where a schedule moves it; None where nothing does: the rate the
    optimiser holds stays (the ``lr`` it was made with, or the rate ``lr_control='kl'``
    set)."""
    if settings.lr_schedule == "constant":
        return None
    return _scheduled(
        settings.lr, settings.lr_schedule, frames, total_frames, start=settings.lr_schedule_start
    )


def entropy_coeff(settings: LossSettings, frames: int, total_frames: int) -> float | None:
    """The entropy bonus of the update that follows ``frames`` of ``total_frames``
    environment steps
    (negative: a penalty, past the zero of a schedule to ``entropy_coeff_end < 0``;
    None with ``entropy_target``: the learned coefficient stays)."""
    if settings.entropy_target is not None:
        return None
    return _scheduled(
        settings.entropy_coeff,
        settings.entropy_schedule,
        frames,
        total_frames,
        end=settings.entropy_coeff_end,
        start=settings.entropy_schedule_start,
    )


def _scheduled(
    value: float,
    schedule: str,
    frames: int,
    total_frames: int,
    *,
    end: float = 0.0,
    start: float = 0.0,
) -> float:
    """``value`` at ``frames``: constant, or held until the fraction ``start`` of
    ``total_frames`` and then moved linearly to ``end`` at ``total_frames``.

    Computed from the frames seen so far, so a resumed run continues the same schedule.
    """
    if schedule == "linear":
        held = start * total_frames
        remaining = 1.0 - (frames - held) / (total_frames - held)
        return end + (value - end) * min(1.0, max(0.0, remaining))
    return value


def update(
    settings: LearningSettings,
    loss: ReinforceLoss,
    optimizer,
    batch: TensorDictBase,
    *,
    lr: float | None,
    entropy_coeff: float | None = None,
) -> dict:
    """One step of the optimiser on ``batch`` at learning rate ``lr`` (None: the rate
    the optimiser holds).

    ``entropy_coeff`` replaces the loss's entropy bonus from this update on (None keeps
    it); it takes effect only where the loss has one (``entropy_coeff > 0``).
    """
    if entropy_coeff is not None and loss.entropy_coeff is not None:
        loss.entropy_coeff = entropy_coeff
    if settings.reward_scale != 1.0:
        batch = scale_rewards(batch, settings.reward_scale, loss.tensor_keys.reward)
    if isinstance(optimizer, NaturalOptimiser):
        return _natural_update(settings, loss, optimizer, batch, lr)
    losses = loss(batch)
    total = sum(value for key, value in losses.items() if key.startswith("loss_"))
    _check_finite(total, f"The loss became {total.item()} ({_describe(losses)})")
    max_norm = settings.max_grad_norm if settings.max_grad_norm is not None else float("inf")
    grad_norm = _step(settings, loss, optimizer, total, lr, max_norm)
    metrics = {
        f"loss/{key[5:]}": value.item() for key, value in losses.items() if key.startswith("loss_")
    }
    metrics["train/grad_norm"] = grad_norm.item()
    return _after_step(settings, loss, optimizer, batch, losses, metrics, max_norm)


def _check_finite(value: torch.Tensor, what: str) -> None:
    if not torch.isfinite(value):
        raise TrainingDiverged(
            f"{what}; training stopped and the last good checkpoint was kept. Lower the "
            f"learning rate (--max-kl with --optimizer natural) or clip gradients."
        )


def _step(
    settings: OptimiserSettings, loss, optimizer, total: torch.Tensor, lr, max_norm: float
) -> torch.Tensor:
    """Back-propagates ``total``, clips the gradient of the optimiser's parameters and
    steps at ``lr``; returns the gradient norm before the clip."""
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    params = [p for group in optimizer.param_groups for p in group["params"]]
    if settings.clip_scope == "per_network":
        grad_norm = _clip_per_network(loss, params, max_norm)
    else:
        grad_norm = nn.utils.clip_grad_norm_(
            params, max_norm, foreach=_fused_kernels(params) or None
        )
    _check_finite(grad_norm, f"The gradient norm became {grad_norm.item()}")
    _set_lr(optimizer, lr)
    optimizer.step()
    return grad_norm


def _set_lr(optimizer, lr: float | None) -> None:
    if lr is not None:
        for group in optimizer.param_groups:
            group["lr"] = lr * group.get("lr_factor", 1.0)


def _after_step(
    settings: LearningSettings, loss, optimizer, batch, losses, metrics: dict, max_norm: float
) -> dict:
    """What follows either optimiser's step: the critic's further steps, the running
    norms, the diagnostics."""
    if settings.critic_steps > 1:
        critic_optimizer = (
            optimizer.critic if isinstance(optimizer, NaturalOptimiser) else optimizer
        )
        metrics["loss/value_fitted"] = _fit_critic(
            loss, critic_optimizer, batch, settings.critic_steps, max_norm
        )
    # Observation statistics move after the step: the batch was collected, and its
    # loss computed, with the ones before it.
    update_running_norms(loss, batch)
    for key in ("entropy", "advantage_mean", "advantage_std", "explained_variance", "baseline"):
        value = losses.get(key, None)
        if value is not None:
            metrics[f"train/{key}"] = value.item()
    beyond = means_beyond_bounds(loss.actor_network, batch)
    if beyond is not None:
        metrics["train/mean_beyond_bounds"] = beyond
    if optimizer.param_groups:
        metrics["train/lr"] = optimizer.param_groups[0]["lr"]
    if loss.entropy_coeff is not None:
        metrics["train/entropy_coeff"] = loss.entropy_coeff
    return metrics


def _natural_update(
    settings: LearningSettings, loss: ReinforceLoss, optimizer: NaturalOptimiser, batch, lr
) -> dict:
    """The policy's natural-gradient step, then the critic's Adam step on the value
    targets the step wrote into the batch."""
    # The critic's V(s_t) from the returns' pass is regressed as it is: one critic
    # call per batch, as in the Adam update.
    weights, valid, value = loss.policy_weights(batch, keep_value=True)
    out = optimizer.natural.step(batch, weights, valid)
    policy = out["loss_actor"] + out.get("loss_entropy", 0.0)
    _check_finite(policy, f"The policy loss became {policy.item()} ({_describe(out)})")
    metrics = {
        f"loss/{key[5:]}": value.item() for key, value in out.items() if key.startswith("loss_")
    }
    for key in ("kl", "step_fraction", "improvement"):
        metrics[f"train/{key}"] = out[key].item()
    max_norm = settings.max_grad_norm if settings.max_grad_norm is not None else float("inf")
    if optimizer.critic is not None:
        value_loss = loss.value_loss(batch, value=value)
        _check_finite(value_loss, f"The critic's loss became {value_loss.item()}")
        grad_norm = _step(settings, loss, optimizer, value_loss, lr, max_norm)
        metrics["loss/value"] = value_loss.item()
        metrics["train/grad_norm"] = grad_norm.item()
    return _after_step(settings, loss, optimizer, batch, out, metrics, max_norm)


def scale_rewards(batch: TensorDictBase, scale: float, reward_key: str = "reward"):
    """A shallow copy of ``batch`` whose ``("next", reward_key)`` is multiplied by
    ``scale``; ``batch`` itself, which the run's episode returns are counted from, is
    left as it is.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> batch = TensorDict({"next": {"reward": torch.tensor([[-300.0], [100.0]])}}, [2])
        >>> scale_rewards(batch, 0.01)["next", "reward"].squeeze(-1)
        tensor([-3.,  1.])
        >>> batch["next", "reward"].squeeze(-1)
        tensor([-300.,  100.])
    """
    scaled = batch.copy()
    scaled.set(("next", reward_key), batch.get(("next", reward_key)) * scale)
    return scaled


def _fit_critic(loss: ReinforceLoss, optimizer, batch, steps: int, max_norm: float) -> float:
    """The critic's further steps on the batch; returns its value loss after them.

    Only the critic's parameters get gradients here (a trunk it shares with the policy
    included), so the optimiser leaves the policy's own parameters alone.
    """
    params = [p for p in loss.critic_network.parameters() if p.requires_grad]
    for _ in range(steps - 1):
        value_loss = loss.value_loss(batch)
        if not torch.isfinite(value_loss):
            raise TrainingDiverged(
                f"The critic's loss became {value_loss.item()} while fitting it to the batch; "
                f"training stopped and the last good checkpoint was kept. Lower the learning "
                f"rate or --critic-steps."
            )
        optimizer.zero_grad(set_to_none=True)
        value_loss.backward()
        nn.utils.clip_grad_norm_(params, max_norm, foreach=_fused_kernels(params) or None)
        optimizer.step()
    with torch.no_grad():
        return loss.value_loss(batch).item()


def _clip_per_network(loss: ReinforceLoss, params, max_norm: float) -> torch.Tensor:
    """Clips the actor's gradient and the rest (the critic's, a trunk they share
    counted with the actor) each to ``max_norm``; returns the norm of both before."""
    actor = {id(p) for p in loss.actor_network.parameters()}
    groups = [[p for p in params if id(p) in actor], [p for p in params if id(p) not in actor]]
    norms = [
        nn.utils.clip_grad_norm_(group, max_norm, foreach=_fused_kernels(group) or None)
        for group in groups
        if group
    ]
    return torch.linalg.vector_norm(torch.stack(norms))


def _fused_kernels(params) -> bool:
    """Whether torch has multi-tensor kernels for ``params``' devices (CPU and CUDA):
    the optimiser step and the gradient clip then run one kernel over every tensor
    instead of a Python loop that costs more than a small network's arithmetic (torch
    picks them by default on CUDA only). Elsewhere torch's defaults apply."""
    return all(p.device.type in ("cpu", "cuda") for p in params)


def _describe(losses: TensorDictBase) -> str:
    return ", ".join(f"{k}={v.item():.4g}" for k, v in losses.items() if k.startswith("loss_"))
