"""Runs by setting: the flags a stored file's runs share that differ from their
recipe's defaults, the runs of a file that holds several settings, and the table of
one row per setting (``rl-pg report --stored FILE... --settings``).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from rl_pg.app.flags import flag
from rl_pg.app.stores import MODES, stored_runs
from rl_pg.recipes import load
from rl_pg.training import TrainConfig

__all__ = [
    "NOT_SETTINGS",
    "as_run",
    "by_setting",
    "format_settings",
    "quiet_fields",
    "setting_flags",
]

# What a setting's flags leave out: where a run went, which seed, how it was watched.
NOT_SETTINGS = frozenset({"seed", "n_seeds", "run_dir", "resume", "progress", "threads", "device"})


def format_settings(paths: list[Path]) -> str:
    """One Markdown row per stored file: the setting its runs share, how many reached
    the threshold and when, and how their best checkpoints score both ways.

    A run that never reached the threshold counts as later than any that did (so the
    median is "—" when half of them never did). "held" counts the best checkpoints whose
    greedy and sampled means both reach the threshold.
    """
    head = (
        "| setting | seeds | reached | median frames to threshold | held both ways "
        "| greedy, median | sampled, median |"
    )
    lines = [head, "|---|---:|---:|---:|---:|---:|---:|"]
    stored = [stored_runs(path) for path in paths]
    settings = [setting_flags(runs) for runs in stored]
    recipes = [runs[0]["report"]["recipe"] for runs in stored]
    mixed = len(set(recipes)) > 1  # settings of several recipes: say which is which
    # flags every row shares (a budget, say) are said once, under the table
    shared = set.intersection(*map(set, settings)) if len(settings) > 1 else set()
    for runs, setting, recipe in zip(stored, settings, recipes, strict=True):
        reports = [run["report"] for run in runs]
        reached = [r.get("solved_at_frames") for r in reports]
        median = float(np.median([np.inf if at is None else at for at in reached]))
        scores = {
            mode: [r[mode]["mean_return"] for r in reports if r.get(mode) is not None]
            for mode in MODES
        }
        evaluated = all(len(values) == len(reports) for values in scores.values())
        threshold = reports[0].get("threshold")
        held = (
            f"{sum(min(g, s) >= threshold for g, s in zip(*scores.values(), strict=True))}"
            f"/{len(reports)}"
            if evaluated and threshold is not None
            else "—"
        )
        # a row of the shared flags alone is not the defaults: say where its flags are
        label = " ".join(f"`{f}`" for f in setting if f not in shared) or (
            "only the flags below" if setting else "defaults"
        )
        lines.append(
            f"| {recipe + ': ' if mixed else ''}{label} | "
            f"{_seeds([r['seed'] for r in reports])} | "
            f"{sum(at is not None for at in reached)}/{len(reports)} | "
            + ("—" if not np.isfinite(median) else f"{median:,.0f}")
            + f" | {held} | "
            + " | ".join(
                f"{np.median(values):.1f}" if values and evaluated else "—"
                for values in scores.values()
            )
            + " |"
        )
    if shared:
        common = " ".join(f"`{flag}`" for flag in settings[0] if flag in shared)
        lines += ["", f"Every row: {common}."]
    return "\n".join(lines)


def _seeds(seeds: list[int]) -> str:
    """Seeds as a short list: runs of three or more consecutive ones as a range.

    Examples:
        >>> from rl_pg.app.settings import _seeds
        >>> _seeds([0, 1, 2, 3, 4, 5, 6, 7, 8, 9]), _seeds([0, 1, 2, 4, 5, 8, 9]), _seeds([4])
        ('0–9', '0–2 4 5 8 9', '4')
    """
    parts, run = [], []
    for seed in sorted(set(seeds)):
        if run and seed != run[-1] + 1:
            parts.append(run)
            run = []
        run.append(seed)
    parts.append(run)
    return " ".join(f"{r[0]}–{r[-1]}" if len(r) >= 3 else " ".join(map(str, r)) for r in parts if r)


def setting_flags(runs: list[dict[str, Any]]) -> list[str]:
    """The flags every run shares that differ from its recipe's defaults, as rl-pg
    train would take them; a flag the runs disagree on is listed with all its values.
    A field that does nothing in a run (``TrainConfig.inert``: ``--target-kl`` without
    ``--lr-control kl``) counts as the default there; a field whose default None is
    resolved by the run's other fields (LunarLander's ``scale_lr_factor``, the
    gridworld's ``threshold``) is compared with what it resolves to for that run."""
    from rl_pg.recipes import load
    from rl_pg.training import TrainConfig

    recipes = {run["report"]["recipe"] for run in runs}
    if len(recipes) != 1:
        raise ValueError(f"a setting's runs come from one recipe, got {sorted(recipes)}.")
    recipe = load(recipes.pop())
    defaults = _defaults(recipe)
    quiet = quiet_fields()
    configs = [config for config, _ in as_run(runs)]
    resolved = [
        field.name
        for field in dataclasses.fields(recipe.config)
        if field.default is None and defaults.get(field.name) is not None
    ]
    flags = []
    for name in defaults:
        if name in quiet:
            continue
        values, own = [], []  # each run's value, and whether it is its default
        for config in configs:
            default = _resolved(recipe, config, name) if name in resolved else defaults[name]
            inert = TrainConfig.inert(name, config)
            values.append(default if inert else config[name])
            own.append(inert or config[name] == default)
        if not all(own):
            distinct = [v for i, v in enumerate(values) if v not in values[:i]]
            shown = [flag(name, v) for v in distinct]
            flags.append(shown[0] if len(shown) == 1 else " / ".join(shown))
    return flags


