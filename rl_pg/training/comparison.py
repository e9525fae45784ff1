"""Run a recipe under several variants and seeds (``rl_pg.training.curves`` plots them)."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rl_pg.checkpoint import write_atomically
from rl_pg.training.config import TrainConfig

__all__ = ["run_variants"]


def run_variants(
    main: Callable[[Any], dict],
    cfg: TrainConfig,
    variants: dict[str, dict[str, Any]],
    *,
    seeds: Sequence[int],
    root: Path,
) -> dict[str, list[dict]]:
    """Runs ``main`` for every variant (a dict of config overrides) and seed.

    Each run goes to ``root/<variant>/seed<seed>``; the summaries are returned and
    written to ``root/comparison.json``.
    """
    results: dict[str, list[dict]] = {}
    for name, overrides in variants.items():
        for seed in seeds:
            run_cfg = dataclasses.replace(
                cfg, **overrides, seed=seed, run_dir=root / name / f"seed{seed}", resume=False
            )
            results.setdefault(name, []).append(main(run_cfg))
    write_atomically(root / "comparison.json", json.dumps(results, indent=2))
    return results
