"""The house plan of the package: imports point one way, no module reaches into
another's private names, and modules stay small enough to read.

docs/layout.md draws the same plan in words."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, Transform
from torchrl.objectives import LossModule
from torchrl.objectives.value import ValueEstimatorBase

PACKAGE = Path(__file__).resolve().parents[1] / "rl_pg"

MAX_LINES = 400
LONGER = {"rl_pg.loss": 1030}
"""Modules allowed above ``MAX_LINES``, each at most this long: ``ReinforceLoss`` is one
class, TorchRL's interface and its checks of every batch."""
FRAMEWORK = (torch.nn.Module, EnvBase, Transform, LossModule, TensorDictModuleBase,
             ValueEstimatorBase)  # fmt: skip
"""Classes whose underscored methods are hooks their subclasses define and callers use
(``EnvBase._step``, ``Transform._reset``): names of the framework's, not of a module's."""


def _modules() -> dict[str, Path]:
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


MODULES = _modules()
TREES = {name: ast.parse(path.read_text()) for name, path in MODULES.items()}


def _type_checking_only(tree: ast.Module) -> set[int]:
    """The ids of import nodes under ``if TYPE_CHECKING:`` (annotations, not imports)."""
    return {
        id(node)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and ast.unparse(block.test).endswith("TYPE_CHECKING")
        for stmt in block.body
        for node in ast.walk(stmt)
    }


def _imports(name: str) -> dict[str, list[str]]:
    """The rl_pg modules ``name`` imports, anywhere in it (a function's body too), each
    with the names it takes from there."""
    tree, out = TREES[name], {}
    skip = _type_checking_only(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "rl_pg":
                    out.setdefault(alias.name, [])
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "rl_pg":
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                target = sub if sub in MODULES else node.module
                out.setdefault(target, []).append(alias.name)
    return out


def _cycle() -> list[str] | None:
    """A circle of imports among the package's files, if there is one."""
    graph = {name: [m for m in _imports(name) if m in MODULES and m != name] for name in MODULES}
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(name: str) -> list[str] | None:
        state[name] = 1
        path.append(name)
        for nxt in graph[name]:
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[name] = 2
        return None

    for name in graph:
        if name not in state and (found := visit(name)):
            return found
    return None


def test_no_circle_of_imports_among_the_files():
    assert _cycle() is None, " -> ".join(_cycle() or [])


def test_the_library_imports_neither_the_harness_nor_the_application():
    floors = {"rl_pg.training": 1, "rl_pg.recipes": 2, "rl_pg.app": 3}

    def floor(name: str) -> int:
        return max((f for prefix, f in floors.items() if name.startswith(prefix)), default=0)

    upward = [
        f"{name} imports {target}"
        for name in MODULES
        for target in _imports(name)
        if floor(target) > floor(name)
    ]
    assert upward == []


def _defined_private_names(name: str) -> set[str]:
    """The underscored names module ``name`` defines: its functions, classes, methods,
    globals and instance attributes (``self._x = ...``)."""
    names = set()
    for node in ast.walk(TREES[name]):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
    return {n for n in names if _private(n)}


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _framework_names() -> set[str]:
    from tensordict.nn import TensorDictModule

    module = TensorDictModule(torch.nn.Identity(), ["x"], ["y"])  # its instance attributes
    return {attr for cls in FRAMEWORK for attr in dir(cls)} | set(vars(module))


def _private_crossings() -> list[str]:
    owners: dict[str, set[str]] = {}
    for name in MODULES:
        for private in _defined_private_names(name):
            owners.setdefault(private, set()).add(name)
    framework = _framework_names()
    found = []
    for name, tree in TREES.items():
        own = _defined_private_names(name)
        for target, taken in _imports(name).items():
            for taken_name in taken:  # a private module itself is the package's own
                if _private(taken_name) and not target.endswith(f".{taken_name}"):
                    found.append(f"{name} imports {taken_name} from {target}")
        for node in ast.walk(tree):
            if not isinstance(node, ast.Attribute) or not _private(node.attr):
                continue
            attr, value = node.attr, node.value
            if attr in own or attr in framework:
                continue
            if isinstance(value, ast.Name) and value.id in ("self", "cls"):
                continue
            if isinstance(value, ast.Call) and ast.unparse(value.func) == "super":
                continue
            if owners.get(attr, set()) - {name}:
                found.append(f"{name}:{node.lineno} uses {ast.unparse(node)}")
    return found


def test_no_module_uses_another_modules_private_names():
    """A name with a leading underscore is its module's own: another module that needs
    it needs a public one (a private module, ``rl_pg._checks``, is the package's own)."""
    assert _private_crossings() == []


@pytest.mark.parametrize("name", sorted(MODULES))
def test_modules_stay_short(name):
    lines = len(MODULES[name].read_text().splitlines())
    limit = LONGER.get(name, MAX_LINES)
    assert lines <= limit, f"{MODULES[name]}: {lines} lines, more than {limit}"
