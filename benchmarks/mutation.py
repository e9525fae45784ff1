"""Mutation testing of rl_pg's core: one deliberate small bug at a time (a comparison
turned round, a sign flipped, a constant moved by one, a condition negated), and the
tests of that module run against it. A mutant the tests fail on is killed; one they pass
on survived, and is either a gap in the tests or a change that cannot be told apart from
the code (an equivalent mutant, argued in ``EQUIVALENT``). A survivor no test on this
machine can kill keeps its reason in ``ARGUED``.

    python benchmarks/mutation.py --modules functional training.seeds  # these modules
    python benchmarks/mutation.py                 # the whole core: hours
    python benchmarks/mutation.py --survivors     # the survivors again, once tests changed
    python benchmarks/mutation.py --targets       # the targets, their tests and mutants
    python benchmarks/mutation.py --summary       # the scores again, after EQUIVALENT or
                                                  # ARGUED changed

Scores go to ``benchmarks/results/mutation.json`` after every mutant, so a stopped run
continues where it was; a module whose source changed is scored afresh. Runs on
different modules may share the file (one per core: each writes its own modules). The heavy
imports (torch, TorchRL, pytest) happen once: each mutant's tests run in a fork of this
process, on a copy of the package, so a mutant costs what its tests take.
"""

from __future__ import annotations

import ast
import fcntl
import hashlib
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "mutation.json"

TARGETS: dict[str, list[str]] = {  # each also answers with its doctests
    "rl_pg.functional": ["tests/test_functional.py"],
    "rl_pg._scan": ["tests/test_scan.py", "tests/test_functional.py"],
    "rl_pg.estimators": [
        "tests/test_estimators.py",
        "tests/test_loss.py::TestReinforceLoss::test_make_value_estimator_by_name",
    ],
    "rl_pg.baselines": ["tests/test_baselines.py"],
    "rl_pg.groups": ["tests/test_groups.py"],
    "rl_pg.greedy_play": ["tests/test_groups.py"],
    "rl_pg.loss": [
        "tests/test_loss.py",
        "tests/test_loss_torchrl_compat.py",
        "tests/test_popart.py",  # the loss's value_norm
    ],
    "rl_pg.loss_checks": ["tests/test_loss.py", "tests/test_loss_torchrl_compat.py"],
    "rl_pg.discretize": ["tests/test_discretize.py"],
    "rl_pg.training.seeds": ["tests/test_seeds.py"],
    "rl_pg.checkpoint": ["tests/test_checkpoint.py"],
    "rl_pg.gradient_noise": ["tests/test_gradient_statistics.py"],
    "rl_pg.gradient_statistics": ["tests/test_gradient_statistics.py"],
    "rl_pg.step_log_prob": ["tests/test_gradient_statistics.py"],
    "rl_pg.training.selection": ["tests/test_selection.py"],
    "rl_pg.episode_workers": ["tests/test_evaluation.py"],
    "rl_pg.collectors": ["tests/test_collectors.py", "tests/test_segment_collector.py"],
    "rl_pg.segments": ["tests/test_collectors.py", "tests/test_segment_collector.py"],
    "rl_pg.episode_collector": ["tests/test_episode_collector.py"],
}
"""The core's modules, each with the tests that answer for it."""

