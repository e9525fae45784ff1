"""What the run learns from: the returns that weight log pi, the loss and the
optimiser (the groups of settings a resume may not change), each with the rules among
its own fields; ``LearningSettings`` is the three at once, what an update reads.

    >>> from rl_pg.training import TrainConfig
    >>> from rl_pg.training.learning import LearningSettings
    >>> LearningSettings.of(TrainConfig(lr=5e-3, returns="discounted_return")).returns
    'discounted_return'
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal

from rl_pg._checks import Range
from rl_pg.groups import GROUP_BASELINES
from rl_pg.training.settings import Count, NonNegative, Positive, Settings

__all__ = [
    "LearningSettings",
    "LossSettings",
    "OptimiserSettings",
    "ReturnSettings",
    "check_kl_lr_range",
]


def check_kl_lr_range(lr_range: tuple[float, float], name: str = "lr_range") -> None:
    """Refuses bounds of a KL-set learning rate, as factors of the rate it starts at,
    that do not hold it: ``0 < low <= 1 <= high < inf``."""
    low, high = lr_range
    if not 0 < low <= 1 <= high < math.inf:
        raise ValueError(
            f"{name} {low} {high} bounds the rate --lr-control kl sets, as factors of "
            f"--lr, which it starts at: LOW must be in (0, 1] and HIGH finite and at "
            f"least 1 (e.g. 0.01 10)."
        )


@dataclass
class ReturnSettings(Settings, group="returns"):
    """What weights log pi: the return, its discount, the baseline."""

    returns: Literal["reward_to_go", "discounted_return", "gae"] = "reward_to_go"
    """Return that weights log pi. Reward-to-go (causality), the whole-episode return,
    or TorchRL's generalised advantage estimate (GAE; needs baseline='critic')."""
    gae_lambda: Annotated[float, Range(0, 1)] = 0.95
    """GAE's lambda, with returns='gae'. At 1 it is reward-to-go minus V, at 0 the
    one-step TD error."""
    gamma: Annotated[float, Range(0, 1)] = 0.99
    """Discount factor."""
    reward_scale: Positive = 1.0
    """Factor on the rewards, for learning only. It scales returns, advantages and the
    critic's targets; logged and evaluated returns are the environment's. Below 1 it
    keeps a critic's targets, and its share of a clipped gradient, in range where
    returns run into the hundreds. Unless normalize_advantage is set, the policy term
    shrinks with it too: multiply entropy_coeff by the same factor to keep the bonus's
    weight."""
    baseline: Literal[
        "none", "batch_mean", "running_mean", "ema", "critic", "leave_one_out", "group_mean",
        "greedy",
    ] = "critic"  # fmt: skip
    """What is subtracted from the return. The group baselines ('leave_one_out',
    'group_mean', 'greedy') compare each episode with the others of its group,
    group_size episodes started from one seed ('greedy': one more, played greedily);
    whole-episode batches of one episode per environment."""
    baseline_rate: Annotated[float, Range(0, 1, low_open=True)] = 0.01
    """Rate of the 'ema' baseline."""
    group_size: Annotated[int, Range(low=2)] = 4
    """Sampled episodes per group (the group baselines). The environments
    (episodes_per_batch of them, one episode each) form groups of group_size, plus one
    for the greedy episode with baseline 'greedy'."""
    group_scale: bool = False
    """Divide group advantages by their group's standard deviation. GRPO's
    normalisation; it biases the gradient (see the theory page)."""
    normalize_advantage: bool = False
    """Standardise the policy weights over each batch."""

    acts_only_with: ClassVar[dict[str, tuple[str, Any]]] = {
        "gae_lambda": ("returns", ("gae",)),
        "baseline_rate": ("baseline", ("ema",)),
        "group_size": ("baseline", GROUP_BASELINES),
    }

    @property
    def grouped(self) -> bool:
        """Whether the baseline compares episodes within groups."""
        return self.baseline in GROUP_BASELINES

    @property
    def group_width(self) -> int:
        """Episodes per group: ``group_size``, and the greedy one with 'greedy'."""
        return self.group_size + (self.baseline == "greedy")

    def check(self) -> None:
        if self.returns == "gae" and self.baseline != "critic":
            raise ValueError(
                f"--returns gae estimates advantages with a critic, but --baseline is "
                f"{self.baseline!r}: use --baseline critic, or --returns reward_to_go."
            )
        if self.group_scale and not self.grouped:
            raise ValueError(
                f"--group-scale divides group advantages by their group's standard "
                f"deviation, but --baseline is {self.baseline!r}: pick leave_one_out, "
                f"group_mean or greedy, or use --normalize-advantage."
            )


