"""Synchronous segment collection: TorchRL's Collector's batches, value for value."""

from __future__ import annotations

import itertools

import pytest
import torch
from tensordict import LazyStackedTensorDict, TensorDict
from torchrl.collectors import Collector
from torchrl.envs import StepCounter, TransformedEnv

from rl_pg.collectors import SegmentCollector
from rl_pg.envs import GridWorldEnv, gym_env
from rl_pg.envs.vector import VectorGymEnv
from rl_pg.lean import lean_policy
from rl_pg.models import mlp_actor
from rl_pg.segments import stacked


def _envs(kind: str, num_envs: int):
    """Two identical environments: one for each collector."""
    if kind == "gridworld":  # an EnvBase without step_tensors: the generic path
        return [GridWorldEnv(batch_size=num_envs) for _ in range(2)]
    if kind == "transformed":  # a TorchRL transform on top of a vector environment
        return [
            TransformedEnv(gym_env("CartPole-v1", num_envs=num_envs), StepCounter())
            for _ in range(2)
        ]
    task, backend = kind.split(":")
    if backend == "envpool":
        pytest.importorskip("envpool")
    return [gym_env(task, num_envs=num_envs, backend=backend) for _ in range(2)]


@pytest.mark.parametrize(
    ("kind", "num_envs", "steps"),
    [
        ("CartPole-v1:gymnasium", 8, 40),
        ("CartPole-v1:gymnasium", 1, 30),
        ("CartPole-v1:envpool", 5, 30),
        ("LunarLander-v3:gymnasium", 4, 150),
        ("LunarLander-v3:envpool", 3, 150),
        ("gridworld", 6, 20),
        ("transformed", 4, 30),
    ],
)
@pytest.mark.parametrize("lean", [True, False], ids=["lean-policy", "actor"])
def test_sampled_batches_are_those_of_torchrls_collector(kind, num_envs, steps, lean):
    """Same seeds, same random stream, a stochastic policy: the same batches, episode
    ends, resets and sampled actions included, across batch boundaries and a reseed."""
    if kind.startswith("LunarLander"):
        pytest.importorskip("Box2D")
    reference_env, env = _envs(kind, num_envs)
    torch.manual_seed(0)
    actor = mlp_actor(env, hidden=(16,))
    policy = lean_policy(actor) if lean else actor
    kwargs = {"frames_per_batch": num_envs * steps}
    reference = Collector(reference_env, policy, total_frames=-1, track_traj_ids=False, **kwargs)
    collector = SegmentCollector(env, policy, **kwargs)
    # The lean policy acts on the vector environments' tensors, without a TensorDict.
    assert collector._on_tensors == (lean and kind.endswith(("gymnasium", "envpool")))
    ends = 0
    for seed in (3, 4):
        reference.set_seed(seed)
        reference.reset()
        collector.set_seed(seed)
        for _ in range(3):
            torch.manual_seed(seed)
            expected = next(iter(reference))
            torch.manual_seed(seed)
            batch = next(iter(collector))
            assert batch.batch_size == (num_envs, steps)
            assert set(batch.keys(True, True)) == set(expected.keys(True, True))
            for key in expected.keys(True, True):
                assert torch.equal(batch[key], expected[key]), key
            ends += int(batch["next", "done"].sum())
    assert ends > 0  # the comparison crossed episode ends and resets
    assert collector.state_dict()["frames"] == 6 * num_envs * steps
    reference.shutdown()
    collector.shutdown()


@pytest.mark.parametrize("lean", [True, False], ids=["lean-policy", "actor"])
def test_segments_of_one_step_are_those_of_torchrls_collector(lean):
    reference_env, env = _envs("CartPole-v1:gymnasium", 4)
    torch.manual_seed(0)
    actor = mlp_actor(env, hidden=(8,))
    policy = lean_policy(actor) if lean else actor
    reference = Collector(reference_env, policy, frames_per_batch=4, total_frames=-1,
                          track_traj_ids=False)  # fmt: skip
    collector = SegmentCollector(env, policy, frames_per_batch=4)
    reference.set_seed(2)
    reference.reset()
    collector.set_seed(2)
    ends = 0
    for step in range(60):
        torch.manual_seed(step)  # the same random stream for both
        expected = next(iter(reference))
        torch.manual_seed(step)
        batch = next(iter(collector))
        assert batch.batch_size == (4, 1)
        for key in expected.keys(True, True):
            assert torch.equal(batch[key], expected[key]), key
        ends += int(batch["next", "done"].sum())
    assert ends > 0  # across episode ends and resets
    reference.shutdown()
    collector.shutdown()


def _lazy(root: TensorDict):
    return LazyStackedTensorDict.lazy_stack(list(root.unbind(0)), 0)


@pytest.mark.parametrize("form", ["tensordict", "lazy", "dict"])
def test_stacked_roots_are_torch_stack_of_them(form):
    """``stacked`` builds what ``torch.stack(roots, dim=1)`` does, faster: nested entries,
    lazily stacked roots, and the done flags that every root shares (all-False, one tensor
    for all: built as zeros) or not (a shared flag that is set is stacked as it is)."""
    torch.manual_seed(0)
    clear, raised = torch.zeros(3, 1, dtype=torch.bool), torch.ones(3, 1, dtype=torch.bool)
    nested = form == "tensordict"
    roots = [
        TensorDict({
            "observation": torch.randn(3, 2), "done": clear, "truncated": raised,
            "terminated": torch.zeros(3, 1, dtype=torch.bool),
            **({"agent": {"hidden": torch.randn(3, 4)}} if nested else {}),
        }, batch_size=[3])
        for _ in range(4)
    ]  # fmt: skip
    expected = torch.stack(roots, dim=1)
    given = {
        "tensordict": roots, "lazy": [_lazy(root) for root in roots],
        "dict": [dict(root.items()) for root in roots],
    }[form]  # fmt: skip
    batch = stacked(given, torch.Size([3]), None, cleared=("done", "terminated", "truncated"))
    assert batch.batch_size == (3, 4)
    assert set(batch.keys(True, True)) == set(expected.keys(True, True))
    for key in expected.keys(True, True):
        assert torch.equal(batch[key], expected[key]), key


