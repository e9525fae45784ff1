"""Whole-episode batches over any segment collector (TorchRL's ``Collector`` or
rl_pg's own), every episode drawn from the current policy: optionally in groups
started from one seed, with a greedy episode in each."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import torch
from tensordict import TensorDictBase

from rl_pg._checks import check_bool, check_int

__all__ = ["EpisodeCollector"]


class EpisodeCollector:
    """Batches of exactly ``episodes`` complete episodes, each one an independent draw
    from the current policy, taken from a collector of segments.

    Handing over the first ``episodes`` episodes to end, as
    ``Collector(trajs_per_batch=episodes)`` does, favours short episodes: an environment
    whose episodes end quickly finishes two or three while another is still on its
    first, and the batch fills before the long one ends. The policy gradient of such a
    batch is not the policy's (``tests/test_exact_gradients.py`` measures how far on the
    4x4 gridworld, against the exact gradient). Keeping the episodes in flight for the next
    batch adds episodes that the previous policy began.

    Here every environment contributes a number of episodes fixed in advance:
    ``episodes`` shared out over the environments as evenly as they allow (the first
    ``episodes mod n`` environments one more), each environment's first ones after the
    batch starts. Those are independent draws whatever their lengths. The price is the
    wait for each environment's last episode: the steps an environment takes beyond its
    share are collected and dropped (they count in ``frames``). With as many
    environments as episodes, each plays one episode per batch.

    Args:
        collector: a collector of segments (TorchRL's ``Collector`` or multi-process
            collector with ``frames_per_batch``, a
            [`SegmentCollector`][rl_pg.collectors.SegmentCollector], ...): batches of
            batch size ``[*environments, T]`` (time last), with ``("next", "done")``,
            whose environments continue from one batch to the next until it is reset.
            Its ``frames_per_batch`` is how often the episodes' ends are checked: the
            steps of its last batch past the last share are dropped too.
        episodes (int): complete episodes per batch.

    Keyword Args:
        reset (bool): reset the collector's environments after each batch, so that the
            next batch begins new episodes under the policy as it is then. Defaults to
            True. A caller that resets (or reseeds) them itself between batches passes
            False. With ``group_size`` the environments are reset with the groups'
            seeds as each batch starts, whatever ``reset`` says.
        group_size (int, optional): play the episodes in groups of ``group_size`` that
            start alike, for the group baselines of
            [`ReinforceLoss`][rl_pg.ReinforceLoss] (``baseline="leave_one_out"``,
            ``"group_mean"``, ``"greedy"``; see [`rl_pg.groups`][rl_pg.groups]). The
            batch is then played in rounds of one episode per environment
            (``episodes`` a multiple of the number of environments ``n``): episode
            ``i`` of round ``r`` is the batch's episode ``e = r·n + i`` and belongs
            to its group ``e // group_size``. Before each round the environments are
            reset with their groups' seeds, one fresh seed per group: an int in
            ``[0, 2**31 - 1)``, which any simulator with signed 32-bit seeds takes. They
            go through ``collector.reset(seed=[...])``, which TorchRL's ``Collector``
            hands to the environment's ``reset`` (a gymnasium vector environment seeds
            environment ``i`` with ``seed[i]``; an environment of batch size ``[]``
            gets the one seed). With as many environments as episodes that is one
            round; with one environment (a simulator that runs one engine per
            process) a group's episodes are played one after the other from the same
            seed. Each step gets its group's id under ``"group"``, unique over the
            collector's batches. Defaults to ``None``: independent episodes.
        greedy (bool): with ``group_size``, each group has one more episode, the
            last, whose episode is the group's greedy one (``"greedy"`` is ``True`` on
            its steps). The collector's policy must act greedily there: wrap it in
            [`GreedyInGroups`][rl_pg.greedy_play.GreedyInGroups], which picks the greedy
            environments by their place in the batch (so ``n`` must be a multiple of
            ``group_size + 1``). Its steps count in ``frames``. Defaults to
            ``False``.
        seed (int, optional): seeds the groups' seeds (``set_seed`` reseeds them too).
            Defaults to ``None``: drawn from torch's global generator.

    Each batch is flat, batch size ``[total steps]``: the episodes one after the other
    (those of the first environment first; with groups, round after round, the
    environments in order within each), each ending on ``("next", "done")``, as
    TorchRL's ``traj_format="cat"`` lays them out.

    Examples:
        >>> from torchrl.collectors import Collector
        >>> from rl_pg.episode_collector import EpisodeCollector
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.models import mlp_actor
        >>> env = GridWorldEnv(batch_size=4)
        >>> segments = Collector(env, mlp_actor(env), frames_per_batch=4 * 8, total_frames=-1,
        ...                      auto_register_policy_transforms=False)
        >>> collector = EpisodeCollector(segments, episodes=6)
        >>> batch = next(iter(collector))
        >>> int(batch["next", "done"].sum())
        6
        >>> collector.shutdown()
    """

    def __init__(
        self,
        collector: Any,
        episodes: int,
        *,
        reset: bool = True,
        group_size: int | None = None,
        greedy: bool = False,
        seed: int | None = None,
    ) -> None:
        if getattr(collector, "trajs_per_batch", None) is not None:
            raise ValueError(
                "EpisodeCollector assembles episodes from segments itself: build the "
                "collector with frames_per_batch only (no trajs_per_batch)."
            )
        self.collector = collector
        self.episodes = check_int("episodes", episodes, low=1)
        self.reset_each_batch = check_bool("reset", reset)
        self.greedy = check_bool("greedy", greedy)
        self.group_size = check_int("group_size", group_size, low=1, optional=True)
        if self.group_size is None and self.greedy:
            raise ValueError("greedy=True adds a greedy episode to each group: set group_size.")
        seed = check_int("seed", seed, low=0, optional=True)
        self._generator = torch.Generator()
        self._batches = 0
        if self.group_size is not None:
            self._check_groups()
            # Only grouped batches draw from torch's generator: ungrouped ones leave the
            # global stream as it was.
            self._generator.manual_seed(int(torch.randint(2**62, ())) if seed is None else seed)
        self._segments: Iterator[TensorDictBase] | None = None
        self.frames = 0
        """Environment steps collected so far, the dropped ones included."""

    @property
    def _group_width(self) -> int:
        """Episodes per group: its sampled ones and, with ``greedy``, one more."""
        return self.group_size + self.greedy

    def _check_groups(self) -> None:
        env = getattr(self.collector, "env", None)
        if env is None:
            raise TypeError(
                f"group_size resets the environments with a seed per group, through the "
                f"collector's reset(seed=...): it needs a collector that steps its "
                f"environments in this process (TorchRL's Collector, rl_pg's "
                f"SegmentCollector), got {type(self.collector).__name__}."
            )
        n, width = env.batch_size.numel(), self._group_width
        extra = " plus its greedy one" if self.greedy else ""
        if self.episodes % n or self.episodes % width:
            raise ValueError(
                f"With group_size={self.group_size}, the {n} environment(s) play the batch "
                f"in rounds of one episode each, and each group is {width} episodes "
                f"({self.group_size} sampled{extra}): set episodes to a multiple of both "
                f"{n} and {width} (got episodes={self.episodes})."
            )
        if self.greedy and n % width:
            raise ValueError(
                f"With greedy=True, GreedyInGroups plays the last environment of every "
                f"{width} greedily: build a multiple of {width} environments ({self.group_size} "
                f"sampled episodes plus its greedy one per group; got {n})."
            )

    def __iter__(self) -> Iterator[TensorDictBase]:
        while True:
            try:
                batch = self.next()
            except StopIteration:  # the collector's total_frames is spent
                return
            yield batch

    def next(self) -> TensorDictBase:
        """Collects one batch (``StopIteration`` when the collector has no more)."""
        if self.group_size is not None:
            return self._grouped()
        rows, keep = self._shares(None)
        batch = rows[keep]  # row-major: environment after environment
        if self.reset_each_batch:
            self.reset()
        return batch

    def _shares(self, share: torch.Tensor | None) -> tuple[TensorDictBase, torch.Tensor]:
        """Segments until every environment has ended its ``share`` of episodes (None:
        ``episodes`` shared out evenly), as ``[environments, T]`` rows and the mask of
        the steps that belong to those episodes."""
        if self._segments is None:
            self._segments = iter(self.collector)
        segments, keeps = [], []
        ended = None
        while ended is None or bool((ended < share).any()):
            segment = next(self._segments)
            if segment.ndim == 0:
                raise ValueError("The collector's batches must have a time dimension.")
            self.frames += segment.numel()
            rows = segment.reshape(-1, segment.shape[-1])  # [environments, T]
            done = rows.get(("next", "done")).reshape(*rows.shape, -1).any(-1).long()
            if ended is None:
                n = rows.shape[0]
                if share is None:
                    share = torch.full((n,), self.episodes // n, device=done.device)
                    share[: self.episodes % n] += 1
                ended = torch.zeros(n, dtype=torch.long, device=done.device)
            # An environment's step belongs to its k-th episode of the batch, k counted
            # from 0: keep it while k is below the environment's share.
            before = ended[:, None] + done.cumsum(-1) - done
            keeps.append(before < share[:, None])
            segments.append(rows)
            ended = ended + done.sum(-1)
        rows = torch.cat(segments, dim=1) if len(segments) > 1 else segments[0]
        return rows, torch.cat(keeps, dim=1)

    def _grouped(self) -> TensorDictBase:
        """A batch of groups, in rounds of one episode per environment, each round's
        environments reset with their groups' seeds (the rounds one after the other)."""
        env = self.collector.env
        n, width = env.batch_size.numel(), self._group_width
        groups = self.episodes // width
        seeds = torch.randint(2**31 - 1, (groups,), generator=self._generator)
        rounds = []
        for start in range(0, self.episodes, n):
            episode = torch.arange(start, start + n)  # the batch's episodes this round
            group = episode // width
            round_seeds = seeds[group].tolist()  # one environment of batch size []: an int
            self._reset_groups(round_seeds if env.batch_dims else round_seeds[0])
            rows, keep = self._shares(torch.ones(n, dtype=torch.long))
            length = rows.shape[1]
            device = rows.device
            first = self._batches * groups
            rows.set("group", (first + group).to(device)[:, None].expand(n, length).contiguous())
            if self.greedy:
                greedy = (episode % width == self.group_size).to(device)
                rows.set("greedy", greedy[:, None].expand(n, length).contiguous())
            rounds.append(rows[keep])
        self._batches += 1
        return torch.cat(rounds) if len(rounds) > 1 else rounds[0]

    def _reset_groups(self, seed: list[int] | int) -> None:
        """Resets the environments with their groups' seeds (the next round's)."""
        try:
            self.collector.reset(seed=seed)
        except TypeError as err:
            raise TypeError(
                f"group_size resets the environments with a seed each, by "
                f"collector.reset(seed=[...]); {type(self.collector).__name__} does not "
                f"take it ({err})."
            ) from err

    def reset(self) -> None:
        """Resets the environments: the next batch begins new episodes."""
        self.collector.reset()

    def set_seed(self, seed: int) -> int:
        """Seeds the collector's environments (as its own ``set_seed`` does) and the
        groups' seeds."""
        self._generator.manual_seed(check_int("seed", seed, low=0))
        return self.collector.set_seed(seed)

    def state_dict(self) -> dict:
        """The collector's state (its frame count)."""
        return self.collector.state_dict()

    def shutdown(self) -> None:
        """Shuts the collector down."""
        self.collector.shutdown()
