"""Every seed a run derives from its own, in one place.

A run with seed ``s`` plays several random streams: its training environments
(reseeded at each restart), its evaluations during training, the episodes that confirm
a candidate for ``best.pt``, the fresh episodes of ``rl-pg evaluate`` and the replays of
``rl-pg tune --objective held_out``. Each stream's seed is a function of ``s`` here; a
batched environment seeds its members ``seed, seed + 1, …``. Known overlaps, kept so
that stored runs reproduce until they are re-run: ``replay_seed(s) ==
confirmation_seed(s)``, and for ``s`` = 1, 2, 3 the training members' seeds overlap the
evaluation's, the fresh episodes' and the confirmation's members' seeds respectively.
"""

from __future__ import annotations

import random

import numpy as np
import torch

__all__ = [
    "confirmation_seed",
    "evaluation_seed",
    "fresh_seed",
    "replay_seed",
    "seed_everything",
    "training_seed",
]

_SPREAD = 1_000_003  # a prime: streams of one run start this far apart


def seed_everything(seed: int) -> None:
    """Seeds torch's, numpy's and Python's generators (a fresh run: the initial
    weights and the sampled actions)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def training_seed(seed: int, updates: int) -> int:
    """The seed of the training environments when they (re)start after ``updates``
    updates: the next batch depends only on ``(seed, updates)``."""
    # Spread runs apart so that run s at update u never replays run s + 1 at update u - 1.
    return (seed * _SPREAD + updates) % 2**31


def evaluation_seed(seed: int) -> int:
    """The seed of a run's evaluation environment (apart from its training seeds)."""
    return seed + _SPREAD


def fresh_seed(seed: int) -> int:
    """The seed that scores a run's checkpoints after training (``rl-pg evaluate``):
    apart from its training and its evaluations during training."""
    return (evaluation_seed(seed) + _SPREAD) % 2**32


def confirmation_seed(seed: int) -> int:
    """The seed of the episodes that confirm a run's candidates for ``best.pt`` (apart
    from its training, its evaluations and ``rl-pg evaluate``'s fresh episodes)."""
    return (evaluation_seed(seed) + 2 * _SPREAD) % 2**32


def replay_seed(seed: int) -> int:
    """The seed of ``rl-pg tune --objective held_out``'s replays of a run with ``seed``:
    apart from its evaluations during training and from ``rl-pg evaluate``'s default
    episodes, so that the tuned settings can be confirmed on episodes the search never
    saw."""
    return (fresh_seed(seed) + _SPREAD) % 2**32
