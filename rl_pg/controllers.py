"""Coefficients that follow a measurement at every update: the learning rate by the
KL divergence the update caused, the entropy bonus by an entropy target.

Both keep a quantity that matters for the policy where it should be, instead of a
schedule fixed in advance: how far an update moves the policy (a learning rate that
suits the first updates is too large near a confident policy, and the reverse), and
how random the policy stays (an entropy bonus that keeps one task exploring lets
another collapse, or never commit).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from rl_pg._checks import check_real
from rl_pg.loss import ReinforceLoss
from rl_pg.policy_kl import kl_per_step, masked_mean

__all__ = ["EntropyTarget", "KLStepSize"]


class KLStepSize:
    """Sets an optimiser's learning rate from the KL divergence each update causes.

    Before the update, ``before(batch)`` keeps the policy's distribution on the
    batch's states; after it, ``after(batch)`` measures `KL(π_before ‖ π_after)` there
    and sets the learning rate for the next update: divided by ``factor`` when the KL
    was above twice ``target_kl``, multiplied by it when below half (the adaptive rule
    of rl_games and of PPO with an adaptive KL, Schulman et al. 2017), within
    ``[lr_min, lr_max]``. Any ``torch.optim`` optimiser; the learning rate it holds is
    in its ``state_dict``, so a checkpoint keeps it. Several groups set change by one
    factor, so their rates keep their ratios (a larger step for some parameters stays
    larger); the bounds hold the first group's rate.

    Args:
        optimizer (torch.optim.Optimizer): the optimiser of the policy.
        actor (TensorDictModuleBase): the policy (``get_dist``).

    Keyword Args:
        target_kl (float): the KL divergence per update aimed at. Defaults to ``0.01``.
        factor (float): the change of the learning rate per update, ``> 1``.
            Defaults to ``1.5``.
        lr_min (float): the lowest learning rate. Defaults to ``1e-6``.
        lr_max (float): the highest learning rate. Defaults to ``1.0``.
        groups (Sequence[int], optional): the optimiser's parameter groups to set (the
            policy's, when a critic shares the optimiser). Defaults to ``None``: all.
            The first one named is the one ``lr_min`` and ``lr_max`` bound.
        action_key (NestedKey): the stored actions (for policies without a closed-form
            KL). Defaults to ``"action"``.

    Raises:
        ValueError: an argument out of range; ``after`` without ``before``.

    Examples:
        >>> import torch
        >>> from rl_pg.controllers import KLStepSize
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor
        >>> from rl_pg import ReinforceLoss
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> env = GridWorldEnv(batch_size=8, max_steps=20)
        >>> actor = mlp_actor(env, hidden=(16,))
        >>> loss = ReinforceLoss(actor)
        >>> optimizer = torch.optim.Adam(loss.parameters(), lr=1.0)
        >>> step_size = KLStepSize(optimizer, actor, target_kl=0.01)
        >>> batch = env.rollout(20, actor, break_when_all_done=True)
        >>> step_size.before(batch)
        >>> loss(batch)["loss_actor"].backward()
        >>> optimizer.step()
        >>> out = step_size.after(batch)
        >>> bool(out["kl"] > 0.02), optimizer.param_groups[0]["lr"]  # too far: smaller
        (True, 0.6666666666666666)
    """

    def __init__(
        self,
        optimizer: torch.optim.Optimizer,
        actor: TensorDictModuleBase,
        *,
        target_kl: float = 0.01,
        factor: float = 1.5,
        lr_min: float = 1e-6,
        lr_max: float = 1.0,
        groups: Sequence[int] | None = None,
        action_key="action",
    ) -> None:
        if not isinstance(optimizer, torch.optim.Optimizer):
            raise TypeError(
                f"optimizer must be a torch.optim.Optimizer, got {type(optimizer).__name__}."
            )
        if not hasattr(actor, "get_dist"):
            raise TypeError(
                f"actor must be a probabilistic policy with get_dist() (e.g. a "
                f"ProbabilisticActor), got {type(actor).__name__}."
            )
        self.optimizer, self.actor = optimizer, actor
        self.target_kl = check_real("target_kl", target_kl, low=0, low_open=True)
        self.factor = check_real("factor", factor, low=1, low_open=True)
        self.lr_min = check_real("lr_min", lr_min, low=0, low_open=True)
        self.lr_max = check_real("lr_max", lr_max, low=self.lr_min)
        count = len(optimizer.param_groups)
        self.groups = list(range(count)) if groups is None else list(groups)
        if not self.groups or any(
            isinstance(g, bool) or not isinstance(g, int) or not 0 <= g < count for g in self.groups
        ):
            raise ValueError(
                f"groups must name the optimiser's parameter groups (0 to {count - 1}), got "
                f"{groups!r}."
            )
        self.action_key = action_key
        self._before = None

    def before(self, tensordict: TensorDictBase) -> None:
        """Keeps the policy's distribution on ``tensordict``'s states, before the update."""
        with torch.no_grad():
            self._before = self.actor.get_dist(tensordict)

    def after(
        self, tensordict: TensorDictBase, valid: torch.Tensor | None = None
    ) -> dict[str, float]:
        """Measures the update's KL divergence on ``tensordict`` (the ``valid`` steps)
        and sets the next learning rate.

        Returns:
            ``{"kl": ..., "lr": ...}``: the KL divergence measured, the learning rate set
            (of the first group set).
        """
        if self._before is None:
            raise ValueError(
                "KLStepSize.after measures the KL divergence from the policy kept by "
                "before(batch): call before(batch) ahead of the update."
            )
        with torch.no_grad():
            after = self.actor.get_dist(tensordict)
            kl = float(
                masked_mean(
                    kl_per_step(self._before, after, tensordict, action_key=self.action_key),
                    valid,
                )
            )
        self._before = None
        if math.isnan(kl):
            raise ValueError(
                "The update's KL divergence is nan: the policy's outputs are not finite "
                "after the update (its weights diverged)."
            )
        # An infinite KL is a step so large that the new policy gives some action the old
        # one could take no probability at all: far above the target, like any large KL.
        change = 1.0
        if kl > 2 * self.target_kl:
            change = 1 / self.factor
        elif kl < self.target_kl / 2:
            change = self.factor
        groups = self.optimizer.param_groups
        first = groups[self.groups[0]]["lr"]
        change = min(max(first * change, self.lr_min), self.lr_max) / first
        for index in self.groups:
            groups[index]["lr"] *= change
        return {"kl": kl, "lr": self.optimizer.param_groups[self.groups[0]]["lr"]}


class EntropyTarget:
    """Holds the policy's entropy at a target with a learned entropy coefficient.

    The coefficient `β` of the loss's entropy term follows the entropy each update
    measures, `β ← max(β + lr · (H_target − H), min_coeff)`: the gradient step of a
    Lagrange multiplier on the constraint `H = H_target` (SAC learns its temperature
    the same way, Haarnoja et al. 2018, there in log space to keep it positive). Below
    the target the bonus grows; above it the bonus shrinks, to 0 with the default
    ``min_coeff`` (the target is then a floor: the policy's own learning lowers its
    entropy) and, with a negative ``min_coeff``, on into a penalty that brings the
    entropy down to the target. Where the policy holds the target, the coefficient
    stops moving. ``state_dict`` holds `β`, for checkpoints.

    Args:
        loss (ReinforceLoss): built with an ``entropy_coeff`` (the starting `β`):
            ``update`` sets ``loss.entropy_coeff``.

    Keyword Args:
        target (float): the entropy to hold, in nats (for ``n`` actions at most
            ``log n``).
        lr (float): the change of `β` per nat of difference, per update. Defaults to
            ``0.001``.
        min_coeff (float): the lowest `β`; negative lets it become a penalty.
            Defaults to ``0.0``.

    Raises:
        ValueError: a loss without an entropy term (``entropy_coeff=None``), a
            non-finite ``target`` or ``min_coeff``, or ``lr <= 0``.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> from rl_pg import ReinforceLoss
        >>> from rl_pg.controllers import EntropyTarget
        >>> actor = ProbabilisticActor(
        ...     TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"]),
        ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
        ... )
        >>> loss = ReinforceLoss(actor, entropy_coeff=0.01)
        >>> controller = EntropyTarget(loss, target=0.5, lr=0.01, min_coeff=-0.05)
        >>> round(controller.update(0.3), 6)  # below the target: the bonus grows
        0.012
        >>> round(controller.update(2.0), 6)  # far above: it turns into a penalty
        -0.003
        >>> round(loss.entropy_coeff, 6)
        -0.003
    """

    def __init__(
        self, loss: ReinforceLoss, *, target: float, lr: float = 0.001, min_coeff: float = 0.0
    ) -> None:
        if not isinstance(loss, ReinforceLoss):
            raise TypeError(f"loss must be an rl_pg.ReinforceLoss, got {type(loss).__name__}.")
        if loss.entropy_coeff is None:
            raise ValueError(
                "EntropyTarget learns the loss's entropy coefficient, but the loss has "
                "entropy_coeff=None (no entropy term): build it with the starting "
                "coefficient, e.g. ReinforceLoss(actor, entropy_coeff=0.01)."
            )
        self.loss = loss
        self.target = check_real("target", target)
        self.lr = check_real("lr", lr, low=0, low_open=True)
        self.min_coeff = check_real("min_coeff", min_coeff)
        self.coeff = max(float(loss.entropy_coeff), self.min_coeff)
        loss.entropy_coeff = self.coeff

    def update(self, entropy: float | torch.Tensor) -> float:
        """Takes the entropy the last batch measured (the loss's ``"entropy"`` output)
        and sets ``loss.entropy_coeff``; returns it."""
        entropy = float(entropy)
        if not math.isfinite(entropy):
            raise ValueError(f"EntropyTarget.update needs a finite entropy, got {entropy}.")
        self.coeff = max(self.coeff + self.lr * (self.target - entropy), self.min_coeff)
        self.loss.entropy_coeff = self.coeff
        return self.coeff

    def state_dict(self) -> dict[str, float]:
        """``{"coeff": β}``."""
        return {"coeff": self.coeff}

    def load_state_dict(self, state_dict: dict[str, float]) -> None:
        """Restores `β` and sets the loss's coefficient to it."""
        self.coeff = float(check_real("state_dict['coeff']", state_dict["coeff"]))
        self.loss.entropy_coeff = self.coeff