@pytest.mark.parametrize("frames", [10, 0, -4])
def test_a_batch_size_that_is_no_positive_multiple_is_refused(frames):
    env = gym_env("CartPole-v1", num_envs=4)
    with pytest.raises(ValueError, match=f"positive multiple of the 4 .* got {frames}"):
        SegmentCollector(env, mlp_actor(env, hidden=(4,)), frames_per_batch=frames)


def test_one_environment_gives_batches_of_its_steps():
    """Batch size []: the batch is [T], as TorchRL's Collector gives it (down to one step)."""
    reference_env, env = gym_env("CartPole-v1"), gym_env("CartPole-v1")
    torch.manual_seed(0)
    actor = mlp_actor(env, hidden=(8,))
    reference = Collector(reference_env, actor, frames_per_batch=50, total_frames=-1)
    collector = SegmentCollector(env, actor, frames_per_batch=50)
    reference.set_seed(1)
    reference.reset()
    collector.set_seed(1)
    for _ in range(2):
        torch.manual_seed(2)
        expected = next(iter(reference))
        torch.manual_seed(2)
        batch = next(iter(collector))
        assert batch.batch_size == expected.batch_size == (50,)
        for key in ("action", "observation", ("next", "observation"), ("next", "done")):
            assert torch.equal(batch[key], expected[key]), key
    reference.shutdown()
    collector.shutdown()
    env = gym_env("CartPole-v1")
    single = SegmentCollector(env, actor, frames_per_batch=1)
    assert single.next().batch_size == (1,)
    single.shutdown()


def test_a_policy_without_an_action_is_named():
    from tensordict.nn import TensorDictModule

    env = gym_env("CartPole-v1", num_envs=2)
    silent = TensorDictModule(torch.nn.Linear(4, 2), ["observation"], ["logits"])
    with pytest.raises(KeyError, match=r"wrote no 'action' entry.*'logits'"):
        SegmentCollector(env, silent, 8).next()


def test_total_frames_ends_the_iteration():
    env = gym_env("CartPole-v1", num_envs=2)
    actor = mlp_actor(env, hidden=(4,))
    collector = SegmentCollector(env, actor, 8, total_frames=24)
    assert [b.batch_size for b in collector] == [torch.Size([2, 4])] * 3
    assert list(SegmentCollector(env, actor, 8, total_frames=0)) == []
    endless = iter(SegmentCollector(env, actor, 8))  # the default: -1, no end
    assert len(list(itertools.islice(endless, 4))) == 4
    collector.shutdown()
    assert env.is_closed


def test_shutdown_closes_the_environments_it_steps():
    import gymnasium

    vector = gymnasium.make_vec(
        "CartPole-v1",
        num_envs=2,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": gymnasium.vector.AutoresetMode.DISABLED},
    )
    env = VectorGymEnv(vector)
    assert not env.is_closed
    collector = SegmentCollector(env, mlp_actor(env, hidden=(4,)), 8)
    collector.next()
    collector.shutdown()
    assert env.is_closed and vector.closed
    collector.shutdown()  # again: nothing is left to close


def test_done_flags_a_policy_writes_into_its_input_are_kept():
    """The roots' done flags are one shared all-False tensor that the batch rebuilds in
    one go; a policy that writes flags of its own keeps them in the batch."""
    from tensordict.nn import TensorDictModule, TensorDictSequential

    env = gym_env("CartPole-v1", num_envs=3)
    actor = mlp_actor(env, hidden=(4,))
    flags = TensorDictModule(lambda obs: obs[..., :1] > 0, ["observation"], ["truncated"])
    collector = SegmentCollector(env, TensorDictSequential(actor, flags), frames_per_batch=30)
    batch = collector.next()
    written = batch["observation"][..., :1] > 0
    assert written.any() and not written.all()
    assert torch.equal(batch["truncated"], written)
    assert not batch["done"].any() and not batch["terminated"].any()
    collector.shutdown()


@pytest.mark.parametrize("where", ["policy", "everywhere"])
def test_a_hooked_lean_policy_is_called_at_every_step(where):
    """A forward hook on the lean policy (or on every module) still sees every step,
    and the batches stay those of the policy without the hook."""
    envs = [gym_env("CartPole-v1", num_envs=3) for _ in range(2)]
    torch.manual_seed(0)
    policy = lean_policy(mlp_actor(envs[0], hidden=(8,)))
    plain, hooked = (SegmentCollector(env, policy, frames_per_batch=30) for env in envs)
    for collector in (plain, hooked):
        collector.set_seed(1)
    torch.manual_seed(1)
    expected = plain.next()
    calls = []

    def hook(module, args, output):
        if module is policy:
            calls.append(args[0].batch_size)

    if where == "policy":
        handle = policy.register_forward_hook(hook)
    else:
        handle = torch.nn.modules.module.register_module_forward_hook(hook)
    try:
        torch.manual_seed(1)
        batch = hooked.next()
    finally:
        handle.remove()
    assert calls == [torch.Size([3])] * 10
    for key in expected.keys(True, True):
        assert torch.equal(batch[key], expected[key]), key
    for collector in (plain, hooked):
        collector.shutdown()