def _defaults(recipe) -> dict[str, Any]:
    config = recipe.config() if recipe.prepare is None else recipe.prepare(recipe.config())
    return json.loads(json.dumps(vars(config), default=str))


def quiet_fields() -> set[str]:
    """Fields that say nothing about a setting: the seed, where and how it logged."""

    return NOT_SETTINGS | set(TrainConfig.groups["logging"][1])


def as_run(runs: list[dict[str, Any]]) -> list[tuple[dict[str, Any], Any]]:
    """Each stored run's config as it ran (a field newer than the run at the value it
    had then, the rest at the recipe's defaults), with its recipe."""

    out = []
    for run in runs:
        recipe = load(run["report"]["recipe"])
        out.append(({**_defaults(recipe), **recipe.config.as_run(run["config"])}, recipe))
    return out


def _resolved(recipe, config: dict[str, Any], name: str) -> Any:
    """What field ``name``'s default None resolves to in a run of ``config`` (its
    other fields as they are, by the config or the recipe's ``prepare``), as
    ``config_dict`` writes it."""
    own = recipe.config.from_stored(config, **{name: None})
    own = own if recipe.prepare is None else recipe.prepare(own)
    return json.loads(json.dumps(getattr(own, name), default=str))


def by_setting(runs: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """A stored file's runs by setting: seeds of one setting are one group; runs whose
    configs differ in more than the seed (a file written from mixed runs) are not
    seeds of each other, and each setting is named by the flags that set it apart."""
    recipes = [run["report"]["recipe"] for run in runs]
    if len(set(recipes)) > 1:
        return {
            name: [r for r, of in zip(runs, recipes, strict=True) if of == name] for name in recipes
        }
    if len({tuple(setting_flags([run])) for run in runs}) == 1:
        return {"": runs}

    configs = [config for config, _ in as_run(runs)]
    quiet = quiet_fields()
    varying = [
        name
        for name in configs[0]
        if name not in quiet and len({json.dumps(c.get(name)) for c in configs}) > 1
    ]
    groups: dict[str, list[dict[str, Any]]] = {}
    for run, config in zip(runs, configs, strict=True):
        label = " ".join(flag(name, config.get(name)) for name in varying)
        groups.setdefault(label, []).append(run)
    return groups