@dataclass
class LossSettings(Settings, group="loss"):
    """The entropy bonus and the critic's part of the loss."""

    entropy_coeff: NonNegative = 0.0
    """Entropy bonus weight."""
    entropy_schedule: Literal["constant", "linear"] = "constant"
    """'linear': move the bonus to entropy_coeff_end by the end. It moves from
    entropy_coeff at frame 0 (or from entropy_schedule_start on) to entropy_coeff_end at
    total_frames, as lr_schedule decays the learning rate."""
    entropy_coeff_end: float = 0.0
    """Where the 'linear' entropy schedule ends. Below 0 the bonus turns into a penalty
    on entropy once it crosses 0, which drives a policy that stays stochastic towards
    the deterministic one a greedy evaluation plays (needs entropy_coeff > 0)."""
    entropy_schedule_start: Annotated[float, Range(0, 1, high_open=True)] = 0.0
    """Share of the run before the entropy schedule starts. During this fraction of
    total_frames the 'linear' schedule holds at entropy_coeff, then moves to
    entropy_coeff_end (0: it moves from frame 0). With lr_schedule 'linear' the learning
    rate has decayed by then, so a late schedule moves the policy less than the same
    change early would."""
    entropy_target: float | None = None
    """Entropy (nats) to hold with a learned entropy coefficient (None: off). The
    coefficient starts at entropy_coeff (> 0) and follows each update's entropy
    (rl_pg.controllers.EntropyTarget), down to entropy_coeff_min; without it the
    coefficient is entropy_coeff, or its schedule."""
    entropy_target_lr: Positive = 0.001
    """Step of the learned entropy coefficient. Per update and per nat between the
    measured entropy and entropy_target."""
    entropy_coeff_min: float = 0.0
    """Lowest learned entropy coefficient (entropy_target). Below 0 the coefficient may
    turn into a penalty, which holds the entropy down to the target as well as up."""
    critic_coeff: NonNegative = 1.0
    """Value-loss weight."""
    value_norm: Literal["none", "popart"] = "none"
    """'popart': the critic learns standardised values. Its output layer answers at the
    rewards' scale (rl_pg.normalization.PopArt; statistics from each batch's value
    targets), and its loss is taken in those units. A critic then fits returns in the
    hundreds as quickly as returns near one, while the policy's weights stay at the
    rewards' scale (unlike reward_scale, which scales both)."""
    critic_steps: Count = 1
    """Gradient steps of the critic on each batch (the policy takes one). The first is
    taken with the policy's; more fit the baseline to the batch's returns, as
    "vanilla" policy gradient fits its value function (needs baseline='critic')."""

    acts_only_with: ClassVar[dict[str, tuple[str, Any]]] = {
        "entropy_target_lr": ("entropy_target", "not None"),
    }

    def check(self) -> None:
        if self.entropy_coeff_end != 0 and (
            self.entropy_schedule != "linear" or self.entropy_coeff == 0
        ):
            raise ValueError(
                f"--entropy-coeff-end {self.entropy_coeff_end} is where the linear entropy "
                "schedule ends: add --entropy-schedule linear and a positive --entropy-coeff "
                "(the bonus it starts from), or pass --entropy-coeff-end 0."
            )
        if self.entropy_schedule_start != 0 and self.entropy_schedule != "linear":
            raise ValueError(
                f"--entropy-schedule-start {self.entropy_schedule_start} is where the linear "
                "entropy schedule starts moving: add --entropy-schedule linear, or pass "
                "--entropy-schedule-start 0."
            )
        if self.entropy_coeff_min != 0 and self.entropy_target is None:
            raise ValueError(
                f"--entropy-coeff-min {self.entropy_coeff_min} bounds the learned entropy "
                f"coefficient: add --entropy-target, or leave --entropy-coeff-min at 0."
            )
        if self.entropy_target is not None and (
            self.entropy_coeff <= 0 or self.entropy_schedule != "constant"
        ):
            raise ValueError(
                f"--entropy-target {self.entropy_target} learns the entropy coefficient from "
                f"--entropy-coeff (its start, > 0) without a schedule: set a positive "
                f"--entropy-coeff and leave --entropy-schedule constant."
            )


