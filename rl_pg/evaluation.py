"""Play whole episodes with a policy, greedily or by sampling, and summarise them."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple, Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from rl_pg._checks import check_bool, check_int, check_names
from rl_pg.action_stats import action_steps, describe_actions

__all__ = [
    "EpisodePlayer",
    "EpisodeRequest",
    "EvaluationEnv",
    "check_playing",
    "episode_shares",
    "evaluate",
    "first_episodes",
    "play_episodes",
    "policy_device",
    "reported",
]


def first_episodes(
    rollout: TensorDictBase, flags: Sequence[str] = (), values: Sequence[str] = ()
) -> dict[str, torch.Tensor]:
    """Return, length, flags and final values of the first episode of each environment.

    Args:
        rollout (TensorDictBase): ``[T]`` or ``[*B, T]`` output of ``env.rollout``.
        flags (sequence of str): boolean ``("next", key)`` entries to report, true if set
            at any step of the episode (e.g. ``"crashed"``, ``"success"``).
        values (sequence of str): ``("next", key)`` entries to report as their value at
            the episode's last step (e.g. ``"route_completion"``; the rollout's last step
            for an episode that did not finish).

    Returns:
        A dict of ``[N]`` tensors: ``return``, ``length``, ``finished`` and one per flag
        and value found in the rollout.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rl_pg.evaluation import first_episodes
        >>> rollout = TensorDict({"next": {
        ...     "reward": torch.ones(2, 4, 1),
        ...     "done": torch.tensor([[0, 1, 0, 0], [0, 0, 0, 1]], dtype=torch.bool)[..., None],
        ... }}, batch_size=[2, 4])
        >>> first_episodes(rollout)["return"]
        tensor([2., 4.])
    """
    rollout = rollout.reshape(-1, rollout.shape[-1]) if rollout.ndim > 1 else rollout[None]
    done = rollout["next", "done"].reshape(*rollout.shape, -1).any(-1)
    # A step belongs to the first episode if no done came strictly before it.
    first = (done.cumsum(-1) - done.long()) == 0
    reward = rollout["next", "reward"].reshape(*rollout.shape, -1).sum(-1)
    out = {
        "return": (reward * first).sum(-1),
        "length": first.sum(-1),
        "finished": (done & first).any(-1),
    }
    for flag in flags:
        value = rollout.get(("next", flag), None)
        if value is not None:
            value = value.reshape(*rollout.shape, -1).any(-1).bool()
            out[flag] = (value & first).any(-1)
    last = (out["length"] - 1).clamp(min=0)  # index of each first episode's last step
    for key in values:
        value = rollout.get(("next", key), None)
        if value is not None:
            value = _one_per_step(key, value.reshape(*rollout.shape, -1))
            out[key] = value.float().gather(-1, last[:, None])[:, 0]
    return out


def evaluate(
    policy: TensorDictModuleBase,
    env: EvaluationEnv,
    *,
    episodes: int,
    deterministic: bool = True,
    max_steps: int = 100_000,
    flags: Sequence[str] = (),
    values: Sequence[str] = (),
    action_stats: bool = False,
) -> dict[str, Any]:
    """Plays ``episodes`` episodes; returns their mean and std return, flag rates, values.

    A batched ``env`` plays its environments side by side, each its share of the
    ``episodes`` ([`episode_shares`][rl_pg.evaluation.episode_shares]) back to back:
    a fixed number of episodes each, so the result does not favour short episodes.
    Environments are reset only when their episode ends, so one that walks through a
    fixed list of start states (an in-order scenario set) skips none. An
    [`EpisodeWorkers`][rl_pg.episode_workers.EpisodeWorkers] shares the episodes the same
    way among its processes.

    Keyword Args:
        episodes (int): number of episodes.
        deterministic (bool): act greedily (the distribution's mode, e.g. argmax) rather
            than by sampling. Defaults to ``True``.
        max_steps (int): cap on an episode's length. Defaults to ``100_000``.
        flags (sequence of str): boolean entries to report as rates (see
            [`first_episodes`][rl_pg.evaluation.first_episodes]). Defaults to ``()``.
        values (sequence of str): entries averaged at the episodes' last step, e.g.
            ``"route_completion"``. Defaults to ``()``.
        action_stats (bool): also describe how a discrete policy acted, over every
            step of the counted episodes (policies that write their ``"logits"``, as
            [`mlp_actor`][rl_pg.models.mlp_actor]'s do): ``action_shares`` (the share
            of steps each action was played), ``action_switch_rate`` (the share of
            steps, after an episode's first, whose action differs from the one before),
            ``greedy_action_rate`` (the share of steps that played the policy's most
            probable action: 1 when greedy) and ``mean_entropy`` (of the policy, in
            nats). Left out for other policies. Defaults to ``False``.

    Returns:
        ``{"mean_return", "std_return", "mean_length", "<flag>_rate", ...,
        "mean_<value>", ...}``, and the action statistics when asked for.

    Raises:
        ValueError: for ``episodes < 1`` or ``max_steps < 1``, or more episodes than an
            environment with ``distinct_episodes`` (a fixed set of scenarios) has.
        TypeError: for a non-boolean ``deterministic`` or flags that are not strings.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> from rl_pg.envs import BanditEnv
        >>> from rl_pg.evaluation import evaluate
        >>> actor = ProbabilisticActor(
        ...     TensorDictModule(torch.nn.Linear(1, 4), ["observation"], ["logits"]),
        ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
        ... )
        >>> with torch.no_grad():  # a policy that prefers arm 3, which pays 0
        ...     _ = actor.module[0].module.bias.copy_(torch.tensor([0.0, 0.0, 0.0, 9.0]))
        ...     _ = actor.module[0].module.weight.zero_()
        >>> evaluate(actor, BanditEnv(num_arms=4, batch_size=8), episodes=8)["mean_return"]
        0.0
    """
    episodes, max_steps, deterministic = check_playing(episodes, max_steps, deterministic)
    # (a TorchRL batched env answers attribute lookups only once started: ask players only)
    distinct = None if isinstance(env, EnvBase) else getattr(env, "distinct_episodes", None)
    if distinct is not None and episodes > distinct:
        raise ValueError(
            f"This evaluation plays a fixed set of {distinct} episodes (scenarios played in "
            f"order, each once): {episodes} would play {episodes - distinct} of them twice "
            f"and count them twice. Ask for at most {distinct} episodes."
        )
    flags, values = check_names("flags", flags), check_names("values", values)
    action_stats = check_bool("action_stats", action_stats)
    request = EpisodeRequest(episodes, deterministic, max_steps, flags, values, action_stats)
    if isinstance(env, EnvBase):
        stats = play_episodes(policy, env, request)
    elif isinstance(env, EpisodePlayer):
        stats = env.play(policy, request)
    else:
        raise TypeError(
            f"evaluate plays its episodes on a TorchRL EnvBase or an EpisodePlayer "
            f"(e.g. rl_pg.episode_workers.EpisodeWorkers), got {type(env).__name__}."
        )
    stats = {key: value.float() for key, value in stats.items()}
    out = {
        "mean_return": stats["return"].mean().item(),
        "std_return": stats["return"].std(unbiased=False).item(),
        "mean_length": stats["length"].mean().item(),
    }
    averaged = _averaged(flags, values)
    out.update({name: stats[key].mean().item() for name, key in averaged.items() if key in stats})
    if action_stats and "action_counts" in stats:
        out.update(describe_actions(stats))
    return out


def reported(flags: Sequence[str] = (), values: Sequence[str] = ()) -> tuple[str, ...]:
    """The entries [`evaluate`][rl_pg.evaluation.evaluate] reports for these ``flags``
    and ``values`` (its action statistics aside), when the episodes carry them.

    Examples:
        >>> from rl_pg.evaluation import reported
        >>> reported(flags=["crashed"], values=["route_completion"])
        ('mean_return', 'std_return', 'mean_length', 'crashed_rate', 'mean_route_completion')
    """
    flags, values = check_names("flags", flags), check_names("values", values)
    return ("mean_return", "std_return", "mean_length", *_averaged(flags, values))


def _averaged(flags: Sequence[str], values: Sequence[str]) -> dict[str, str]:
    """Each entry that averages a ``flag`` (``<flag>_rate``) or a ``value``
    (``mean_<value>``) over the episodes, with the per-episode statistic it averages."""
    return {**{f"{flag}_rate": flag for flag in flags}, **{f"mean_{key}": key for key in values}}


def episode_shares(episodes: int, n: int) -> list[int]:
    """How ``n`` environments share ``episodes`` episodes in an evaluation: ``episodes //
    n`` each, one more for the first ``episodes % n``.

    Examples:
        >>> from rl_pg.evaluation import episode_shares
        >>> episode_shares(100, 3)
        [34, 33, 33]
    """
    return [episodes // n + (i < episodes % n) for i in range(n)]


class EpisodeRequest(NamedTuple):
    """Which episodes to play, how, and what to report of them (the arguments of
    [`evaluate`][rl_pg.evaluation.evaluate], checked)."""

    episodes: int
    deterministic: bool
    max_steps: int
    flags: Sequence[str]
    values: Sequence[str]
    action_stats: bool = False


@runtime_checkable
class EpisodePlayer(Protocol):
    """Plays a policy's episodes where its environments are, for
    [`evaluate`][rl_pg.evaluation.evaluate]: what an evaluation environment that is not
    a TorchRL ``EnvBase`` implements
    ([`EpisodeWorkers`][rl_pg.episode_workers.EpisodeWorkers], one process per
    environment). ``set_seed`` seeds the next ``play``; ``play`` returns what
    [`play_episodes`][rl_pg.evaluation.play_episodes] does."""

    batch_size: torch.Size

    def set_seed(self, seed: int | None) -> int | None: ...

    def play(
        self, policy: TensorDictModuleBase, request: EpisodeRequest
    ) -> dict[str, torch.Tensor]: ...

    def close(self) -> None: ...


EvaluationEnv = EnvBase | EpisodePlayer
"""What plays an evaluation's episodes: a TorchRL environment (batched: side by side),
or an [`EpisodePlayer`][rl_pg.evaluation.EpisodePlayer]."""


def play_episodes(
    policy: TensorDictModuleBase, env: EnvBase, request: EpisodeRequest
) -> dict[str, torch.Tensor]:
    """Plays ``request`` on ``env`` in this process: one entry per episode, ``return``,
    ``length``, ``finished``, the flags and values asked for (and the action tallies
    that ``action_stats`` asks for). What [`evaluate`][rl_pg.evaluation.evaluate]
    summarises, and what an [`EpisodePlayer`][rl_pg.evaluation.EpisodePlayer] returns."""
    episodes, deterministic, max_steps, flags, values, action_stats = request
    exploration = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    cast = policy_device(policy) not in (None, env.device)  # a policy on a GPU, say
    with set_exploration_type(exploration), torch.no_grad():
        if math.prod(env.batch_size) > 1:
            return _side_by_side(
                policy, env, episodes, max_steps, flags, values, cast=cast,
                action_stats=action_stats,
            )  # fmt: skip
        results: dict[str, list[torch.Tensor]] = {}
        for _ in range(episodes):
            rollout = env.rollout(
                max_steps, policy, break_when_any_done=True, auto_cast_to_device=cast
            )
            episode = first_episodes(rollout, flags, values)
            if action_stats:  # the first episode's steps, tallied
                length = int(episode["length"][0])
                steps = rollout.reshape(-1)[:length]
                acts = action_steps(steps, 1, length, torch.tensor([-1])) if length else None
                if acts is not None:
                    episode.update({key: value.sum(1) for key, value in acts[0].items()})
            for key, value in episode.items():
                results.setdefault(key, []).append(value)
        return {key: torch.cat(value) for key, value in results.items()}


def policy_device(policy: TensorDictModuleBase) -> torch.device | None:
    """The device of ``policy``'s first parameter (None: it has none)."""
    parameters = getattr(policy, "parameters", None)  # TorchRL's RandomPolicy has none
    return None if parameters is None else next((p.device for p in parameters()), None)


def _side_by_side(
    policy: TensorDictModuleBase,
    env: EnvBase,
    episodes: int,
    max_steps: int,
    flags: Sequence[str],
    values: Sequence[str],
    *,
    cast: bool,
    action_stats: bool = False,
    chunk: int = 64,
) -> dict[str, torch.Tensor]:
    """``episodes`` episodes of a batched ``env``, each of its environments playing its
    share back to back; returns one entry per episode, as ``first_episodes`` does.

    Environment ``i`` contributes its first ``episode_shares(episodes, n)[i]`` episodes,
    whatever their lengths, so short episodes are not favoured;
    one that has played its share plays on uncounted until the others have. Each
    environment is reset only when its episode ends (or is cut at ``max_steps``), so an
    environment that walks through a fixed list of start states, like an in-order
    scenario set, skips none of them.
    """
    n = math.prod(env.batch_size)
    share = torch.tensor(episode_shares(episodes, n))
    played = torch.zeros(n, dtype=torch.long)
    running = {"return": torch.zeros(n), "length": torch.zeros(n, dtype=torch.long)}
    episodes_out: dict[str, list[torch.Tensor]] = {"finished": []}
    previous = torch.full((n,), -1, dtype=torch.long)  # each episode's last action so far
    tensordict = env.reset()
    while (played < share).any():
        steps = min(chunk, max_steps - int(running["length"].max()))
        part = env.rollout(
            steps,
            policy,
            auto_reset=False,
            tensordict=tensordict,
            break_when_any_done=False,
            auto_cast_to_device=cast,
        )
        nxt = part["next"].reshape(n, steps)
        per_step = {
            "return": nxt["reward"].reshape(n, steps, -1).sum(-1).float(),
            "done": nxt["done"].reshape(n, steps, -1).any(-1),
        }
        for flag in flags:
            if (value := nxt.get(flag, None)) is not None:
                per_step[flag] = value.reshape(n, steps, -1).any(-1)
                running.setdefault(flag, torch.zeros(n, dtype=torch.bool))
        for key in values:
            if (value := nxt.get(key, None)) is not None:
                per_step[key] = _one_per_step(key, value.reshape(n, steps, -1)).float()
                running.setdefault(key, torch.zeros(n))
        seen_flags = [flag for flag in flags if flag in per_step]
        seen_values = [key for key in values if key in per_step]
        acts = action_steps(part, n, steps, previous) if action_stats else None
        if acts is not None:
            for key, value in acts[0].items():
                running.setdefault(key, torch.zeros(n, *value.shape[2:]))
        for t in range(steps):
            running["return"] += per_step["return"][:, t]
            running["length"] += 1
            for flag in seen_flags:
                running[flag] |= per_step[flag][:, t]
            for key in seen_values:
                running[key] = per_step[key][:, t].clone()
            if acts is not None:
                for key, value in acts[0].items():
                    running[key] += value[:, t]
            done = per_step["done"][:, t]
            ended = done | (running["length"] >= max_steps)
            if ended.any():
                counted = ended & (played < share)
                for key, value in running.items():
                    episodes_out.setdefault(key, []).append(value[counted].clone())
                    value[ended] = 0
                episodes_out["finished"].append(done[counted])
                played += ended.long()
        if acts is not None:  # `ended`: at the chunk's last step
            previous = acts[1].masked_fill(ended, -1)
        cut = (running["length"] == 0) & ~per_step["done"][:, -1]  # at max_steps, not done
        tensordict = step_mdp(part[..., -1])
        if cut.any():  # end those episodes as a time limit would, so they are reset
            for key in ("done", "truncated"):
                if key in tensordict.keys():
                    tensordict[key] = tensordict[key] | cut.reshape(tensordict[key].shape)
        tensordict = env.maybe_reset(tensordict)
    return {key: torch.cat(value) for key, value in episodes_out.items()}


def _one_per_step(key: str, value: torch.Tensor) -> torch.Tensor:
    if value.shape[-1] != 1:
        raise ValueError(
            f"values are read as one number per step; {key!r} has "
            f"{value.shape[-1]} (pass it under flags if it is a boolean)."
        )
    return value[..., 0]


def check_playing(episodes, max_steps, deterministic) -> tuple[int, int, bool]:
    """The arguments ``evaluate`` and ``rl_pg.recording.play`` share, checked."""
    return (
        check_int("episodes", episodes, low=1),
        check_int("max_steps", max_steps, low=1),
        check_bool("deterministic", deterministic),
    )