_THREADS = (
    "how many threads the return kernel runs on: its results are the same for any count "
    "(tests/test_scan.py checks the parallel kernel against the serial one)"
)
_LAST_OF_2D = "the scan's tensors are [rows, steps]: dimension -1 is dimension 1"
EQUIVALENT: dict[str, str] = {
    **{
        f"rl_pg._scan:{key}": _THREADS
        for key in (
            "41:7 compare 0 Lt->LtE",
            "42:15 constant 1->2",
            "47:16 binary Add->Sub",
            "47:16 binary Sub->Add",
            "47:42 constant 1->2",
            "48:15 constant 1->2",
        )
    },
    **{
        f"rl_pg._scan:{key}": _LAST_OF_2D
        for key in (
            "70:27 drop USub",
            "76:16 drop USub",
            "80:16 drop USub",
            "88:52 drop USub",
            "89:29 drop USub",
        )
    },
    "rl_pg._scan:72:10 compare 0 Lt->LtE": (
        "one more doubling step with shift >= steps slices nothing off and adds nothing"
    ),
    "rl_pg._scan:86:22 constant True->False": (
        "a row's first step starts an episode either way: the running maximum of the start "
        "positions is 0 before any marked start"
    ),
    **{
        f"rl_pg.estimators:{key}": (
            "the work above which the estimator reuses the following step's V(s_t) as "
            "V(s_{t+1}): the values are the same either way "
            "(test_next_values_taken_from_the_following_step_match_a_full_pass)"
        )
        for key in ("25:17 constant 1->2", "25:22 constant 21->22")
    },
    **{
        f"rl_pg.estimators:{key}": (
            "how TorchRL is asked for the values (vmapped or in a loop, the parameters "
            "copied deep or shallow): the same values either way"
        )
        for key in ("46:32 constant False->True", "132:49 constant False->True")
    },
    **{
        f"rl_pg.estimators:{key}": (
            "whether a chunked value network takes the one-call path: chunking bounds "
            "memory, the values are the same"
        )
        for key in ("160:11 bool Or->And", "161:19 constant False->True")
    },
    "rl_pg.estimators:171:64 constant False->True": (
        "the default of _values' graph, which every call passes"
    ),
    "rl_pg.estimators:238:67 constant 0->1": (
        "a batch without a time dimension is refused before (estimate checks batch_dims)"
    ),
    **{
        f"rl_pg.estimators:{key}": (
            "when a segment's values are worth reusing (its length, the work): the values "
            "are the same either way"
        )
        for key in ("239:11 compare 0 Lt->LtE", "239:19 constant 2->3", "243:11 compare 0 Lt->LtE")
    },
    **{
        f"rl_pg.estimators:{key}": (
            "values are reused only where a next observation equals, entry by entry, the "
            "one they were computed at: V is a function of the observation, so along any "
            "dimension and for any shape the checks let through, the values are the same"
        )
        for key in ("239:11 bool Or->And", "253:15 bool Or->And")
    },
    "rl_pg.estimators:249:24 compare 0 Eq->NotEq": (
        "done != 0 of a bool tensor is the tensor itself, and 0/1 numbers mark the same steps"
    ),
    "rl_pg.checkpoint:82:36 constant True->False": (
        "the temporary file exists whenever the try fails: it is made before it, and only "
        "os.replace, its last statement, takes it away"
    ),
    "rl_pg.checkpoint:99:25 constant 0->1": (
        "the umask set while the old one is read is put back at once; the value read is the same"
    ),
    "rl_pg.checkpoint:114:30 constant True->False": (
        "rglob yields files that exist, and nothing else removes them under the run's lock "
        "(the function's stated condition)"
    ),
    **{
        f"rl_pg.checkpoint:{key}": (
            "the array and scalar that name numpy's constructors: any shape or value gives "
            "the same functions"
        )
        for key in ("212:46 constant 1->2", "213:21 constant 0->1")
    },
    "rl_pg.gradient_noise:82:72 constant 1e-30->2e-30": (
        "the cosine's floor for halves of zero length: halves whose norms multiply to more "
        "than 2e-30 get the same cosine, and shorter ones 0 either way"
    ),
    "rl_pg.discretize:93:72 constant 1->2": (
        "the ndim read of counts that have none (an int, a list): any default but 0 says "
        "'not a 0-d array'"
    ),
    **{
        f"rl_pg.discretize:{key}": "zip's strict check of lists equal in length by construction"
        for key in ("196:82 constant True->False", "263:76 constant True->False")
    },
    "rl_pg.discretize:300:49 constant 1e-12->2e-12": (
        "the scale of a dimension of zero width, where every table entry has the same value: "
        "it scales every distance alike, and the nearest entry is the same"
    ),
    **{
        f"rl_pg.groups:{key}": (
            "unsqueeze of a vector (one entry per episode or per group): dimension -1 is "
            "dimension 1"
        )
        for key in (
            "151:43 drop USub",
            "154:31 drop USub",
            "165:39 drop USub",
            "167:90 drop USub",
            "168:42 drop USub",
            "170:50 drop USub",
        )
    },
    "rl_pg.groups:282:58 constant 1->2": (
        "one more all-zero column in the episodes' table: each position is compared with "
        "its own column (scaled too), and the extra one is never read back"
    ),
    "rl_pg.greedy_play:76:67 constant 1->2": (
        "the row count of a batch without dimensions, which is refused on the next line"
    ),
    "rl_pg.episode_workers:135:83 constant True->False": (
        "zip's strict check of the workers, their shares and seeds: one of each per worker "
        "by construction"
    ),
    **{
        f"rl_pg.episode_workers:{key}": (
            "how long to wait for a worker process or actor asked to stop, which stops at once"
        )
        for key in ("150:33 constant 30->31", "179:33 constant 5->6", "243:55 constant 30->31")
    },
    **{
        f"rl_pg.episode_workers:{key}": (
            "a worker's torch threads: it plays the same episodes on one or two (the tests "
            "compare the workers' episodes with those played in this process)"
        )
        for key in ("280:30 constant 1->2", "300:26 constant 1->2")
    },
    "rl_pg.episode_workers:225:80 constant True->False": (
        "zip's strict check of the actors, their shares and seeds: one of each per actor"
    ),
    "rl_pg.episode_workers:248:29 constant False->True": (
        "ownership of a Ray instance already shut down: shutting it down again does nothing"
    ),
    "rl_pg._scan:103:34 constant 0->1": (
        "reward[:0] is read for its dtype alone, which reward[:1] has too"
    ),
    **{
        f"rl_pg.segments:{key}": (
            "which entries are made as new zeros instead of stacked: only ones whose every "
            "step is the same all-False tensor, which stack to those zeros (the values are "
            "the same; a shared flag that is set is stacked, test_stacked_roots_are_torch_"
            "stack_of_them)"
        )
        for key in ("71:11 compare 0 In->NotIn", "71:34 compare 0 Is->IsNot")
    },
    "rl_pg.gradient_statistics:49:15 constant 8->9": (
        "the unit count below which the per-unit product is taken dense rather than sparse: "
        "the same product either way"
    ),
    **{
        f"rl_pg.gradient_statistics:{key}": (
            "where the padding mask of [E, T] gets its trailing dimension: batch_group_"
            "advantage reads it flattened, in the same order either way"
        )
        for key in ("243:66 drop USub", "243:67 constant 1->2")
    },
    **{
        f"rl_pg.gradient_statistics:{key}": (
            "the order the steps are summed in (time last, a group's steps together): each "
            "chunk's product covers the whole range of unit numbers its steps carry, in "
            "whatever order they come, so the sums are the same "
            "(test_a_time_dimension_first_gives_the_same_units)"
        )
        for key in (
            "286:11 compare 0 NotEq->Eq",
            "286:11 negate condition",
            "286:23 binary Sub->Add",
            "286:42 constant 1->2",
            "293:11 compare 0 Eq->NotEq",
            "293:11 negate condition",
            "294:48 constant True->False",
        )
    },
    "rl_pg.gradient_statistics:324:80 constant True->False": (
        "functional_call's check that every parameter is given: each of the actor's is, "
        "by construction"
    ),
    **{
        f"rl_pg.gradient_statistics:{key}": (
            "how many steps go to a chunk, or units to a backward pass, by default: it "
            "bounds memory, the gradients are the same (test_both_methods_agree_and_vmap_"
            "needs_no_fallback, chunks of 7 and the default)"
        )
        for key in (
            "328:34 constant 1->2",
            "328:37 constant 2->3",
            "328:40 constant 21->22",
            "364:24 constant 1->2",
            "364:42 constant 256->257",
            "364:51 constant 4->5",
            "364:65 constant 0->1",
        )
    },
    "rl_pg.gradient_statistics:337:15 compare 0 LtE->Lt": (
        "a chunk of exactly 8 units built as a sparse matrix, then multiplied as a dense "
        "one would be (sparse @ dense): the same product"
    ),
    "rl_pg.gradient_statistics:348:37 constant False->True": (
        "torch's check of a sparse matrix's indices, all in range by construction"
    ),
    "rl_pg.gradient_statistics:368:74 drop USub": (
        "nonzero() of a vector is [n, 1]: dimension -1 is dimension 1"
    ),
    **{
        f"rl_pg.episode_collector:{key}": (
            "the done flags are [environments, T]: dimension -1 is dimension 1"
        )
        for key in ("207:50 drop USub", "210:37 drop USub")
    },
    **{
        f"rl_pg.episode_collector:{key}": "torch.cat of one batch is that batch"
        for key in ("211:45 compare 0 Gt->GtE", "237:36 compare 0 Gt->GtE")
    },
    "rl_pg.loss:537:66 constant False->True": (
        "the training flag kept for a baseline that does not exist: read only when there is one"
    ),
    "rl_pg.loss_checks:72:39 constant True->False": (
        "a spec's values with its composite nodes as well as its leaves: the Bounded leaves "
        "are among them either way"
    ),
    **{
        f"rl_pg.loss_checks:{key}": (
            "the fast path for integer indices of a categorical policy: an index it "
            "sends to the full support check is accepted there as well"
        )
        for key in ("113:17 compare 0 GtE->Gt", "113:24 constant 0->1")
    },
    "rl_pg.loss_checks:146:61 compare 0 Gt->GtE": (
        "per-step values with as many dimensions as the batch and its prefix: those are "
        "the batch's shape, taken by the branch before"
    ),
    **{
        f"rl_pg.loss:{key}": (
            "how the parameters are put into the module for the call (registered as "
            "before, or replaced): the same values and gradients, the module restored after"
        )
        for key in ("823:90 constant False->True", "900:72 constant False->True")
    },
    "rl_pg.loss:850:61 drop Not": (
        "float actions of a categorical policy through the gather rather than log_prob: "
        "the support check let only whole numbers through, which both score alike"
    ),
    **{
        f"rl_pg.loss:{key}": (
            "gather's [*B, 1] squeezed at another dimension of 1 or not at all: per_step "
            "brings [*B] and [*B, 1] to the same column"
        )
        for key in ("853:83 drop USub", "853:84 constant 1->2")
    },
    "rl_pg.collectors:34:29 constant 1->2": (
        "the default total_frames, -1 or -2: any negative count collects without end"
    ),
    **{
        f"rl_pg.collectors:{key}": (
            "which of two paths steps an EnvPoolEnv, its plain tensors or the TensorDicts "
            "of any other two-group environment: the same batches (the tests compare "
            "both with TorchRL's collector)"
        )
        for key in ("297:11 compare 0 IsNot->Is", "297:11 negate condition")
    },
    "rl_pg.training.seeds:105:11 compare 0 LtE->Lt": (
        "a training span that ends exactly at 2**31 (runs 2**31 - 1 and 2**32 - 1) then "
        "also claims the members past it; both runs' streams lie elsewhere either way "
        "(stream_seed gives the same four seeds under the mutant)"
    ),
}