@dataclass
class OptimiserSettings(Settings, group="optimiser"):
    """The optimiser and its step size."""

    optimizer: Literal["adam", "sgd", "natural"] = "adam"
    """Optimiser of actor and critic. With 'natural' the policy takes natural-gradient
    steps of KL max_kl (rl_pg.natural_gradient.NaturalGradient) and the critic Adam
    steps at lr."""
    max_kl: Positive = 0.01
    """KL divergence of each natural-gradient step (optimizer 'natural')."""
    fisher: Literal["exact", "kfac"] = "exact"
    """How the natural step solves with the policy's Fisher (optimizer 'natural').
    'exact': conjugate gradient on Fisher-vector products; 'kfac': a Kronecker-factored
    Fisher per linear layer, inverted in closed form (cheaper, approximate)."""
    adam_beta1: Annotated[float, Range(0, 1, high_open=True)] = 0.9
    """Adam's first-moment decay. Each step follows an average of about 1 / (1 -
    adam_beta1) batches' gradients. Where one batch's gradient is mostly noise (gradient
    noise scale far above the batch: rl-pg lab variance), a longer average keeps the
    signal and takes out more of the noise."""
    lr: Positive = 1e-3
    """Learning rate."""
    lr_schedule: Literal["constant", "linear"] = "constant"
    """'linear': decay the learning rate to 0 by the end. It goes from lr at frame 0 to
    0 at total_frames (set before each update from the frames seen so far, so a resumed
    run continues the same schedule; raising total_frames on resume stretches what is
    left of it)."""
    lr_schedule_start: Annotated[float, Range(0, 1, high_open=True)] = 0.0
    """Share of the run before the learning rate decays. During this fraction of
    total_frames the 'linear' rate holds at lr, then decays to 0 at total_frames (0: it
    decays from frame 0). A late decay keeps the constant rate's progress and then takes
    the noise of the last updates out of the weights that are deployed."""
    lr_control: Literal["none", "kl"] = "none"
    """'kl': set the learning rate from each update's KL divergence. It starts at lr and
    is divided by 1.5 after an update above twice target_kl, multiplied by 1.5 after one
    below half of it (rl_pg.controllers.KLStepSize)."""
    target_kl: Positive = 0.01
    """KL divergence per update that lr_control 'kl' aims at."""
    kl_lr_range: tuple[float, float] = (0.01, 10.0)
    """With lr_control 'kl': the rate's bounds, as factors of lr (LOW HIGH). The upper
    one keeps a run of small KLs from growing the rate to where one update wrecks the
    policy."""
    scale_lr_factor: Positive | None = 1.0
    """A Gaussian scale's rate, times lr (None: the recipe's choice).
    For a policy with one scale per action dimension, the same in every state (its own
    parameter group; the ratio holds through lr_schedule and lr_control). Its gradient
    changes sign from batch to batch, so at the rate of the rest the scale barely
    moves from where it starts. None lets a recipe choose by its policy (its page says
    how; 1 where it does not)."""
    weight_decay: NonNegative = 0.0
    """L2 weight decay."""
    max_grad_norm: Positive | None = None
    """Gradient-norm clipping (None: no clipping)."""
    clip_scope: Literal["joint", "per_network"] = "joint"
    """Whose gradient norm max_grad_norm bounds. 'joint': the actor's and the critic's
    gradients together; 'per_network': each network's on its own, so that the critic's
    error (whose gradient can be tens of times the actor's) does not set the actor's
    step."""

    acts_only_with: ClassVar[dict[str, tuple[str, Any]]] = {
        "max_kl": ("optimizer", ("natural",)),
        "fisher": ("optimizer", ("natural",)),
        "target_kl": ("lr_control", ("kl",)),
        "kl_lr_range": ("lr_control", ("kl",)),
    }

    def check(self) -> None:
        if self.adam_beta1 != 0.9 and self.optimizer == "sgd":
            raise ValueError(
                f"--adam-beta1 {self.adam_beta1} sets Adam's gradient average, but "
                f"--optimizer is {self.optimizer!r}: use --optimizer adam, or leave "
                "--adam-beta1 at 0.9."
            )
        if self.fisher != "exact" and self.optimizer != "natural":
            raise ValueError(
                f"--fisher {self.fisher} sets how the natural-gradient step uses the policy's "
                f"Fisher: add --optimizer natural (got --optimizer {self.optimizer})."
            )
        if self.lr_control == "kl" and (
            self.optimizer == "natural" or self.lr_schedule != "constant"
        ):
            raise ValueError(
                f"--lr-control kl sets the learning rate from each update's KL divergence, "
                f"which --optimizer natural (its step is set by --max-kl) and --lr-schedule "
                f"linear also set: use one (got --optimizer {self.optimizer}, --lr-schedule "
                f"{self.lr_schedule}; --lr-control none turns the KL-set rate off where a "
                f"recipe has it on)."
            )
        if self.scale_lr_factor != 1 and self.optimizer == "natural":
            raise ValueError(
                f"--scale-lr-factor {self.scale_lr_factor} sets the learning rate of a "
                f"Gaussian policy's scale, but --optimizer natural has no learning rate (its "
                f"step is set by --max-kl): use --optimizer adam or sgd, or drop the flag."
            )
        check_kl_lr_range(self.kl_lr_range, "--kl-lr-range")
        if self.lr_schedule_start != 0 and self.lr_schedule != "linear":
            raise ValueError(
                f"--lr-schedule-start {self.lr_schedule_start} is where the linear learning "
                "rate schedule starts decaying: add --lr-schedule linear, or pass "
                "--lr-schedule-start 0."
            )


@dataclass
class LearningSettings(ReturnSettings, LossSettings, OptimiserSettings):
    """What the run learns from: the returns, the loss and the optimiser (the groups a
    resume may not change), which the update reads."""
