"""EpisodeCollector: whole episodes, each environment's share, from a collector of
segments. (Its batches against the exact policy gradient: tests/test_exact_gradients.py.)"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector

from rl_pg.collectors import SegmentCollector
from rl_pg.envs import GridWorldEnv
from rl_pg.episode_collector import EpisodeCollector
from rl_pg.models import mlp_actor


def _episodes_of(rows) -> list[list[int]]:
    """Each environment's episodes, as lists of step counts (the gridworld observes them)."""
    out = []
    for row in rows:
        episodes, current = [], []
        for step, done in zip(row["step_count"].tolist(), row["next", "done"].squeeze(-1).tolist(),
                              strict=True):  # fmt: skip
            current.append(step)
            if done:
                episodes.append(current)
                current = []
        out.append(episodes)
    return out


@pytest.mark.parametrize(("envs", "episodes"), [(4, 4), (4, 6), (3, 10), (5, 2)])
def test_each_environment_gives_its_first_episodes_of_the_batch(envs, episodes):
    """The batch is, environment after environment, each one's first episodes since the
    batch began: ``episodes // envs`` each and one more for the first ``episodes % envs``."""
    torch.manual_seed(0)
    env = GridWorldEnv(batch_size=envs, max_steps=30)
    actor = mlp_actor(env, hidden=(8,))
    raw = SegmentCollector(env, actor, frames_per_batch=envs * 200)
    torch.manual_seed(1)
    expected = _episodes_of(raw.next())  # 200 steps of each environment, from a reset
    shares = [episodes // envs + (i < episodes % envs) for i in range(envs)]
    assert all(len(found) >= share for found, share in zip(expected, shares, strict=True))
    raw.reset()
    collector = EpisodeCollector(
        SegmentCollector(env, actor, frames_per_batch=envs * 3), episodes=episodes
    )
    torch.manual_seed(1)
    batch = collector.next()
    assert batch.ndim == 1 and int(batch["next", "done"].sum()) == episodes
    assert bool(batch["next", "done"][-1])  # nothing after the last episode's end
    flat = [step for found, share in zip(expected, shares, strict=True)
            for episode in found[:share] for step in episode]  # fmt: skip
    assert batch["step_count"].tolist() == flat
    assert collector.frames >= batch.numel() and collector.frames % (envs * 3) == 0
    collector.shutdown()


def test_every_batch_begins_new_episodes_unless_the_caller_resets():
    env = GridWorldEnv(batch_size=3, max_steps=8)
    actor = mlp_actor(env, hidden=(8,))
    for reset in (True, False):
        kwargs = {} if reset else {"reset": False}  # resetting is the default
        collector = EpisodeCollector(
            SegmentCollector(env, actor, frames_per_batch=3 * 5), episodes=3, **kwargs
        )
        starts = []
        for _ in range(6):
            batch = collector.next()
            done = batch["next", "done"].squeeze(-1)
            first = torch.cat([torch.ones(1, dtype=torch.bool), done[:-1]])
            starts.append(batch["step_count"][first].tolist())
        # Reset: each episode starts at step 0. Without: the environments carry on, so
        # some batch starts mid-episode (one that began in the previous batch).
        assert all(s == [0, 0, 0] for s in starts) is reset
        collector.shutdown()


def test_torchrls_collector_and_the_end_of_its_frames():
    env = GridWorldEnv(batch_size=2, max_steps=5)
    actor = mlp_actor(env, hidden=(8,))
    segments = Collector(env, actor, frames_per_batch=2 * 5, total_frames=2 * 5 * 4,
                         auto_register_policy_transforms=False)  # fmt: skip
    batches = list(EpisodeCollector(segments, episodes=2))
    # Episodes of at most 5 steps, one per environment per batch, a reset after each:
    # one segment of 5 steps per batch, until the collector's 40 frames are spent.
    assert len(batches) == 4
    assert all(int(b["next", "done"].sum()) == 2 for b in batches)


def test_an_environment_of_batch_size_one_or_none():
    env = GridWorldEnv(max_steps=6)  # batch size []
    actor = mlp_actor(env, hidden=(8,))
    collector = EpisodeCollector(SegmentCollector(env, actor, frames_per_batch=4), episodes=3)
    batch = collector.next()
    assert int(batch["next", "done"].sum()) == 3 and bool(batch["next", "done"][-1])


def test_what_it_cannot_use_is_refused():
    env = GridWorldEnv(batch_size=2)
    actor = mlp_actor(env, hidden=(8,))
    trajectories = Collector(env, actor, frames_per_batch=8, total_frames=-1, trajs_per_batch=2,
                             traj_format="cat", auto_register_policy_transforms=False)  # fmt: skip
    with pytest.raises(ValueError, match="frames_per_batch only"):
        EpisodeCollector(trajectories, episodes=2)
    trajectories.shutdown()
    segments = SegmentCollector(env, actor, frames_per_batch=8)
    with pytest.raises(ValueError, match="episodes must be an integer >= 1"):
        EpisodeCollector(segments, episodes=0)
    with pytest.raises(TypeError, match="reset"):
        EpisodeCollector(segments, episodes=2, reset="yes")


@pytest.mark.parametrize("flags", [(), (1,), (2,)], ids=["[E,T]", "[E,T,1]", "[E,T,2]"])
def test_a_step_ends_its_episode_when_any_of_its_done_flags_is_set(flags):
    # Any collector of [E, T] batches will do, whatever shape its done has: several
    # flags a step (one per agent, say) end the episode when any one is set.
    def segments():
        generator = torch.Generator().manual_seed(0)
        while True:
            done = torch.rand(2, 5, *flags, generator=generator) < 0.3
            yield TensorDict({"next": {"done": done}}, batch_size=[2, 5])

    collector = EpisodeCollector(segments(), episodes=4, reset=False)
    for _ in range(3):
        batch = collector.next()
        ended = batch["next", "done"].reshape(batch.numel(), -1).any(-1)
        assert int(ended.sum()) == 4 and bool(ended[-1])


def _starts(batch):
    """The first step of every episode of a flat batch."""
    done = batch["next", "done"].squeeze(-1)
    return batch[torch.cat([torch.ones(1, dtype=torch.bool), done[:-1]])]


@pytest.mark.parametrize("torchrl", [False, True], ids=["SegmentCollector", "Collector"])
@pytest.mark.parametrize("greedy", [False, True])
def test_groups_start_alike_and_each_batch_draws_new_starts(torchrl, greedy):
    """Every environment of a group is reset with the group's seed: the same first
    observation (CartPole draws it from its seed); each batch, new seeds."""
    from rl_pg.envs import gym_env
    from rl_pg.groups import GreedyInGroups

    torch.manual_seed(0)
    k, groups = 3, 2
    width = k + greedy
    env = gym_env("CartPole-v1", num_envs=width * groups)
    actor = mlp_actor(env, hidden=(8,))
    policy = GreedyInGroups(actor, group_size=k) if greedy else actor
    if torchrl:
        segments = Collector(env, policy, frames_per_batch=env.batch_size[0] * 16,
                             total_frames=-1, auto_register_policy_transforms=False)  # fmt: skip
    else:
        segments = SegmentCollector(env, policy, frames_per_batch=env.batch_size[0] * 16)
    collector = EpisodeCollector(segments, width * groups, group_size=k, greedy=greedy, seed=3)
    seen = []
    for batch_index in range(2):
        batch = collector.next()
        assert int(batch["next", "done"].sum()) == width * groups  # one episode each
        starts = _starts(batch)
        group = starts["group"].squeeze(-1)
        assert group.tolist() == [
            batch_index * groups + g for g in range(groups) for _ in range(width)
        ]
        first = starts["observation"].reshape(groups, width, -1)
        assert torch.equal(first, first[:, :1].expand_as(first))  # alike within a group
        assert not torch.equal(first[0, 0], first[1, 0])  # and not across groups
        seen.append(first[:, 0])
        # Every step carries its episode's group.
        episode = batch["next", "done"].squeeze(-1).long().cumsum(0)
        episode = torch.cat([torch.zeros(1, dtype=torch.long), episode[:-1]])
        assert torch.equal(batch["group"].squeeze(-1), group[episode])
        if greedy:
            flags = starts["greedy"].squeeze(-1).reshape(groups, width)
            assert flags[:, -1].all() and not flags[:, :-1].any()
            assert torch.equal(batch["greedy"].squeeze(-1), flags.flatten()[episode])
        else:
            assert "greedy" not in batch.keys()
    assert not torch.equal(seen[0], seen[1])
    collector.shutdown()


@pytest.mark.parametrize(
    ("envs", "k", "greedy", "episodes", "torchrl"),
    [
        (None, 3, False, 6, False),  # one environment of batch size []: a group after another
        (None, 2, False, 4, True),  # the same through TorchRL's Collector
        (2, 4, False, 8, False),  # a group spans two rounds
        (2, 4, False, 8, True),
        (4, 2, False, 8, False),  # two groups a round, two rounds
        (4, 1, True, 8, False),  # the greedy episode in every round
    ],
)
def test_groups_play_in_rounds_of_one_episode_per_environment(envs, k, greedy, episodes, torchrl):
    """Fewer environments than episodes: rounds, each environment reset with its
    episode's group seed; the batch's episode e = round * n + i is in group e // width."""
    from rl_pg.envs import gym_env
    from rl_pg.groups import GreedyInGroups

    torch.manual_seed(0)
    env = gym_env("CartPole-v1", num_envs=envs)
    actor = mlp_actor(env, hidden=(8,))
    policy = GreedyInGroups(actor, group_size=k) if greedy else actor
    if torchrl:
        segments = Collector(env, policy, frames_per_batch=(envs or 1) * 16, total_frames=-1,
                             auto_register_policy_transforms=False)  # fmt: skip
    else:
        segments = SegmentCollector(env, policy, frames_per_batch=(envs or 1) * 16)
    collector = EpisodeCollector(segments, episodes, group_size=k, greedy=greedy, seed=3)
    width = k + greedy
    groups = episodes // width
    for batch_index in range(2):
        frames = collector.frames
        batch = collector.next()
        assert int(batch["next", "done"].sum()) == episodes
        assert collector.frames - frames >= batch.numel()  # dropped steps count too
        starts = _starts(batch)
        assert starts["group"].squeeze(-1).tolist() == [
            batch_index * groups + e // width for e in range(episodes)
        ]
        first = starts["observation"].reshape(groups, width, -1)
        assert torch.equal(first, first[:, :1].expand_as(first))  # alike within a group
        assert len({tuple(row.tolist()) for row in first[:, 0]}) == groups  # not across
        if greedy:
            assert starts["greedy"].squeeze(-1).tolist() == [
                e % width == k for e in range(episodes)
            ]
    collector.shutdown()


def test_the_groups_seeds_are_reproducible():
    from rl_pg.envs import gym_env

    firsts = []
    for seed in (0, 0, 5):  # 0 is a seed like any other
        env = gym_env("CartPole-v1", num_envs=4)
        segments = SegmentCollector(env, mlp_actor(env, hidden=(8,)), frames_per_batch=4 * 8)
        collector = EpisodeCollector(segments, 4, group_size=2)
        collector.set_seed(seed)
        firsts.append(_starts(collector.next())["observation"])
        collector.shutdown()
    assert torch.equal(firsts[0], firsts[1]) and not torch.equal(firsts[0], firsts[2])


def test_the_groups_seeds_are_fresh_32_bit_integers():
    seen = []

    class Recording(SegmentCollector):
        def reset(self, **kwargs):
            seen.extend(kwargs.get("seed", []))
            super().reset(**kwargs)

    env = GridWorldEnv(batch_size=4, max_steps=5)
    segments = Recording(env, mlp_actor(env, hidden=(8,)), frames_per_batch=4 * 5)
    collector = EpisodeCollector(segments, 8, group_size=2, seed=0)
    for _ in range(5):
        collector.next()
    # Four groups a batch, two rounds of four environments: each seed given twice.
    assert len(seen) == 5 * 2 * 4 and len(set(seen)) == 5 * 4
    assert all(type(seed) is int and 0 <= seed < 2**31 - 1 for seed in seen)


def test_a_seed_given_when_made_fixes_the_groups_starts():
    from rl_pg.envs import gym_env

    firsts = []
    for seed in (0, 0, 1):  # 0 is a seed like any other
        env = gym_env("CartPole-v1", num_envs=4)
        segments = SegmentCollector(env, mlp_actor(env, hidden=(8,)), frames_per_batch=4 * 8)
        collector = EpisodeCollector(segments, 4, group_size=2, seed=seed)
        firsts.append(_starts(collector.next())["observation"])
        collector.shutdown()
    assert torch.equal(firsts[0], firsts[1]) and not torch.equal(firsts[0], firsts[2])


@pytest.mark.parametrize(
    ("envs", "kwargs", "error", "match"),
    [
        (6, {"episodes": 4, "group_size": 2}, ValueError, "a multiple of both 6 and 2"),
        (6, {"episodes": 6, "group_size": 4}, ValueError, "a multiple of both 6 and 4"),
        (6, {"episodes": 6, "group_size": 3, "greedy": True}, ValueError,
         "3 sampled plus its greedy one"),
        (6, {"episodes": 12, "group_size": 3, "greedy": True}, ValueError,
         "build a multiple of 4 environments"),
        (6, {"episodes": 6, "greedy": True}, ValueError, "set group_size"),
        (6, {"episodes": 6, "group_size": 0}, ValueError, "group_size must be an integer"),
    ],
)  # fmt: skip
def test_groups_that_cannot_be_played_are_refused(envs, kwargs, error, match):
    env = GridWorldEnv(batch_size=envs)
    segments = SegmentCollector(env, mlp_actor(env, hidden=(8,)), frames_per_batch=envs * 4)
    with pytest.raises(error, match=match):
        EpisodeCollector(segments, **kwargs)


def test_groups_need_a_collector_of_environments_in_this_process():
    class Remote:  # a multi-process collector: no environment here
        def __iter__(self):
            return iter(())

    with pytest.raises(TypeError, match="steps its environments in this process"):
        EpisodeCollector(Remote(), 4, group_size=2)


def test_a_collector_whose_reset_takes_no_seed_is_named():
    env = GridWorldEnv(batch_size=4)

    class OldCollector(SegmentCollector):
        def reset(self):
            super().reset()

    segments = OldCollector(env, mlp_actor(env, hidden=(8,)), frames_per_batch=4 * 4)
    collector = EpisodeCollector(segments, 4, group_size=2)
    with pytest.raises(TypeError, match=r"OldCollector does not take it"):
        collector.next()


def test_ungrouped_batches_leave_torchs_generator_alone():
    env = GridWorldEnv(batch_size=4)
    segments = SegmentCollector(env, mlp_actor(env, hidden=(8,)), frames_per_batch=4 * 4)
    state = torch.get_rng_state()
    EpisodeCollector(segments, 4)
    assert torch.equal(state, torch.get_rng_state())