"""Mutants that change no behaviour (``module:line:col operator`` -> why), left out of
the score."""

ARGUED: dict[str, str] = {
    "rl_pg.training.selection:162:40 compare 0 Is->IsNot": (
        "the index of a CUDA device, read only where training runs on CUDA: this machine "
        "has none to run the test on"
    ),
    **{
        f"rl_pg.gradient_noise:{key}": (
            "torch.unique sorts on the CPU whatever sorted= says; the units' numbering (and "
            "the half-batch split) differ only on CUDA, which this machine cannot run"
        )
        for key in ("165:58 constant True->False", "180:54 constant True->False")
    },
    "rl_pg.episode_workers:151:15 negate condition": (
        "killing a worker process that has not stopped 30 s after it was asked to: a test "
        "of it waits those 30 s"
    ),
    "rl_pg.episode_workers:167:93 constant True->False": (
        "worker processes as daemons, ended with this one if it exits without closing them: "
        "seen only in a process that exits with workers left open"
    ),
    **{
        f"rl_pg.episode_workers:{key}": (
            "how a Ray instance started for the workers alone logs and is owned: the tests "
            "evaluate on the suite's shared Ray instance, which this branch never starts"
        )
        for key in ("194:39 constant False->True", "195:29 constant True->False")
    },
    **{
        f"rl_pg.episode_workers:{key}": (
            "how actors are placed over a cluster's nodes (CPU reservations, hard node "
            "affinity): one node places them alike; tests/test_ray_cluster.py checks the "
            "two-node placement, outside the module's tests"
        )
        for key in ("202:16 bool Or->And", "206:25 constant 0->1", "210:48 constant False->True")
    },
    **{
        f"rl_pg.episode_collector:{key}": (
            "the groups' seeds' range moved at its top (2**31 - 1 and 2**31 let in, or "
            "2**31 - 2 left out): a draw lands there once in about 2**30, which no test "
            "can wait for (test_the_groups_seeds_are_fresh_32_bit_integers checks the range)"
        )
        for key in ("220:30 binary Sub->Add", "220:38 constant 1->2")
    },
    **{
        f"rl_pg.collectors:{key}": (
            "whether batches are copied to a device the user named: on this machine's "
            "only device, the CPU, a copy changes nothing; a GPU would tell them apart"
        )
        for key in (
            "50:11 compare 0 Eq->NotEq",
            "50:11 negate condition",
            "50:27 bool Or->And",
            "95:24 compare 0 Is->IsNot",
            "114:35 compare 0 Is->IsNot",
        )
    },
    "rl_pg.collectors:273:34 constant 1->2": (
        "an environment with step_send but no groups attribute, accepted as two groups: "
        "none exists (EnvPoolEnv has both, and any other is refused for want of step_send)"
    ),
    "rl_pg.loss_checks:120:9 bool And->Or": (
        "a distribution with one bound a tensor and the other not: none in torch or "
        "TorchRL has such bounds"
    ),
    "rl_pg.estimators:164:19 constant False->True": (
        "a value network with recurrent state (is_init in its inputs) taking the one-call "
        "path: rl_pg builds none, and the test needs one of TorchRL's recurrent modules"
    ),
    "rl_pg.estimators:166:12 bool And->Or": (
        "an input that is a plain tensor at the root but not under 'next' (or the "
        "reverse): TorchRL's collectors never write one, and both paths refuse it, by "
        "different errors"
    ),
}
"""Survivors that stay, each with why no test here kills it (they count as survivors)."""


