"""The recipes: complete experiments on real environments, run by ``rl-pg``.

Each module defines a config class, builds its environments and models, and exposes
them as a [`Recipe`][rl_pg.training.recipe.Recipe] named ``RECIPE``.
[`load`][rl_pg.recipes.load] is the one way to get a recipe by name: the command
line, deployment, the tests, the benchmarks and the docs all use it.

Examples:
    >>> from rl_pg.recipes import NAMES, load
    >>> NAMES[:3], NAMES[-1]
    (('bandit', 'gridworld', 'cartpole'), 'gym')
    >>> recipe = load("cartpole")
    >>> recipe.config().threshold
    475.0
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from rl_pg.training.recipe import Recipe

__all__ = ["NAMES", "load", "recipe_modules", "recipe_of"]

_SIMPLEST_FIRST = (
    "bandit", "gridworld", "cartpole", "pendulum", "lunarlander", "highway", "pong", "metadrive",
    "gym",
)  # fmt: skip


def recipe_modules(folder: str | Path, order: tuple[str, ...] = _SIMPLEST_FIRST) -> tuple[str, ...]:
    """The recipe modules in ``folder``: those ``order`` names first, in its order, then
    any other (a recipe file just added) by name; underscored modules are not recipes.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> folder = Path(tempfile.mkdtemp())
        >>> for name in ("cartpole", "toy", "bandit", "_helpers"):
        ...     _ = (folder / f"{name}.py").write_text("")
        >>> recipe_modules(folder)
        ('bandit', 'cartpole', 'toy')
    """
    found = {m.name for m in pkgutil.iter_modules([str(folder)]) if not m.name.startswith("_")}
    return tuple(name for name in order if name in found) + tuple(sorted(found - set(order)))


NAMES = recipe_modules(Path(__file__).parent)
"""The built-in recipes, simplest first (a recipe file added to this package is one too,
after them); ``gym`` takes any gymnasium id (``--env-id``)."""


def load(name: str, module: str | None = None) -> Recipe:
    """The recipe called ``name``: a built-in one, or the one ``module`` defines.

    Args:
        name (str): a name of [`NAMES`][rl_pg.recipes.NAMES], or a recipe's own name.
        module (str, optional): the importable module that defines the recipe (runs
            record it). Tried first.

    Raises:
        ValueError: no such recipe; the message lists the built-in ones and says what
            a recipe of your own needs.
    """
    if module is not None:
        recipe = _find(name, module)
        if recipe is not None:
            return recipe
    if name in NAMES:
        return importlib.import_module(f"{__name__}.{name}").RECIPE
    where = ""
    if module == "__main__":
        where = " (it was defined in a script, which cannot be imported again)"
    elif module is not None:
        where = f" (its module {module!r} does not define it, or cannot be imported)"
    raise ValueError(
        f"No recipe called {name!r}{where}. The built-in recipes are {', '.join(NAMES)}. "
        f"A recipe of your own is an rl_pg.training.recipe.Recipe in an importable module, "
        f"trained with recipe.train(cfg): its runs record that module."
    )


def _find(name: str, module: str) -> Recipe | None:
    """The recipe ``name`` in ``module``; None when the module is not there (a script's
    ``__main__``, or a module since removed). A module that is there but fails to import
    says why: its own error, not "no such recipe"."""
    try:
        namespace = vars(importlib.import_module(module))
    except ModuleNotFoundError as err:
        if err.name is not None and module.split(".")[0] != err.name.split(".")[0]:
            raise ValueError(
                f"The module {module!r} that defines recipe {name!r} cannot be imported: "
                f"it needs {err.name!r}, which is not installed ({err})."
            ) from err
        return None
    except Exception as err:  # the user's module raised while importing
        raise ValueError(
            f"The module {module!r} that defines recipe {name!r} failed to import: "
            f"{type(err).__name__}: {err}"
        ) from err
    found = [v for v in namespace.values() if isinstance(v, Recipe) and v.name == name]
    return found[0] if found else None


def recipe_of(saved: dict, run) -> Recipe:
    """The recipe that trained ``run``, whose checkpoint is ``saved`` (``read_run``),
    once its stored config is one the recipe's config class takes.

    Raises:
        ValueError: the run cannot be rebuilt, or its config holds a value the recipe
            refuses; the message names the run (and the field).
    """
    try:
        recipe = load(saved["recipe"], saved.get("recipe_module"))
    except ValueError as err:
        raise ValueError(
            f"{run} cannot be rebuilt: {err} Its weights load from Python: "
            f"saved = rl_pg.training.read_run(run_dir, which='best'); build the same actor "
            f"and critic; rl_pg.training.load_models(saved, actor, critic)."
        ) from None
    try:
        recipe.config.from_stored(saved["config"])
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"{run}: its stored config does not fit the {recipe.name} recipe: {err}"
        ) from None
    return recipe
