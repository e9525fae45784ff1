"""Every seed a run derives from its own, in one place.

A run with seed ``s`` plays several random streams. Each is a named entry of
``STREAMS``; a batched environment (or a set of worker processes) seeds its members
``seed, seed + 1, …``, so a stream occupies a span of seeds, not one:

- ``training``: the training environments, reseeded at each restart after ``u``
  updates: ``s·P + u`` (mod 2³¹);
- ``actions``: torch's, numpy's and Python's generators (initial weights, sampled
  actions): ``s`` (other generators than the environments');
- ``confirmation``: the episodes that confirm a candidate for ``best.pt``: laid out
  (below);
- ``evaluation``: the evaluations during training (the same start states every time):
  ``s + P``;
- ``fresh``: ``rl-pg evaluate``'s episodes after training: ``s + 2·P``;
- ``replay``: ``rl-pg tune --objective held_out``'s replays of a trial's best
  checkpoint: ``s + 3·P``.

(``P`` = 1 000 003, a prime.) The training stream of run ``s`` spans ``P`` seeds from
``s·P``: its restarts and their members. The evaluation, fresh and replay streams keep
these values, which every stored result was made with, except where one would overlap
an earlier stream of the same run (its training span: for ``s`` = 1, 2, 3 and 48
other seeds below 100 000); such a stream, and the confirmation stream always, takes
instead a seed of its own above 2³¹, where no training seed lies: ``2³¹ + (4·s + k)·W``
(mod 2³¹) with ``W`` = 2¹⁴ members per stream and ``k`` the stream's place. No two
streams of one run share a seed (tests/test_seeds.py checks seeds 0-10 000 and random
ones up to 2³²); laid-out streams of runs below 2¹⁵ do not meet one another either.
Across runs, the training spans of runs 1, 2 and 3 still hold the other runs' kept
evaluation, fresh and replay seeds (run 1 trains on start states that run 0 evaluates
on); moving them would change every stored result of those runs. A run keeps the
evaluation and confirmation seeds it started with in its checkpoint (``run_streams``),
so a run stored before a stream moved resumes on the episodes it was selected on.
"""

from __future__ import annotations

import random

import numpy as np
import torch

__all__ = [
    "MEMBERS",
    "STREAMS",
    "confirmation_seed",
    "evaluation_seed",
    "fresh_seed",
    "replay_seed",
    "run_streams",
    "seed_everything",
    "stream_seed",
    "stream_span",
    "training_seed",
]

_SPREAD = 1_000_003  # a prime: streams of one run start this far apart
MEMBERS = 2**14
"""The span of an episode stream: the members (environments, episodes, worker
processes) it may seed consecutively before it could reach another stream."""
_LAID_OUT = 2**31  # laid-out streams live in [2**31, 2**32); training seeds below

STREAMS = ("training", "actions", "confirmation", "evaluation", "fresh", "replay")
"""The named seed streams of a run, in the order their seeds are settled."""

# The value each stream had before the streams were laid out (None: none kept).
_LEGACY = {
    "confirmation": None,
    "evaluation": lambda seed: (seed + _SPREAD) % 2**32,
    "fresh": lambda seed: (seed + 2 * _SPREAD) % 2**32,
    "replay": lambda seed: (seed + 3 * _SPREAD) % 2**32,
}