_FLIP_COMPARE = {
    ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt,
    ast.Eq: ast.NotEq, ast.NotEq: ast.Eq, ast.Is: ast.IsNot, ast.IsNot: ast.Is,
    ast.In: ast.NotIn, ast.NotIn: ast.In,
}  # fmt: skip
_FLIP_BINARY = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult}


@dataclass(frozen=True)
class Mutant:
    line: int
    col: int
    change: str

    @property
    def key(self) -> str:
        return f"{self.line}:{self.col} {self.change}"


def _skipped(tree: ast.Module) -> set[int]:
    """Nodes no mutant touches: error messages and checks' raises, docstrings, type
    annotations, ``__all__``, and logging or printing."""
    skip: set[int] = set()

    def all_of(node: ast.AST) -> None:
        skip.update(id(n) for n in ast.walk(node))

    for node in ast.walk(tree):
        if isinstance(node, (ast.Raise, ast.JoinedStr, ast.Assert)):
            all_of(node)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Module)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                all_of(body[0])
            if not isinstance(node, (ast.ClassDef, ast.Module)):
                for arg in [*node.args.args, *node.args.kwonlyargs, *node.args.posonlyargs]:
                    if arg.annotation is not None:
                        all_of(arg.annotation)
                if node.returns is not None:
                    all_of(node.returns)
        elif isinstance(node, ast.AnnAssign):
            all_of(node.annotation)
        elif isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            all_of(node)
        elif isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            all_of(node)  # an attribute's docstring
        elif isinstance(node, ast.Call) and ast.unparse(node.func) in ("print", "warnings.warn"):
            all_of(node)
    return skip


