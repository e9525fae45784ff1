"""The settings of a training run: one dataclass, checked when it is made.

Every field declares its kind and bounds in its type (``Count``, ``Positive``,
``NonNegative``, ``Range``). A recipe's config subclasses ``TrainConfig``, declares the
fields it adds, and changes the defaults of inherited fields in its class statement,
without re-declaring them (their type, bounds and help text stay the base's)::

    @dataclass
    class Config(TrainConfig, lr=5e-3, total_frames=300_000):
        hidden: Count = 64
        '''Width of the hidden layers.'''
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import torch

from rl_pg._checks import Range, check_fields

__all__ = [
    "RESUMABLE_FIELDS",
    "Count",
    "DeviceUnavailable",
    "NonNegative",
    "Positive",
    "Range",
    "TrainConfig",
]

Count = Annotated[int, Range(low=1)]
"""An integer >= 1 (a config field type: the bound is checked when a config is made)."""
Positive = Annotated[float, Range(low=0, low_open=True)]
"""A finite number > 0."""
NonNegative = Annotated[float, Range(low=0)]
"""A finite number >= 0."""

RESUMABLE_FIELDS = frozenset(
    {
        "total_frames",
        "total_updates",
        "resume",
        "run_dir",
        "workers",
        "ray",
        "tensorboard",
        "wandb",
        "wandb_project",
        "wandb_mode",
        "mlflow",
        "mlflow_uri",
        "progress",
        "threads",
        "device",
        "keep_every",
        "grad_stats",
    }
)
"""Config fields that may change when a run is resumed; any other change is refused."""


class DeviceUnavailable(ValueError):
    """The device asked for is not one torch can use here (``--device cuda`` on a build
    or machine without CUDA)."""


@dataclass
class TrainConfig:
    """Settings of the training loop shared by every recipe."""

    groups: ClassVar[dict[str, tuple[str, tuple[str, ...]]]] = {
        "run": ("What to train for how long, where, on what.", (
            "seed", "total_frames", "total_updates", "run_dir", "resume", "device",
            "threads", "progress",
        )),
        "collection": ("How the batches are collected.", (
            "workers", "ray", "overlap", "batch_mode", "episodes_per_batch", "segment_length",
            "segments_late", "segments_late_start", "env_restart_interval",
        )),
        "returns": ("What weights log pi: the return, its discount, the baseline.", (
            "returns", "gae_lambda", "gamma", "reward_scale", "baseline", "baseline_rate",
            "group_size", "group_scale", "normalize_advantage",
        )),
        "loss": ("The entropy bonus and the critic's part of the loss.", (
            "entropy_coeff", "entropy_schedule", "entropy_coeff_end",
            "entropy_schedule_start", "entropy_target", "entropy_target_lr", "entropy_coeff_min",
            "critic_coeff",
            "value_norm", "critic_steps",
        )),
        "optimiser": ("The optimiser and its step size.", (
            "optimizer", "max_kl", "fisher", "adam_beta1", "lr", "lr_schedule",
            "lr_schedule_start", "lr_control", "target_kl", "kl_lr_range", "scale_lr_factor",
            "weight_decay",
            "max_grad_norm", "clip_scope",
        )),
        "evaluation": ("Evaluations during training and the checkpoint they keep as best.", (
            "eval_interval", "eval_episodes", "eval_greedy", "policy_ema", "confirm_episodes",
            "threshold", "stop_when_solved",
        )),
        "checkpoints": ("When the run is saved.", ("checkpoint_interval", "keep_every")),
        "logging": ("What is logged, and where.", (
            "log_interval", "grad_stats", "tensorboard", "wandb", "wandb_project",
            "wandb_mode", "mlflow", "mlflow_uri",
        )),
    }  # fmt: skip
    """The fields by concern, as ``--help`` shows them: group -> (what it holds, fields).
    A recipe's own fields form a group of their own."""
    acts_only_with: ClassVar[dict[str, tuple[str, tuple[Any, ...]]]] = {
        "gae_lambda": ("returns", ("gae",)),
        "baseline_rate": ("baseline", ("ema",)),
        "group_size": ("baseline", ("leave_one_out", "group_mean", "greedy")),
        "entropy_target_lr": ("entropy_target", "not None"),
        "max_kl": ("optimizer", ("natural",)),
        "fisher": ("optimizer", ("natural",)),
        "target_kl": ("lr_control", ("kl",)),
        "kl_lr_range": ("lr_control", ("kl",)),
    }  # fmt: skip
    """Fields that act only when another field takes one of some values (``"not
    None"``: any value but None): field -> (that field, those values). A run's value of
    such a field is no setting of the run when the other field says it is unused
    (``inert``)."""
    absent_means: ClassVar[dict[str, Any]] = {}
    """Fields whose default changed after they were added, each with the value a stored
    config that lacks the field ran with (it was written before the field existed). A
    stored config that lacks any other field ran as that field's default does."""

    seed: Annotated[int, Range(low=0, high=2**32 - 1)] = 0
    """Seed of torch, numpy, random and the environments."""
    total_frames: Count = 100_000
    """Environment steps to train for (at most)."""
    total_updates: Count | None = None
    """Updates to train for (at most; None: no limit)."""
    run_dir: Path | None = None
    """Where checkpoints, logs and the summary go. None:
    runs/<recipe>-seed<seed>-<time>."""
    resume: bool = False
    """Continue the run in run_dir from its checkpoint."""
    workers: Count = 1
    """Collector processes. More than 1 uses TorchRL's multi-process collector."""
    ray: bool = False
    """Collect on Ray actors (rl_pg[ray]). TorchRL's Ray collector runs `workers`
    actors; segments only."""
    overlap: bool = False
    """Step half the environments while the policy acts on the other half. Segments
    from one local collector, on environments built in two groups (the EnvPool backend);
    strictly on-policy."""
    device: Literal["auto", "cpu", "cuda"] = "cpu"
    """Where the models and the optimiser live. 'auto': CUDA when available.
    Environments step on the CPU. The recipes' small networks train fastest on the CPU,
    next to their environments; a GPU pays for large models (Pong's trunk)."""
    threads: Count | None = 1
    """torch threads of this process (None: torch's default). The same while rl-pg
    evaluate and rl-pg play run its checkpoints: small models update fastest on one, and
    a second thread only contends with the environment on a busy machine."""
    batch_mode: Literal["episodes", "segments"] = "episodes"
    """Whole episodes per update, or fixed-length segments. Segments bootstrap from the
    critic where they cut an episode."""
    episodes_per_batch: Count = 8
    """Complete episodes per update (batch_mode='episodes')."""
    segment_length: Count = 50
    """Steps per environment per update (batch_mode='segments')."""
    segments_late: Count = 1
    """Segments per update from segments_late_start on. Each update then joins this many
    consecutive segments collected with the same policy: a batch that grows late in the
    run, strictly on-policy (1: one segment per update throughout)."""
    segments_late_start: Annotated[float, Range(0, 1, high_open=True)] = 0.5
    """Share of total_frames after which each update takes segments_late segments."""
    env_restart_interval: Count = 50
    """Updates between restarts of every environment. With segments and one worker;
    episodes in flight are cut there. A resumed run replays the actions since the last
    restart, so the results do not depend on when, or how often, the run checkpoints."""
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
    normalize_advantage: bool = False
    """Standardise the policy weights over each batch."""
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
    eval_interval: Count = 10_000
    """Frames between evaluations."""
    eval_episodes: Count = 20
    """Episodes per evaluation."""
    eval_greedy: bool = True
    """Evaluate greedily (argmax / mean action) rather than by sampling. Sampled
    evaluations draw their own random numbers (the same ones each time, from the run's
    evaluation seed), so they change nothing in the training."""
    policy_ema: Annotated[float, Range(0, 1, high_open=True)] = 0.0
    """Deploy an average of the actor's weights. Evaluations, best.pt and play use an
    exponential moving average (torch's AveragedModel), moved towards the trained
    weights by 1 - policy_ema after every update; the environments are still played with
    the trained weights. 0: evaluate the trained weights themselves."""
    confirm_episodes: Count | None = None
    """Episodes that confirm a new best, greedily and by sampling. Each evaluation that
    could become best.pt is replayed on this many more episodes both ways, and best.pt
    is the checkpoint whose lower mean of the two is highest: the best of many short
    evaluations is partly the luckiest, and a policy can act well greedily and badly by
    sampling. Evaluations at or above threshold (when set) and above the best confirmed
    score are replayed. None: best.pt is the evaluation with the highest mean return."""
    threshold: float | None = None
    """Evaluation mean return that counts as solved."""
    stop_when_solved: bool = True
    """Stop at the first evaluation that reaches the threshold."""
    checkpoint_interval: Count = 50
    """Updates between checkpoints (one is always written at the end)."""
    keep_every: Count | None = None
    """Also keep a checkpoint every N updates (None: never). Kept as
    run_dir/checkpoints/update_<N>.pt beside the last and the best."""
    log_interval: Count = 1
    """Updates between training-metric log lines."""
    tensorboard: bool = False
    """Also log to TensorBoard (rl_pg[tensorboard]). The events go to
    run_dir/logs/tensorboard."""
    wandb: bool = False
    """Also log to Weights & Biases (rl_pg[wandb]). The run is named after run_dir."""
    wandb_project: str = "rl_pg"
    """W&B project of the run."""
    wandb_mode: Literal["offline", "online"] = "offline"
    """W&B without an account, or streamed to its server. 'offline': files in
    run_dir/wandb (upload later with `wandb sync`); 'online': stream to the W&B server
    (after `wandb login`)."""
    mlflow: bool = False
    """Also log to MLflow (rl_pg[mlflow]). One MLflow run in the experiment named after
    the recipe."""
    mlflow_uri: str | None = None
    """MLflow tracking URI (None: MLflow's default). For example sqlite:///mlflow.db or
    http://host:5000; None also reads $MLFLOW_TRACKING_URI."""
    progress: bool = True
    """Show a progress bar."""
    grad_stats: Count | None = None
    """Measure the gradient's noise every N updates (None: never). The noise scale, SNR
    and half-batch cosine of every return estimator on that update's batch, logged as
    grad/<estimator>/<statistic>. Changes nothing in the training."""

    def __init_subclass__(cls, **defaults: Any) -> None:
        """``class Config(TrainConfig, lr=5e-3)``: new defaults for inherited fields."""
        super().__init_subclass__()
        if not defaults:
            return
        inherited = {}
        for base in reversed(cls.__mro__[1:]):
            if dataclasses.is_dataclass(base):
                inherited.update(typing.get_type_hints(base, include_extras=True))
        unknown = sorted(set(defaults) - set(inherited))
        if unknown:
            raise TypeError(
                f"{cls.__name__} sets defaults of {', '.join(unknown)}, which "
                f"{cls.__mro__[1].__name__} does not have: declare new fields in the class body."
            )
        own = dict(inspect.get_annotations(cls))
        clash = sorted(set(defaults) & set(own))
        if clash:
            raise TypeError(
                f"{cls.__name__} both declares and overrides {', '.join(clash)}: do one."
            )
        # Re-declared with the base's type: @dataclass then keeps the field in place.
        annotations = {name: inherited[name] for name in defaults}
        cls.__annotations__ = {**annotations, **own}
        for name, value in defaults.items():
            setattr(cls, name, value)

    def __post_init__(self) -> None:
        if self.scale_lr_factor is None:  # a recipe that chooses by policy did so first
            self.scale_lr_factor = 1.0
        self.validate()

    @classmethod
    def from_stored(cls, stored: dict[str, Any], **changes: Any) -> TrainConfig:
        """This config from a run's stored one (``config.json``, a checkpoint's
        ``"config"``) with ``changes``; fields this class lacks are ignored, fields the
        stored config lacks take the values the run had (``as_run``)."""
        fields = {field.name: field for field in dataclasses.fields(cls)}
        values = {k: v for k, v in {**cls.as_run(stored), **changes}.items() if k in fields}
        for name, value in values.items():  # JSON gave back a list for a tuple
            if isinstance(value, list) and isinstance(fields[name].default, tuple):
                values[name] = tuple(value)
        return cls(**values)

    @classmethod
    def inert(cls, name: str, config: dict[str, Any]) -> bool:
        """Whether field ``name`` does nothing in ``config`` (a stored config, as
        ``as_run`` completes it), by ``acts_only_with``.

        Examples:
            >>> from rl_pg.training import TrainConfig
            >>> TrainConfig.inert("target_kl", {"lr_control": "none"})
            True
            >>> TrainConfig.inert("target_kl", {"lr_control": "kl"})
            False
        """
        if name not in cls.acts_only_with:
            return False
        other, values = cls.acts_only_with[name]
        value = config.get(other)
        return value is None if values == "not None" else value not in values

    @classmethod
    def as_run(cls, stored: dict[str, Any]) -> dict[str, Any]:
        """A stored config with the fields it lacks (newer than the run) at the values
        the run had: their defaults, or ``absent_means`` where a default has changed
        since. Values as ``config_dict`` writes them (paths as strings)."""
        defaults = {
            field.name: _plain(field.default)
            for field in dataclasses.fields(cls)
            if field.default is not dataclasses.MISSING
        }
        return {key: _plain(value) for key, value in {**defaults, **cls.absent_means,
                                                      **stored}.items()}  # fmt: skip

    def torch_device(self) -> torch.device:
        """``device`` as a ``torch.device`` ('auto' resolved).

        Raises:
            DeviceUnavailable: ``device='cuda'`` where torch sees no CUDA device.
            ValueError: a CUDA device with worker processes.
        """
        device = self.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device == "cuda" and (self.workers > 1 or self.ray):
            raise ValueError(
                f"--device {self.device} trains on CUDA with local collection only: drop "
                f"--workers / --ray, or use --device cpu with them."
            )
        if device == "cuda" and not torch.cuda.is_available():
            raise DeviceUnavailable(
                "device (--device) is 'cuda' but torch sees no CUDA device (torch "
                f"{torch.__version__}, built for CUDA {torch.version.cuda}); use --device cpu, "
                "or install a CUDA build of torch (README: Bring your own torch)."
            )
        return torch.device(device)

    def validate(self) -> None:
        """Checks every field (also those a recipe adds) against its type and bounds.

        Runs when the config is made, so that the command line refuses a bad flag
        before anything starts, and again in [`train`][rl_pg.training.loop.train].

        Raises:
            ValueError: a value out of its range or choices; the message names the
                field and its flag.
            TypeError: a value of the wrong kind (from Python code).
        """
        check_fields(self)
        if self.resume and self.run_dir is None:
            raise ValueError("--resume needs --run-dir: the directory of the run to continue.")
        if self.segments_late > 1 and self.batch_mode != "segments":
            raise ValueError(
                f"--segments-late {self.segments_late} joins segments into one update, but "
                f"--batch-mode is {self.batch_mode!r}: use --batch-mode segments, or "
                "--episodes-per-batch for more whole episodes per update."
            )
        if self.overlap and (self.batch_mode != "segments" or self.workers > 1 or self.ray):
            raise ValueError(
                "--overlap steps the two halves of this process's environments in turn, "
                "segment by segment: use it with --batch-mode segments and one local "
                f"collector (got --batch-mode {self.batch_mode}, --workers {self.workers}"
                f"{', --ray' if self.ray else ''})."
            )
        if self.overlap and getattr(self, "num_envs", 2) < 2:
            raise ValueError(
                f"--overlap steps two halves of the environments in turn: use --num-envs 2 "
                f"or more (got {self.num_envs})."
            )
        if self.overlap and getattr(self, "backend", None) != "envpool":
            raise ValueError(
                "--overlap needs environments that step without holding Python: use "
                "--backend envpool with it"
                + ("." if hasattr(self, "backend") else " (this recipe has no EnvPool backend).")
            )
        if self.critic_steps > 1 and self.baseline != "critic":
            raise ValueError(
                f"--critic-steps {self.critic_steps} fits a critic, but --baseline is "
                f"{self.baseline!r}: use --baseline critic, or leave --critic-steps at 1."
            )
        if self.returns == "gae" and self.baseline != "critic":
            raise ValueError(
                f"--returns gae estimates advantages with a critic, but --baseline is "
                f"{self.baseline!r}: use --baseline critic, or --returns reward_to_go."
            )
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
        if self.adam_beta1 != 0.9 and self.optimizer == "sgd":
            raise ValueError(
                f"--adam-beta1 {self.adam_beta1} sets Adam's gradient average, but "
                f"--optimizer is {self.optimizer!r}: use --optimizer adam, or leave "
                "--adam-beta1 at 0.9."
            )
        self._validate_new_steps()
        if self.lr_schedule_start != 0 and self.lr_schedule != "linear":
            raise ValueError(
                f"--lr-schedule-start {self.lr_schedule_start} is where the linear learning "
                "rate schedule starts decaying: add --lr-schedule linear, or pass "
                "--lr-schedule-start 0."
            )
        if self.ray and self.batch_mode != "segments":
            raise ValueError(
                "The Ray collector yields fixed-length batches: use --batch-mode segments with "
                "--ray (whole-episode batches need the local or multi-process collectors)."
            )

    def _validate_new_steps(self) -> None:
        """The group baselines, the natural step and the controllers."""
        from rl_pg.groups import GROUP_BASELINES

        grouped = self.baseline in GROUP_BASELINES
        if grouped and (self.batch_mode != "episodes" or self.workers > 1 or self.ray):
            raise ValueError(
                f"--baseline {self.baseline} plays episodes in groups from one seed: use "
                f"--batch-mode episodes with one local collector (got --batch-mode "
                f"{self.batch_mode}, --workers {self.workers}{', --ray' if self.ray else ''})."
            )
        width = self.group_size + (self.baseline == "greedy")
        if grouped and self.episodes_per_batch % width:
            raise ValueError(
                f"--baseline {self.baseline} plays groups of {width} episodes (--group-size "
                f"{self.group_size}{' and the greedy one' if width > self.group_size else ''}): "
                f"set --episodes-per-batch to a multiple of {width} (got "
                f"{self.episodes_per_batch})."
            )
        num_envs = getattr(self, "num_envs", None)
        if grouped and num_envs is not None and self.episodes_per_batch % num_envs:
            raise ValueError(
                f"--baseline {self.baseline} plays each batch in rounds of one episode per "
                f"environment: set --episodes-per-batch to a multiple of --num-envs (got "
                f"{self.episodes_per_batch} and {num_envs}; as many environments as "
                f"episodes is one round)."
            )
        if self.baseline == "greedy" and num_envs is not None and num_envs % width:
            raise ValueError(
                f"--baseline greedy plays the last environment of every {width} greedily: "
                f"set --num-envs to a multiple of {width} (--group-size {self.group_size} "
                f"and the greedy one; got {num_envs})."
            )
        if self.group_scale and not grouped:
            raise ValueError(
                f"--group-scale divides group advantages by their group's standard "
                f"deviation, but --baseline is {self.baseline!r}: pick leave_one_out, "
                f"group_mean or greedy, or use --normalize-advantage."
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
        low, high = self.kl_lr_range
        if not 0 < low <= 1 <= high < math.inf:
            raise ValueError(
                f"--kl-lr-range {low} {high} bounds the rate --lr-control kl sets, as "
                f"factors of --lr, which it starts at: LOW must be in (0, 1] and HIGH finite "
                f"and at least 1 (e.g. 0.01 10)."
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


def config_dict(cfg: Any) -> dict[str, Any]:
    """The config (a ``TrainConfig``, or any dataclass) as plain JSON-able values (paths
    as strings, pairs as lists), as a run's config.json holds them: a stored config and
    a new one compare entry by entry."""
    return {key: _plain(value) for key, value in dataclasses.asdict(cfg).items()}


def _plain(value: Any) -> Any:
    """``value`` as JSON gives it back: a path as a string, a tuple as a list."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple | list):
        return [_plain(item) for item in value]
    return value
