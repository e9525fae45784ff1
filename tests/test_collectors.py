"""Double-buffered collection: the batches of the synchronous collector, on-policy, resumable."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import assert_same_run
from scipy import stats
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType

from rl_pg.collectors import DoubleBufferedCollector
from rl_pg.envs import EnvPoolEnv, gym_env
from rl_pg.lean import lean_policy
from rl_pg.models import mlp_actor
from rl_pg.recipes import load

pytest.importorskip("envpool")


def _same(a, b) -> bool:
    """Equal entries, except the policy's logits: a matrix product over a group's rows
    may round differently from the same product over every environment's."""
    torch.testing.assert_close(a.get("logits", None), b.get("logits", None))
    keys = set(a.keys(True, True)) - {"logits"}
    return keys == set(b.keys(True, True)) - {"logits"} and all(
        torch.equal(a[key], b[key]) for key in keys
    )


class _OwnTwoGroups(EnvPoolEnv):
    """Another environment of two groups: stepped through its step_send / step_recv
    TensorDicts (the collector hands plain tensors only to EnvPoolEnv itself)."""


@pytest.mark.parametrize("grouped", [EnvPoolEnv, _OwnTwoGroups])
@pytest.mark.parametrize(
    ("task", "num_envs", "steps"),
    [("CartPole-v1", 8, 40), ("CartPole-v1", 5, 30), ("LunarLander-v3", 4, 150)],
)
def test_greedy_batches_are_those_of_torchrls_collector(task, num_envs, steps, grouped):
    """Same seeds and a deterministic policy: the same batches, episode ends included."""
    torch.manual_seed(0)
    one, two = EnvPoolEnv(task, num_envs), grouped(task, num_envs, groups=2)
    actor = mlp_actor(one, hidden=(16,))
    kwargs = {
        "frames_per_batch": num_envs * steps,
        "total_frames": num_envs * steps * 4,
        "exploration_type": ExplorationType.DETERMINISTIC,
    }
    one.set_seed(3)
    two.set_seed(3)
    reference = Collector(one, actor, track_traj_ids=False, **kwargs)
    overlapped = DoubleBufferedCollector(two, actor, **kwargs)
    ends = 0
    for expected, batch in zip(reference, overlapped, strict=True):
        assert batch.batch_size == (num_envs, steps)
        assert _same(expected, batch)
        ends += int(batch["next", "done"].sum())
    assert ends > 0  # the comparison crossed episode ends and resets
    reference.shutdown()
    overlapped.shutdown()


def test_two_groups_step_as_one_pool():
    """The grouped environment's ordinary step is the single pool's, step for step."""
    one, two = (gym_env("CartPole-v1", num_envs=7, backend="envpool", groups=g) for g in (1, 2))
    assert two.group_sizes == [4, 3]
    one.set_seed(11)
    two.set_seed(11)
    actions = torch.randint(0, 2, (60, 7))
    roots = [one.reset(), two.reset()]
    for action in actions:
        steps = []
        for i, env in enumerate((one, two)):
            step, roots[i] = env.step_and_maybe_reset(roots[i].set("action", action))
            steps.append(step)
        assert _same(*steps)


@pytest.mark.parametrize("lean", [False, True], ids=["actor", "lean-policy"])
def test_every_action_is_sampled_from_the_current_policy(lean):
    """Strictly on-policy: after the policy changes, the next batch's actions all come
    from the new policy (stored logits are the policy's on the stored observations), and
    they are distributed as its probabilities say."""
    torch.manual_seed(1)
    env = EnvPoolEnv("CartPole-v1", 6, groups=2)
    actor = mlp_actor(env, hidden=(16,))
    policy = lean_policy(actor) if lean else actor
    collector = DoubleBufferedCollector(env, policy, frames_per_batch=6 * 200, total_frames=-1)
    assert collector._on_tensors == lean  # the lean policy acts on EnvPool's tensors
    counts, expected = np.zeros(2), np.zeros(2)
    for _ in range(3):
        batch = next(iter(collector))
        with torch.no_grad():
            logits = actor[0](batch["observation"])  # the network, without sampling
        torch.testing.assert_close(batch["logits"], logits)
        probs = logits.softmax(-1)
        counts += np.bincount(batch["action"].flatten().numpy(), minlength=2)
        expected += probs.reshape(-1, 2).double().sum(0).numpy()
        with torch.no_grad():  # a new policy before the next batch
            for p in actor.parameters():
                p.add_(torch.randn_like(p))
    # The expected counts summed from float32 probabilities miss the observed total by
    # rounding, which scipy's chisquare refuses beyond a 1.5e-8 relative difference.
    expected *= counts.sum() / expected.sum()
    assert stats.chisquare(counts, expected).pvalue > 1e-4
    collector.shutdown()


