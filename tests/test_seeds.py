"""The seed streams of a run: disjoint, and where results were made, as they were."""

import itertools
import random

import pytest

from rl_pg.training import seeds
from rl_pg.training.seeds import (
    MEMBERS,
    STREAMS,
    confirmation_seed,
    evaluation_seed,
    fresh_seed,
    replay_seed,
    stream_seed,
    stream_span,
    training_seed,
)

P = 1_000_003


def _spans(seed):
    """Every (stream, first, count) of run ``seed``, the training span split at 2**31."""
    return [(name, first, count) for name in STREAMS for first, count in stream_span(name, seed)]


def _clashes(seed):
    spans = _spans(seed)
    return [
        (a[0], b[0])
        for i, a in enumerate(spans)
        for b in spans[i + 1 :]
        if a[0] != b[0] and a[1] < b[1] + b[2] and b[1] < a[1] + a[2]
    ]


def test_no_two_streams_of_a_run_share_a_seed_for_seeds_0_to_10000():
    clashes = {seed: _clashes(seed) for seed in range(10_001)}
    assert {seed: c for seed, c in clashes.items() if c} == {}


def test_no_two_streams_of_a_run_share_a_seed_far_above():
    rng = random.Random(0)
    for seed in [2**32 - 1, 2**31, 2**31 - 1, *(rng.randrange(2**32) for _ in range(3000))]:
        assert _clashes(seed) == [], seed
        for name in STREAMS[2:]:
            assert 0 <= stream_seed(name, seed) < 2**32


def test_the_check_sees_the_legacy_overlaps_it_removed():
    """Negative control: the streams as they were (evaluation s + P, fresh s + 2P,
    replay and confirmation both s + 3P) clash exactly where the new ones move."""

    def legacy_clash(seed, name, value):
        return any(
            value < first + count and first < value + MEMBERS
            for first, count in stream_span("training", seed)
        )

    assert [s for s in range(10) if legacy_clash(s, "evaluation", s + P)] == [1]
    assert [s for s in range(10) if legacy_clash(s, "fresh", s + 2 * P)] == [2]
    assert [s for s in range(10) if legacy_clash(s, "replay", s + 3 * P)] == [3]
    assert all(evaluation_seed(s) != s + P for s in (1, 2148, 4295))


@pytest.mark.parametrize("seed", [0, 4, 5, 9, 10, 1000, 10_000])
def test_stored_results_keep_their_streams(seed):
    """Every result in RESULTS.md was made with these values (bar the moved ones)."""
    assert training_seed(seed, 100) == (seed * P + 100) % 2**31
    assert evaluation_seed(seed) == seed + P
    assert fresh_seed(seed) == seed + 2 * P
    assert replay_seed(seed) == seed + 3 * P


def test_only_the_clashing_stream_of_a_run_moves():
    assert (fresh_seed(1), replay_seed(1)) == (2 * P + 1, 3 * P + 1)
    assert (evaluation_seed(2), replay_seed(2)) == (P + 2, 3 * P + 2)
    assert (evaluation_seed(3), fresh_seed(3)) == (P + 3, 2 * P + 3)
    # the moved ones lie above every training seed
    assert min(evaluation_seed(1), fresh_seed(2), replay_seed(3)) >= 2**31


def test_confirmation_is_apart_from_the_replays_and_laid_out_runs_apart():
    firsts = sorted(
        stream_seed(name, s) for s in range(2**10) for name in STREAMS[2:]
        if stream_seed(name, s) >= 2**31
    )  # fmt: skip
    assert all(b - a >= MEMBERS for a, b in itertools.pairwise(firsts))
    assert all(confirmation_seed(s) != replay_seed(s) for s in range(1000))


def test_unknown_stream_is_refused_by_name():
    with pytest.raises(ValueError, match=r"Unknown seed stream 'eval'.*training_seed"):
        stream_seed("eval", 0)
    with pytest.raises(ValueError, match="training_seed"):
        stream_seed("training", 0)
    assert seeds.stream_span("actions", 3) == []