def mutants(source: str) -> list[Mutant]:
    """Every mutant of ``source``, in the order of the source."""
    tree = ast.parse(source)
    skip = _skipped(tree)
    found = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        where = (node.lineno, node.col_offset) if hasattr(node, "lineno") else None
        if isinstance(node, ast.Compare):
            for i, op in enumerate(node.ops):
                if type(op) in _FLIP_COMPARE:
                    found.append(Mutant(*where, f"compare {i} {type(op).__name__}->"
                                                f"{_FLIP_COMPARE[type(op)].__name__}"))  # fmt: skip
        elif isinstance(node, (ast.BinOp, ast.AugAssign)) and type(node.op) in _FLIP_BINARY:
            new = _FLIP_BINARY[type(node.op)].__name__
            found.append(Mutant(*where, f"binary {type(node.op).__name__}->{new}"))
        elif isinstance(node, ast.BoolOp):
            other = "Or" if isinstance(node.op, ast.And) else "And"
            found.append(Mutant(*where, f"bool {type(node.op).__name__}->{other}"))
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.Not, ast.USub)):
            found.append(Mutant(*where, f"drop {type(node.op).__name__}"))
        elif isinstance(node, ast.Constant) and type(node.value) in (bool, int, float):
            found.append(Mutant(*where, f"constant {node.value!r}->{_moved(node.value)!r}"))
        elif isinstance(node, (ast.If, ast.While)) and not isinstance(node.test, ast.Constant):
            found.append(Mutant(node.test.lineno, node.test.col_offset, "negate condition"))
    return sorted(set(found), key=lambda m: (m.line, m.col, m.change))


