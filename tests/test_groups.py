"""Group baselines: the kernel against a plain loop, its checks, and the greedy policy."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from rl_pg.greedy_play import GreedyInGroups
from rl_pg.groups import GROUP_BASELINES, batch_group_advantage, group_advantage


def reference_advantage(returns, group, baseline, greedy, scale, eps=1e-8):
    """Episode by episode, position by position, over Python lists."""
    n, width = len(returns), len(returns[0])
    out = [[0.0] * width for _ in range(n)]
    for i in range(n):
        if greedy[i]:
            continue
        mates = [j for j in range(n) if group[j] == group[i] and not greedy[j]]
        for t in range(width):
            values = [returns[j][t] for j in mates]
            if baseline == "leave_one_out":
                others = [returns[j][t] for j in mates if j != i]
                b = sum(others) / len(others)
            elif baseline == "group_mean":
                b = sum(values) / len(values)
            else:
                (g,) = [j for j in range(n) if group[j] == group[i] and greedy[j]]
                b = returns[g][t]
            a = returns[i][t] - b
            if scale:
                mean = sum(values) / len(values)
                std = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))
                a /= std + eps
            out[i][t] = a
    return out


@st.composite
def group_problems(draw):
    """Episodes in groups of random sizes (in any order), with or without a greedy one."""
    baseline = draw(st.sampled_from(GROUP_BASELINES))
    scale = draw(st.booleans())
    least = 2 if (baseline != "greedy" or scale) else 1
    sizes = draw(st.lists(st.integers(least, 5), min_size=1, max_size=4))
    ids = draw(st.lists(st.integers(-50, 50), min_size=len(sizes), max_size=len(sizes),
                        unique=True))  # fmt: skip
    group, greedy = [], []
    for gid, size in zip(ids, sizes, strict=True):
        group += [gid] * (size + (baseline == "greedy"))
        greedy += [False] * size + [True] * (baseline == "greedy")
    order = draw(st.permutations(range(len(group))))
    group, greedy = [group[i] for i in order], [greedy[i] for i in order]
    width = draw(st.integers(1, 6))
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    seed = draw(st.integers(0, 2**31 - 1))
    returns = torch.randn(len(group), width, generator=torch.Generator().manual_seed(seed))
    return baseline, scale, returns.to(dtype), torch.tensor(group), torch.tensor(greedy)


class TestGroupAdvantage:
    @settings(max_examples=300, deadline=None)
    @given(problem=group_problems())
    def test_matches_a_plain_loop(self, problem):
        baseline, scale, returns, group, greedy = problem
        out = group_advantage(
            returns,
            group,
            baseline=baseline,
            greedy=greedy if baseline == "greedy" else None,
            scale=scale,
        )
        expected = reference_advantage(
            returns.double().tolist(), group.tolist(), baseline, greedy.tolist(), scale
        )
        # float32: sums of a few values in another order, then (scale) a division by a
        # standard deviation that can be small, which carries their rounding (~1e-7
        # relative) up to about 1e-4.
        tol = 1e-3 if returns.dtype == torch.float32 else 1e-10
        torch.testing.assert_close(
            out.double(), torch.tensor(expected, dtype=torch.float64), rtol=tol, atol=tol
        )
        assert out.dtype == returns.dtype

    def test_leave_one_out_is_the_group_mean_advantage_scaled_by_k_over_k_minus_one(self):
        returns = torch.randn(12, 3, dtype=torch.float64)
        group = torch.arange(12) // 4
        mean = group_advantage(returns, group, baseline="group_mean")
        torch.testing.assert_close(group_advantage(returns, group), mean * 4 / 3)

    def test_equal_returns_give_no_advantage_even_scaled(self):
        returns = torch.ones(4, 2)
        out = group_advantage(returns, torch.zeros(4, dtype=torch.long), scale=True)
        assert torch.equal(out, torch.zeros(4, 2))

    @pytest.mark.parametrize(
        ("kwargs", "error", "match"),
        [
            ({"baseline": "median"}, ValueError, "baseline must be one of"),
            ({"returns": torch.ones(4, 1, dtype=torch.long)}, TypeError, "floating-point"),
            ({"group": torch.zeros(4)}, TypeError, "group must be an integer"),
            ({"returns": torch.ones(4)}, ValueError, r"\[episodes, positions\]"),
            ({"group": torch.zeros(3, dtype=torch.long)}, ValueError, "group"),
            ({"group": torch.tensor([0, 0, 0, 1])}, ValueError, "at least 2 sampled"),
            ({"greedy": torch.tensor([0, 0, 0, 1])}, ValueError, "boolean"),
            ({"greedy": torch.tensor([False, False, False, True])}, ValueError,
             "only baseline='greedy' reads"),
            ({"baseline": "greedy"}, ValueError, "exactly one greedy episode"),
            ({"baseline": "greedy", "greedy": torch.tensor([True, True, False, False])},
             ValueError, "exactly one greedy episode in each group; a group has 2"),
            ({"baseline": "greedy", "greedy": torch.tensor([False, True, False, True]),
              "group": torch.tensor([0, 0, 1, 1]), "scale": True}, ValueError,
             "with scale needs at least 2"),
        ],
    )  # fmt: skip
    def test_bad_input_is_refused(self, kwargs, error, match):
        args = {"returns": torch.ones(4, 1), "group": torch.zeros(4, dtype=torch.long)}
        args.update(kwargs)
        with pytest.raises(error, match=match):
            group_advantage(args.pop("returns"), args.pop("group"), **args)


def _rows_of_episodes() -> TensorDict:
    """Two rows of whole episodes, [2, 6], each step's end said by two flags (terminated,
    truncated); groups 0 and 1, each with one greedy episode."""
    ends = torch.tensor([[0, 1, 1, 0, 0, 1], [1, 0, 1, 0, 1, 1]], dtype=torch.bool)
    group = torch.tensor([[0, 0, 0, 1, 1, 1], [1, 0, 0, 1, 1, 0]]).unsqueeze(-1)
    greedy = torch.tensor([[0, 0, 1, 0, 0, 0], [1, 0, 0, 0, 0, 0]], dtype=torch.bool)
    return TensorDict(
        {"group": group, "greedy": greedy.unsqueeze(-1),
         "next": {"done": torch.stack([ends, torch.zeros_like(ends)], -1)}},
        [2, 6],
    )  # fmt: skip


class TestBatchGroupAdvantage:
    @pytest.mark.parametrize("baseline", GROUP_BASELINES)
    @pytest.mark.parametrize("scale", [False, True])
    def test_rows_of_episodes_are_the_same_episodes_laid_end_to_end(self, baseline, scale):
        # The advantages of the same steps laid out flat, and those of the episodes'
        # table by group_advantage itself.
        rows = _rows_of_episodes()
        to_go = torch.randn(2, 6, 1, generator=torch.Generator().manual_seed(0))
        kwargs = {"baseline": baseline, "scale": scale}
        by_rows = batch_group_advantage(rows, to_go, **kwargs)
        laid_out = batch_group_advantage(rows.reshape(-1), to_go.reshape(-1, 1), **kwargs)
        assert by_rows.shape == (2, 6, 1)
        torch.testing.assert_close(by_rows.reshape(-1, 1), laid_out)
        # episodes (row, start, length) in order, each step's return at its position
        episodes = [(0, 0, 2), (0, 2, 1), (0, 3, 3), (1, 0, 1), (1, 1, 2), (1, 3, 2), (1, 5, 1)]
        table = torch.zeros(len(episodes), 3)
        for e, (row, start, length) in enumerate(episodes):
            table[e, :length] = to_go[row, start : start + length, 0]
        group = torch.tensor([rows["group"][r, t, 0] for r, t, _ in episodes])
        greedy = torch.tensor([bool(rows["greedy"][r, t, 0]) for r, t, _ in episodes])
        expected = group_advantage(
            table, group, greedy=greedy if baseline == "greedy" else None, **kwargs
        )
        for e, (row, start, length) in enumerate(episodes):
            torch.testing.assert_close(
                by_rows[row, start : start + length, 0], expected[e, :length]
            )

    def test_a_batch_of_one_row(self):
        rows = _rows_of_episodes()[1:]  # two episodes of each group
        to_go = torch.arange(6.0).reshape(1, 6, 1)
        assert batch_group_advantage(rows, to_go).shape == (1, 6, 1)

    @pytest.mark.parametrize(
        ("key", "value", "error", "match"),
        [
            ("group", torch.zeros(2, 6, 2, dtype=torch.long), ValueError, "one value per step"),
            ("group", torch.zeros(2, 6, 1), TypeError, r"group ids, got dtype torch\.float32"),
            ("group", torch.zeros(2, 6, 1, dtype=torch.bool), TypeError, "integer group ids"),
            ("greedy", torch.zeros(2, 6, 1, dtype=torch.long), TypeError,
             r"must be boolean, got dtype torch\.int64"),
        ],
    )  # fmt: skip
    def test_steps_that_do_not_carry_one_id_or_flag_each_are_refused(
        self, key, value, error, match
    ):
        rows = _rows_of_episodes().set(key, value)
        with pytest.raises(error, match=match):
            batch_group_advantage(rows, torch.zeros(2, 6, 1), baseline="greedy")

    def test_what_is_refused_is_named_by_its_kind(self):
        with pytest.raises(TypeError, match="returns must be a floating-point tensor, got list"):
            group_advantage([[1.0]], torch.zeros(1, dtype=torch.long))
        with pytest.raises(
            TypeError, match=r"group must be an integer tensor, got a torch\.float32 tensor"
        ):
            group_advantage(torch.ones(2, 1), torch.zeros(2))


def _actor(n_actions=3):
    return ProbabilisticActor(
        TensorDictModule(torch.nn.Linear(2, n_actions), ["observation"], ["logits"]),
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )


class TestGreedyInGroups:
    def test_the_last_environment_of_each_group_plays_the_most_probable_action(self):
        torch.manual_seed(0)
        actor, n = _actor(), 4 * 50
        policy = GreedyInGroups(actor, group_size=3)
        root = TensorDict({"observation": torch.randn(n, 2)}, batch_size=[n])
        with set_exploration_type(ExplorationType.RANDOM):
            out = policy(root.clone())
        argmax = actor.module[0](root.clone())["logits"].argmax(-1)
        greedy = torch.arange(n) % 4 == 3
        assert torch.equal(out["action"][greedy], argmax[greedy])
        # The others sample: some differ from the argmax (3 actions, random logits).
        assert not torch.equal(out["action"][~greedy], argmax[~greedy])

    def test_the_sampled_environments_act_as_the_policy_alone(self):
        actor, n = _actor(), 8
        root = TensorDict({"observation": torch.randn(n, 2)}, batch_size=[n])
        torch.manual_seed(3)
        alone = actor(root.clone())
        torch.manual_seed(3)
        out = GreedyInGroups(actor, group_size=1)(root.clone())
        sampled = torch.arange(n) % 2 == 0
        assert torch.equal(out["action"][sampled], alone["action"][sampled])

    def test_a_batch_that_is_no_multiple_of_the_groups_is_refused(self):
        policy = GreedyInGroups(_actor(), group_size=2)
        root = TensorDict({"observation": torch.randn(4, 2)}, batch_size=[4])
        with pytest.raises(ValueError, match="multiple of 3 environments"):
            policy(root)

    def test_a_policy_that_is_not_a_tensordict_module_is_refused(self):
        with pytest.raises(TypeError, match="TensorDictModule"):
            GreedyInGroups(torch.nn.Linear(2, 3), group_size=2)