def test_a_lean_policy_samples_the_same_on_tensors_as_on_tensordicts():
    """The lean policy acting on the groups' tensors draws what it draws when it is
    called on a TensorDict at each step (a forward hook makes the collector do so):
    the same batches from the same random stream."""
    batches = []
    for hooked in (False, True):
        torch.manual_seed(2)
        env = EnvPoolEnv("CartPole-v1", 5, groups=2)
        policy = lean_policy(mlp_actor(env, hidden=(16,)))
        handle = policy.register_forward_hook(lambda *_: None) if hooked else None
        env.set_seed(4)
        collector = DoubleBufferedCollector(env, policy, frames_per_batch=5 * 60, total_frames=-1)
        batches.append([collector.next() for _ in range(3)])
        collector.shutdown()
        if handle is not None:
            handle.remove()
    for tensors, tensordicts in zip(*batches, strict=True):
        assert set(tensors.keys(True, True)) == set(tensordicts.keys(True, True))
        for key in tensors.keys(True, True):
            assert torch.equal(tensors[key], tensordicts[key]), key
    assert int(batches[0][-1]["next", "done"].sum()) > 0


def test_an_environment_in_one_group_is_refused():
    env = EnvPoolEnv("CartPole-v1", 4)
    with pytest.raises(TypeError, match="groups=2"):
        DoubleBufferedCollector(env, mlp_actor(env, hidden=(4,)), frames_per_batch=8)
    two = EnvPoolEnv("CartPole-v1", 4, groups=2)
    with pytest.raises(ValueError, match="multiple of the 4"):
        DoubleBufferedCollector(two, mlp_actor(two, hidden=(4,)), frames_per_batch=10)
    with pytest.raises(ValueError, match="at least 2"):
        EnvPoolEnv("CartPole-v1", 1, groups=2)
    with pytest.raises(ValueError, match="backend='envpool'"):
        gym_env("CartPole-v1", num_envs=4, groups=2)


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"backend": "gymnasium"}, "--backend envpool"),
        ({"batch_mode": "episodes"}, "--batch-mode segments"),
        ({"workers": 2}, "one local"),
        ({"num_envs": 1}, "--num-envs 2 or more"),
    ],
)
def test_overlap_flags_that_cannot_work_are_refused(overrides, match):
    recipe = load("cartpole")
    with pytest.raises(ValueError, match=match):
        recipe.config(**{"backend": "envpool", "overlap": True, **overrides})


def test_a_recipe_without_envpool_refuses_overlap():
    with pytest.raises(ValueError, match="no EnvPool backend"):
        load("gridworld").config(overlap=True, batch_mode="segments")


def test_an_overlapped_run_resumes_exactly(tmp_path):
    """Stopped between two restarts of the environments, resumed: the same final
    weights as the run that was never stopped (the recorded actions are replayed group
    by group)."""
    recipe = load("cartpole")
    common = {
        "backend": "envpool",
        "overlap": True,
        "num_envs": 5,
        "segment_length": 8,
        "env_restart_interval": 4,
        "threshold": None,
        "eval_interval": 10**9,
        "eval_episodes": 1,
        "checkpoint_interval": 1000,
        "progress": False,
    }
    recipe.train(recipe.config(run_dir=tmp_path / "straight", total_updates=7, **common))
    recipe.train(recipe.config(run_dir=tmp_path / "split", total_updates=6, **common))
    resumed = recipe.train(
        recipe.config(run_dir=tmp_path / "split", total_updates=7, resume=True, **common)
    )
    assert_same_run(resumed, tmp_path / "split", tmp_path / "straight")


def test_a_group_is_received_the_way_it_was_sent():
    env = EnvPoolEnv("CartPole-v1", 4, groups=2)
    root = env.reset()
    with pytest.raises(RuntimeError, match="not stepping"):
        env.recv_tensors(0)
    env.send_action(torch.zeros(2, dtype=torch.long), 0)
    with pytest.raises(RuntimeError, match="already stepping"):
        env.step_send(root[:2].set("action", torch.zeros(2, dtype=torch.long)), 0)
    with pytest.raises(RuntimeError, match="recv_tensors"):
        env.step_recv(0)
    step, observations = env.recv_tensors(0)
    assert step["reward"].shape == (2, 1) and observations["observation"].shape == (2, 4)
    env.close()