def _moved(value):
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    return value * 2 if value else 1.0


def apply(source: str, mutant: Mutant) -> str:
    """``source`` with ``mutant`` applied."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        line, col = getattr(node, "lineno", None), getattr(node, "col_offset", None)
        kind, *rest = mutant.change.split(" ", 1)
        if kind == "negate" and isinstance(node, (ast.If, ast.While)):
            if (node.test.lineno, node.test.col_offset) == (mutant.line, mutant.col):
                node.test = ast.UnaryOp(op=ast.Not(), operand=node.test)
                return ast.unparse(tree)
            continue
        if (line, col) != (mutant.line, mutant.col):
            continue
        if kind == "compare" and isinstance(node, ast.Compare):
            i = int(rest[0].split()[0])
            node.ops[i] = _FLIP_COMPARE[type(node.ops[i])]()
        elif kind == "binary" and isinstance(node, (ast.BinOp, ast.AugAssign)):
            if type(node.op).__name__ != rest[0].split("->")[0]:
                continue  # ``a + b - c``: both operations start where ``a`` does
            node.op = _FLIP_BINARY[type(node.op)]()
        elif kind == "bool" and isinstance(node, ast.BoolOp):
            node.op = ast.Or() if isinstance(node.op, ast.And) else ast.And()
        elif kind == "drop" and isinstance(node, ast.UnaryOp):
            _replace(tree, node, node.operand)
        elif kind == "constant" and isinstance(node, ast.Constant):
            node.value = _moved(node.value)
        else:
            continue
        return ast.unparse(tree)
    raise ValueError(f"no node for mutant {mutant.key}")


def _replace(tree: ast.AST, old: ast.AST, new: ast.AST) -> None:
    for parent in ast.walk(tree):
        for name, value in ast.iter_fields(parent):
            if value is old:
                setattr(parent, name, new)
                return
            if isinstance(value, list) and any(v is old for v in value):
                value[next(i for i, v in enumerate(value) if v is old)] = new
                return


def _run_tests(root: Path, tests: list[str], timeout: float) -> str:
    """``killed``, ``survived`` or ``timeout``: the tests of the package copy in
    ``root``, in a fork of this process."""
    pid = os.fork()
    if pid == 0:  # the child: a fresh rl_pg from the copy, the heavy imports kept
        code = 3
        try:
            import pytest

            for name in list(sys.modules):
                if name == "rl_pg" or name.startswith(("rl_pg.", "test_", "conftest", "pages")):
                    del sys.modules[name]
            sys.path.insert(0, str(root))
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1), os.dup2(devnull, 2)
            code = pytest.main([
                *[str(root / t) for t in tests], "-x", "-q", "-p", "no:cacheprovider",
                "--doctest-modules",
                "-p", "no:xdist", "-p", "no:randomly", "-o", "addopts=", "--rootdir", str(root),
                "-W", "ignore",
            ])  # fmt: skip
        finally:
            os._exit(int(code))
    deadline, done = time.monotonic() + timeout, 0
    try:
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                code = os.waitstatus_to_exitcode(status)
                return "survived" if code == 0 else "killed"
            if time.monotonic() > deadline:
                return "timeout"
            time.sleep(0.05)
    finally:  # a timeout, a Ctrl-C or a SIGTERM here: the child does not outlive it
        if not done:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)


@dataclass
class Args:
    """Mutation testing of rl_pg's core modules."""

    modules: list[str] = field(default_factory=list)
    """Modules to mutate, by their name after ``rl_pg.`` (default: every target)."""
    limit: int | None = None
    """At most this many new mutants per module in this run (the rest next time)."""
    survivors: bool = False
    """Score the mutants that survived again (after the tests changed), and no others."""
    targets: bool = False
    """Print the targets, their tests and their mutants' counts, and stop."""
    summary: bool = False
    """Write the scores again from the stored outcomes (after EQUIVALENT or ARGUED
    changed), scoring nothing."""