def seed_everything(seed: int) -> None:
    """Seeds torch's, numpy's and Python's generators (a fresh run: the initial
    weights and the sampled actions; the ``actions`` stream)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def training_seed(seed: int, updates: int) -> int:
    """The seed of the training environments when they (re)start after ``updates``
    updates: the next batch depends only on ``(seed, updates)``."""
    # Spread runs apart so that run s at update u never replays run s + 1 at update u - 1.
    return (seed * _SPREAD + updates) % 2**31


def stream_span(name: str, seed: int) -> list[tuple[int, int]]:
    """The seeds stream ``name`` of run ``seed`` may use, as ``(first, count)`` pairs
    (the training stream's restarts wrap round 2³¹, its members past it). The
    ``actions`` stream seeds other generators than the environments' and spans none of
    their seeds.

    Examples:
        >>> stream_span("evaluation", 0)
        [(1000003, 16384)]
        >>> stream_span("training", 2147)  # doctest: +NORMALIZE_WHITESPACE
        [(2147006441, 493591), (0, 522796)]
    """
    if name == "actions":
        return []
    if name == "training":
        first = training_seed(seed, 0)
        if first + _SPREAD <= 2**31:
            return [(first, _SPREAD)]
        # The restart seed wraps round 2**31; the members of the last one before it
        # (seed + 1, ...) do not.
        return [(first, 2**31 - first + MEMBERS), (0, first + _SPREAD - 2**31)]
    return [(stream_seed(name, seed), MEMBERS)]


def stream_seed(name: str, seed: int) -> int:
    """The first seed of stream ``name`` (one of ``STREAMS`` but ``training``, which
    also depends on the updates: [`training_seed`][rl_pg.training.seeds.training_seed])
    of run ``seed``.

    Raises:
        ValueError: an unknown stream, or ``training``.

    Examples:
        >>> stream_seed("evaluation", 0), stream_seed("fresh", 0)
        (1000003, 2000006)
        >>> stream_seed("evaluation", 1) >= 2**31  # its legacy value is in run 1's training
        True
    """
    if name == "actions":
        return seed
    if name not in _LEGACY:
        raise ValueError(
            f"Unknown seed stream {name!r}: one of {', '.join(STREAMS)} (training seeds "
            "also depend on the updates: training_seed(seed, updates))."
        )
    settled = [
        span for earlier in STREAMS[: STREAMS.index(name)] for span in stream_span(earlier, seed)
    ]
    legacy = _LEGACY[name]
    if legacy is not None and _free(legacy(seed), settled):
        return legacy(seed)
    laid_out = len(_LEGACY)  # slots per run
    slot = laid_out * seed + list(_LEGACY).index(name)
    # Slots of runs below 2**15 never meet; far above, step on until the run's own are free.
    while not _free(value := _LAID_OUT + (slot * MEMBERS) % 2**31, settled):
        slot += laid_out
    return value


def _free(first: int, settled: list[tuple[int, int]]) -> bool:
    """Whether a stream from ``first`` overlaps none of the ``settled`` spans."""
    return not any(first < a + n and a < first + MEMBERS for a, n in settled)


def evaluation_seed(seed: int) -> int:
    """The seed of a run's evaluations during training (``stream_seed("evaluation", …)``)."""
    return stream_seed("evaluation", seed)


def fresh_seed(seed: int) -> int:
    """The seed that scores a run's checkpoints after training (``rl-pg evaluate``):
    apart from its training and its evaluations during training."""
    return stream_seed("fresh", seed)


def confirmation_seed(seed: int) -> int:
    """The seed of the episodes that confirm a run's candidates for ``best.pt`` (apart
    from its training, its evaluations, ``rl-pg evaluate``'s fresh episodes and the
    tuner's replays)."""
    return stream_seed("confirmation", seed)


def replay_seed(seed: int) -> int:
    """The seed of ``rl-pg tune --objective held_out``'s replays of a run with ``seed``:
    apart from its evaluations during training, from the episodes that confirmed its
    ``best.pt`` and from ``rl-pg evaluate``'s default episodes, so that the tuned
    settings can be confirmed on episodes the search never saw."""
    return stream_seed("replay", seed)


def run_streams(seed: int, *, stored_before_layout: bool = False) -> dict[str, int]:
    """The seeds a run's evaluations during training play, as its checkpoint keeps them:
    ``{"evaluation": …, "confirmation": …}``. ``stored_before_layout``: the values a run
    checkpointed before the streams were laid out (2026-11-28) played, which it resumes
    with (evaluation ``s + P``, confirmation ``s + 3·P``).

    Examples:
        >>> run_streams(1, stored_before_layout=True)
        {'evaluation': 1000004, 'confirmation': 3000010}
    """
    if stored_before_layout:  # the old confirmation seed was the replays' (s + 3·P)
        return {"evaluation": _LEGACY["evaluation"](seed), "confirmation": _LEGACY["replay"](seed)}
    return {"evaluation": evaluation_seed(seed), "confirmation": confirmation_seed(seed)}
