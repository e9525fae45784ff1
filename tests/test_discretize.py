"""DiscretizeAction: tables, round trips, specs in serial/parallel envs, collector, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torchrl.collectors import Collector
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import GymEnv, ParallelEnv, SerialEnv, TransformedEnv, check_env_specs

from rl_pg import DiscretizeAction
from rl_pg.envs import DRIVING_ACTIONS


def _box(low, high, batch=()) -> Composite:
    low, high = torch.tensor(low), torch.tensor(high)
    spec = Bounded(low=low, high=high, shape=low.shape)
    if batch:
        spec = spec.expand(*batch, *low.shape)
    return Composite(action=spec, shape=batch)


def _bound(transform: DiscretizeAction, low=(-1.0, -1.0), high=(1.0, 1.0), batch=()):
    """Runs the spec transform on a box, as an environment would."""
    return transform.transform_action_spec(_box(list(low), list(high), batch))


def _pendulum():
    return GymEnv("Pendulum-v1")


def _highway():
    import highway_env  # noqa: F401  (registers the environments)

    return GymEnv("highway-fast-v0", config={"action": {"type": "ContinuousAction"}})


class TestDiscretizeAction:
    def test_joint_grid_is_row_major(self):
        transform = DiscretizeAction(counts=(3, 3))
        spec = _bound(transform)
        assert spec["action"].n == 9
        expected = [[x, y] for x in (-1.0, 0.0, 1.0) for y in (-1.0, 0.0, 1.0)]
        assert transform.table.tolist() == expected
        i, j = 2, 0
        assert transform.to_continuous(torch.tensor(3 * i + j)).tolist() == [1.0, -1.0]

    def test_explicit_table_reproduces_the_driving_actions(self):
        transform = DiscretizeAction(actions=DRIVING_ACTIONS)
        _bound(transform)
        for i, x in enumerate((1.0, 0.0, -1.0)):
            for j, y in enumerate((0.6, 0.0, -0.6)):
                action = transform.to_continuous(torch.tensor(3 * i + j))
                torch.testing.assert_close(action, torch.tensor([x, y]))

    def test_single_value_is_the_midpoint(self):
        transform = DiscretizeAction(counts=(1, 2))
        _bound(transform, low=(0.0, -2.0), high=(4.0, 2.0))
        assert transform.table.tolist() == [[2.0, -2.0], [2.0, 2.0]]

    @settings(max_examples=60, deadline=None)
    @given(
        counts=st.lists(st.integers(1, 4), min_size=1, max_size=3),
        mode=st.sampled_from(["joint", "per_dim"]),
        one_hot=st.booleans(),
        seed=st.integers(0, 2**16),
    )
    def test_round_trip(self, counts, mode, one_hot, seed):
        generator = torch.Generator().manual_seed(seed)
        low = torch.rand(len(counts), generator=generator) * -3
        high = low + 0.5 + torch.rand(len(counts), generator=generator) * 3
        transform = DiscretizeAction(counts=counts, mode=mode, one_hot=one_hot)
        spec = _bound(transform, low.tolist(), high.tolist(), batch=(5,))["action"]
        # discrete -> continuous -> discrete is the identity
        discrete = spec.rand()
        if one_hot:
            discrete = discrete.long()
        continuous = transform.to_continuous(discrete)
        assert continuous.shape == (5, len(counts))
        assert ((continuous >= low) & (continuous <= high)).all()
        index = transform.to_index(continuous)
        expected = discrete
        if one_hot:
            if mode == "joint":
                expected = discrete.argmax(-1)
            else:
                chunks = discrete.split(counts, dim=-1)
                expected = torch.stack([c.argmax(-1) for c in chunks], -1)
        assert torch.equal(index, expected)
        # continuous -> discrete picks the nearest action of the grid
        point = low + torch.rand(5, len(counts), generator=generator) * (high - low)
        nearest = transform.to_continuous(
            transform.to_index(point)
            if not one_hot
            else _one_hot(transform.to_index(point), counts, mode)
        )
        scale = high - low
        chosen = (((point - nearest) / scale) ** 2).sum(-1)
        every = (((point.unsqueeze(1) - transform.table) / scale) ** 2).sum(-1)
        assert (chosen <= every.min(-1).values + 1e-6).all()

    def test_table_nearest_index(self):
        transform = DiscretizeAction(actions=DRIVING_ACTIONS)
        _bound(transform)
        points = torch.tensor([[0.9, 0.5], [-0.2, -0.1], [-0.8, -0.7]])
        assert transform.to_index(points).tolist() == [0, 4, 8]

    def test_table_nearest_index_on_unequal_bounds_scales_each_dimension(self):
        # Steering in [0, 1] and throttle in [-10, 10]: measured in raw units the
        # throttle's 1.5 would outweigh the steering's 0.9; measured as shares of each
        # range (0.075 and 0.9), the steering decides.
        transform = DiscretizeAction(actions=[[0.0, 0.0], [1.0, 2.0]])
        _bound(transform, low=(0.0, -10.0), high=(1.0, 10.0))
        points = torch.tensor([[0.9, 0.5], [0.1, 1.5], [0.6, -10.0]])
        assert transform.to_index(points).tolist() == [1, 0, 1]

    @pytest.mark.parametrize("mode", ["joint", "per_dim"])
    def test_nearest_index_of_a_batch_of_segments(self, mode):
        # [B, T, d] actions, as a collector's batch holds them: each step on its own.
        transform = DiscretizeAction(counts=(3, 5), mode=mode)
        _bound(transform, low=(-1.0, 0.0), high=(1.0, 4.0))
        points = torch.rand(2, 4, 2) * torch.tensor([2.0, 4.0]) + torch.tensor([-1.0, 0.0])
        index = transform.to_index(points)
        assert index.shape == ((2, 4) if mode == "joint" else (2, 4, 2))
        flat = transform.to_index(points.reshape(8, 2))
        assert index.reshape(flat.shape).tolist() == flat.tolist()

    def test_a_table_of_one_dimension(self):
        transform = DiscretizeAction(actions=[[-1.0], [0.5]])
        spec = _bound(transform, low=(-1.0,), high=(1.0,))
        assert spec["action"].n == 2
        assert transform.to_index(torch.tensor([[0.9], [-0.7]])).tolist() == [1, 0]

    def test_counts_as_one_number_of_any_kind(self):
        for counts in (3, np.int64(3), torch.tensor(3)):
            transform = DiscretizeAction(counts=counts)
            assert transform.counts == [3] and _bound(transform)["action"].n == 9

    def test_what_the_spec_gives_is_no_state(self):
        # The table and bounds come from the environment's spec: a state_dict holds
        # none of them, so one saved before the spec was seen loads after, and back.
        built, fresh = DiscretizeAction(counts=3), DiscretizeAction(counts=3)
        _bound(built)
        assert built.state_dict().keys() == fresh.state_dict().keys()
        fresh.load_state_dict(built.state_dict())

    def test_repr_names_what_the_actions_come_from(self):
        assert repr(DiscretizeAction(counts=(2, 3))).startswith("DiscretizeAction(counts=[2, 3],")
        table = repr(DiscretizeAction(actions=[[0.0, 1.0]]))
        assert table.startswith("DiscretizeAction(actions=<table>,")

    def test_one_hot_spec(self):
        spec = _bound(DiscretizeAction(counts=3, one_hot=True))["action"]
        assert spec.shape == (9,) and spec.rand().sum() == 1

    def test_per_dim_spec(self):
        spec = _bound(DiscretizeAction(counts=(2, 5), mode="per_dim"))["action"]
        assert spec.nvec.tolist() == [2, 5]

    def test_pendulum_specs(self):
        env = TransformedEnv(_pendulum(), DiscretizeAction(counts=7))
        check_env_specs(env)
        assert env.rollout(5)["action"].dtype == torch.int64

    @pytest.mark.parametrize("mode", ["joint", "per_dim"])
    @pytest.mark.parametrize("one_hot", [False, True])
    def test_pendulum_specs_every_output(self, mode, one_hot):
        check_env_specs(
            TransformedEnv(_pendulum(), DiscretizeAction(counts=3, mode=mode, one_hot=one_hot))
        )

    def test_serial_env_transform_outside(self):
        check_env_specs(TransformedEnv(SerialEnv(2, _pendulum), DiscretizeAction(counts=5)))

    def test_serial_env_transform_inside(self):
        check_env_specs(
            SerialEnv(2, lambda: TransformedEnv(_pendulum(), DiscretizeAction(counts=5)))
        )

    def test_parallel_env(self):
        # One worker each: the transform still crosses the process boundary (the
        # two-worker case is test_highway_parallel_env's).
        outside = TransformedEnv(ParallelEnv(1, _pendulum), DiscretizeAction(counts=5))
        inside = ParallelEnv(1, _discretized_pendulum)
        try:
            check_env_specs(outside)
            check_env_specs(inside)
        finally:
            outside.close()
            inside.close()

    def test_highway_specs(self):
        env = TransformedEnv(_highway(), DiscretizeAction(actions=DRIVING_ACTIONS))
        check_env_specs(env)
        assert env.action_spec.n == 9

    def test_highway_serial_env(self):
        check_env_specs(SerialEnv(2, _discretized_highway))

    def test_highway_parallel_env(self):
        env = ParallelEnv(2, _discretized_highway)
        try:
            check_env_specs(env)
        finally:
            env.close()

    def test_highway_collector(self):
        collector = Collector(
            _discretized_highway(), policy=None, frames_per_batch=8, total_frames=8
        )
        (batch,) = list(collector)
        collector.shutdown()
        assert ((batch["action"] >= 0) & (batch["action"] < 9)).all()

    def test_collector(self):
        env = TransformedEnv(_pendulum(), DiscretizeAction(counts=5))
        collector = Collector(env, policy=None, frames_per_batch=16, total_frames=32)
        batches = list(collector)
        collector.shutdown()
        assert len(batches) == 2
        action = batches[0]["action"]
        assert action.dtype == torch.int64 and ((action >= 0) & (action < 5)).all()


def _discretized_pendulum():
    return TransformedEnv(_pendulum(), DiscretizeAction(counts=5))


def _discretized_highway():
    return TransformedEnv(_highway(), DiscretizeAction(actions=DRIVING_ACTIONS))


def _one_hot(index, counts, mode):
    if mode == "joint":
        n = 1
        for c in counts:
            n *= c
        return torch.nn.functional.one_hot(index, n)
    return torch.cat(
        [torch.nn.functional.one_hot(index[..., k], c) for k, c in enumerate(counts)], -1
    )


class TestDiscretizeActionErrors:
    @pytest.mark.parametrize(
        ("counts", "match"),
        [
            (0, r"counts\[0\] must be an integer >= 1"),
            ((3, 0), r"counts\[1\] must be"),
            ((2, -1), r"counts\[1\] must be"),
            ((), "at least one integer"),
        ],
    )
    def test_counts_below_one(self, counts, match):
        with pytest.raises(ValueError, match=match):
            DiscretizeAction(counts=counts)

    @pytest.mark.parametrize("counts", [2.5, True, "3", (3, 2.0)])
    def test_counts_that_are_not_integers(self, counts):
        with pytest.raises(TypeError, match=r"counts\[\d\] must be an integer"):
            DiscretizeAction(counts=counts)

    def test_numpy_counts(self):
        transform = DiscretizeAction(counts=np.array([3, 2]))
        _bound(transform)
        assert transform.table.shape == (6, 2)

    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_table_that_is_not_finite(self, bad):
        with pytest.raises(ValueError, match=r"actions row 1 .* is not finite"):
            DiscretizeAction(actions=[[0.0, 0.0], [bad, 0.5]])

    def test_table_of_strings(self):
        with pytest.raises(TypeError, match=r"actions must be an \[N, action_dim\] table"):
            DiscretizeAction(actions=[["left", "right"]])

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"one_hot": 1}, "one_hot must be True or False"),
            ({"action_key": 3}, "action_key must be a string or a tuple of strings"),
            ({"action_key": ()}, "action_key must be a string or a tuple of strings"),
        ],
    )
    def test_bad_options(self, kwargs, match):
        with pytest.raises(TypeError, match=match):
            DiscretizeAction(counts=3, **kwargs)

    @pytest.mark.parametrize("index", [torch.tensor([1.5]), torch.tensor([float("nan")])])
    def test_fractional_index(self, index):
        transform = DiscretizeAction(counts=3)
        _bound(transform)
        with pytest.raises(ValueError, match="Discrete actions must be whole numbers"):
            transform.to_continuous(index)

    def test_whole_float_index(self):
        transform = DiscretizeAction(counts=3)
        _bound(transform)
        torch.testing.assert_close(
            transform.to_continuous(torch.tensor([4.0])), transform.to_continuous(torch.tensor([4]))
        )

    def test_boolean_index(self):
        transform = DiscretizeAction(counts=3)
        _bound(transform)
        with pytest.raises(TypeError, match=r"must be integer indices, got dtype torch\.bool"):
            transform.to_continuous(torch.tensor([True]))

    @pytest.mark.parametrize(
        "row", [[0, 0, 0, 0], [1, 1, 0, 0], [0.5, 0.5, 0, 0], [2, 0, 0, 0], [-1, 1, 1, 0]]
    )
    def test_row_that_is_not_one_hot(self, row):
        transform = DiscretizeAction(counts=(2, 2), one_hot=True)
        _bound(transform)
        with pytest.raises(ValueError, match="must hold a single 1 and zeros elsewhere"):
            transform.to_continuous(torch.tensor([row], dtype=torch.float32))

    def test_one_hot_of_the_wrong_width(self):
        transform = DiscretizeAction(counts=(2, 2), one_hot=True)
        _bound(transform)
        with pytest.raises(ValueError, match=r"One-hot actions have 4 columns, got shape \(1, 3\)"):
            transform.to_continuous(torch.tensor([[0, 1, 0]], dtype=torch.bool))

    def test_index_one_past_the_last(self):
        transform = DiscretizeAction(counts=(2, 2))
        _bound(transform)
        with pytest.raises(
            ValueError, match=r"out of range: got values in \[4, 4\], expected \[0, 3\]"
        ):
            transform.to_continuous(torch.tensor([4]))

    def test_per_dim_one_hot_of_the_wrong_width(self):
        transform = DiscretizeAction(counts=(2, 3), mode="per_dim", one_hot=True)
        _bound(transform)
        with pytest.raises(ValueError, match=r"one-hot actions have 5 columns"):
            transform.to_continuous(torch.tensor([[1, 0, 0, 1]], dtype=torch.bool))

    def test_per_dim_row_that_is_not_one_hot(self):
        transform = DiscretizeAction(counts=(2, 3), mode="per_dim", one_hot=True)
        _bound(transform)
        with pytest.raises(ValueError, match="single 1 and zeros elsewhere"):
            transform.to_continuous(torch.tensor([[1, 0, 0, 0, 0]], dtype=torch.bool))

    def test_per_dim_index_of_the_wrong_width(self):
        transform = DiscretizeAction(counts=(2, 3), mode="per_dim")
        _bound(transform)
        with pytest.raises(ValueError, match=r"one index per dimension \(\[\*B, 2\]\)"):
            transform.to_continuous(torch.tensor([[1, 0, 2]]))

    def test_non_finite_continuous_action(self):
        transform = DiscretizeAction(counts=3)
        _bound(transform)
        with pytest.raises(ValueError, match="to_index got non-finite actions"):
            transform.to_index(torch.tensor([[0.0, float("nan")]]))

    def test_mapping_something_that_is_not_a_tensor(self):
        transform = DiscretizeAction(counts=3)
        _bound(transform)
        with pytest.raises(TypeError, match=r"action must be a torch\.Tensor"):
            transform.to_continuous([0, 1])

    def test_neither_counts_nor_actions(self):
        with pytest.raises(ValueError, match=r"exactly one of counts= .* or actions="):
            DiscretizeAction()

    def test_both_counts_and_actions(self):
        with pytest.raises(ValueError, match="exactly one of counts="):
            DiscretizeAction(counts=3, actions=DRIVING_ACTIONS)

    def test_unknown_mode(self):
        with pytest.raises(ValueError, match="mode must be one of"):
            DiscretizeAction(counts=3, mode="grid")

    def test_per_dim_with_a_table(self):
        with pytest.raises(ValueError, match=r"mode='per_dim' .* needs counts="):
            DiscretizeAction(actions=DRIVING_ACTIONS, mode="per_dim")

    def test_empty_table(self):
        with pytest.raises(ValueError, match=r"non-empty \[N, action_dim\] table"):
            DiscretizeAction(actions=torch.zeros(0, 2))

    def test_table_of_the_wrong_width(self):
        with pytest.raises(ValueError, match="actions has 3 columns but the action space has 2"):
            _bound(DiscretizeAction(actions=[[0.0, 0.0, 0.0]]))

    def test_table_outside_the_bounds(self):
        with pytest.raises(ValueError, match=r"actions row 1 \[0.0, 1.5\] lies outside"):
            _bound(DiscretizeAction(actions=[[0.0, 0.0], [0.0, 1.5]]))

    def test_counts_of_the_wrong_length(self):
        with pytest.raises(ValueError, match="counts has 3 entries but the action space has 2"):
            _bound(DiscretizeAction(counts=(2, 2, 2)))

    def test_infinite_bounds(self):
        with pytest.raises(ValueError, match="needs finite bounds"):
            _bound(DiscretizeAction(counts=3), low=(-float("inf"), 0.0), high=(1.0, 1.0))

    def test_unbounded_spec(self):
        spec = Composite(action=Unbounded(shape=(2,)))
        with pytest.raises(TypeError, match="needs a bounded continuous action spec"):
            DiscretizeAction(counts=3).transform_action_spec(spec)

    def test_discrete_env(self):
        with pytest.raises(TypeError, match=r"bounded continuous action spec .* got OneHot"):
            _ = TransformedEnv(GymEnv("CartPole-v1"), DiscretizeAction(counts=3)).action_spec

    def test_index_out_of_range(self):
        transform = DiscretizeAction(counts=3)
        _bound(transform)
        with pytest.raises(ValueError, match=r"index out of range: got values in \[-1, 2\]"):
            transform.to_continuous(torch.tensor([2, -1]))

    def test_continuous_action_of_the_wrong_width(self):
        transform = DiscretizeAction(counts=3)
        _bound(transform)
        with pytest.raises(ValueError, match=r"expects actions of shape \[\*B, 2\]"):
            transform.to_index(torch.zeros(4, 3))

    def test_mapping_before_an_environment(self):
        with pytest.raises(RuntimeError, match="append it to an env"):
            DiscretizeAction(counts=3).to_continuous(torch.tensor(0))