def main(args: Args) -> dict:
    names = [f"rl_pg.{m}" if not m.startswith("rl_pg") else m for m in args.modules] or list(
        TARGETS
    )
    unknown = [n for n in names if n not in TARGETS]
    if unknown:
        sys.exit(f"mutation.py: no target {unknown}; the targets are {sorted(TARGETS)}.")
    if args.targets:
        for name in names:
            source = (REPO / (name.replace(".", "/") + ".py")).read_text()
            print(f"{name}: {len(mutants(source))} mutants; tests {' '.join(TARGETS[name])}")
        return {}
    if args.summary:
        results = json.loads(RESULTS.read_text())
        _save(results)
        print(f"mutation.py: {results['killed']} of {results['scored']} scored mutants killed.")
        return results
    sys.dont_write_bytecode = True  # a mutant's bytecode must never be read for another's
    os.environ["RL_PG_MUTATION"] = "1"  # hypothesis: the same examples, none shrunk
    import numpy  # noqa: F401  (the heavy imports, once, before the forks)
    import pytest  # noqa: F401
    import tensordict  # noqa: F401
    import torch
    import torchrl  # noqa: F401

    torch.set_num_threads(1)
    results = {"modules": {}}
    if RESULTS.is_file():
        try:
            results = json.loads(RESULTS.read_text())
        except ValueError as err:
            sys.exit(f"mutation.py: {RESULTS} is not JSON ({err}); delete it to score afresh.")
    # SIGTERM ends the run as Ctrl-C does: the scores so far are saved, no child is left.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    with tempfile.TemporaryDirectory(prefix="rl_pg-mutation-") as tmp:
        root = Path(tmp)
        for part in ("rl_pg", "tests", "docs", "pyproject.toml"):
            source = REPO / part
            if source.is_dir():
                shutil.copytree(source, root / part, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                shutil.copy(source, root / part)
        for name in names:
            _score_module(name, root, results, args.limit, again=args.survivors)
    return results


def source_digest(source: str) -> str:
    """What a module's stored scores were measured on: its scores hold while it matches."""
    return hashlib.sha256(source.encode()).hexdigest()[:16]


def _score_module(
    name: str, root: Path, results: dict, limit: int | None, *, again: bool = False
) -> None:
    path = root / (name.replace(".", "/") + ".py")
    original = path.read_text()
    digest = source_digest(original)
    entry = results["modules"].get(name)
    if entry is None or entry.get("source") != digest:
        entry = results["modules"][name] = {"source": digest, "tests": TARGETS[name], "mutants": {}}
    started = time.monotonic()
    tests = [*TARGETS[name], str(path.relative_to(root))]  # and the module's doctests
    baseline = _run_tests(root, tests, timeout=3600)
    seconds = time.monotonic() - started
    if baseline != "survived":
        sys.exit(f"mutation.py: the tests of {name} fail without a mutant; fix them first.")
    timeout = 3 * seconds + 20
    every = mutants(original)
    entry["total"] = len(every)
    if again:
        todo = [m for m in every if entry["mutants"].get(m.key) == "survived"]
    else:
        todo = [m for m in every if m.key not in entry["mutants"]]
    print(f"{name}: {len(todo)} mutants to score (tests take {seconds:.0f} s)", flush=True)
    for number, mutant in enumerate(todo[:limit] if limit else todo, start=1):
        path.write_text(apply(original, mutant))
        began = time.monotonic()
        try:
            outcome = _run_tests(root, tests, timeout)
        finally:
            path.write_text(original)
        entry["mutants"][mutant.key] = outcome
        _save(results, [name])
        took = time.monotonic() - began
        print(f"  [{number}/{len(todo)}] {mutant.key}: {outcome} ({took:.0f} s)", flush=True)


def _summarise(results: dict) -> None:
    """Each module's score and survivors, and the core's, as the docs show them: killed
    over scored, equivalent mutants left out, a timeout counted as killed."""
    summary, killed, scored = {}, 0, 0
    for name, entry in results["modules"].items():
        outcomes = {k: v for k, v in entry["mutants"].items() if f"{name}:{k}" not in EQUIVALENT}
        own = sum(v != "survived" for v in outcomes.values())
        summary[name] = {
            "mutants": entry.get("total", len(entry["mutants"])),
            "scored": len(outcomes),
            "killed": own,
            "score": own / len(outcomes) if outcomes else None,
        }
        entry["survivors"] = sorted(
            (k for k, v in outcomes.items() if v == "survived"),
            key=lambda k: int(k.split(":")[0]),
        )
        killed, scored = killed + own, scored + len(outcomes)
    results["summary"] = summary
    results["killed"], results["scored"] = killed, scored
    results["score"] = killed / scored if scored else None
    results["equivalent"] = EQUIVALENT
    results["survivors"] = {
        f"{name}:{key}": ARGUED.get(f"{name}:{key}", "no test kills it yet")
        for name, entry in results["modules"].items()
        for key in entry["survivors"]
    }


def _save(results: dict, names: list[str] | None = None) -> None:
    """Writes the scores. With ``names``, only those modules' entries go over the stored
    file's: runs on different modules (one per core) share the file."""
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with open(Path(tempfile.gettempdir()) / "rl_pg-mutation.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one writer at a time; released on close
        if names is not None and RESULTS.is_file():
            stored = json.loads(RESULTS.read_text())
            stored["modules"].update({n: results["modules"][n] for n in names})
            results = stored
        _summarise(results)
        tmp = RESULTS.with_suffix(".tmp")
        tmp.write_text(json.dumps(results, indent=1) + "\n")
        os.replace(tmp, RESULTS)


if __name__ == "__main__":
    try:
        main(tyro.cli(Args))
    except KeyboardInterrupt:
        sys.exit(f"mutation.py: stopped; the mutants scored so far are in {RESULTS}.")
