"""Shared actors, critics and TensorDict batches for the tests."""

from __future__ import annotations

import gc
import importlib.util
import json
import multiprocessing
import os
import re
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import Phase, settings
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Unbounded
from torchrl.modules import OneHotCategorical, ProbabilisticActor, TanhNormal, ValueOperator

from rl_pg.app.cli import WORKER_IMPORTS
from rl_pg.checkpoint import load_checkpoint
from rl_pg.training.checkpoints import POLICY_AVERAGE, callback_states

# The docs' own tooling (docs/pages.py writes the pages' stored tables and figures).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "docs"))

N_OBS = 3
N_ACT = 4

# CI replays the same examples every run (a red build must be reproducible); local runs
# keep exploring new ones.
settings.register_profile("ci", derandomize=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
# benchmarks/mutation.py needs to know that a test fails, not its smallest example: a
# failing property is not shrunk (which can take a minute a mutant).
settings.register_profile(
    "mutation", derandomize=True, phases=[Phase.explicit, Phase.reuse, Phase.generate]
)
if os.environ.get("RL_PG_MUTATION"):
    settings.load_profile("mutation")

# One torch thread per test process: pytest-xdist runs one test process per core, and two
# processes of two threads each on two cores made the in-process tests 2-3x slower
# (the threads of one wait, spinning, on those of the other). What a test needs more of
# it sets itself, as the training loop does (TrainConfig.threads).
torch.set_num_threads(1)

# Worker processes started in this process (collectors, ParallelEnv, evaluation workers)
# fork from a server that has imported torch, TorchRL and rl_pg once, as the rl-pg
# command's do, instead of paying those imports in every worker (5-10 s here). The
# scripts that import rl_pg (tests/test_docs.py runs the docs' scripts) keep TorchRL's
# default, spawn.
multiprocessing.set_start_method("forkserver", force=True)
multiprocessing.set_forkserver_preload(WORKER_IMPORTS)


# The order of the run. First the kernels' tests: between them they compile every
# signature of the numba kernels (about 2 s each), which numba caches on disk, so that
# the processes started later load them instead of each compiling its own (CI starts
# with an empty cache). Then the test files whose tests take longest (processes,
# trainings, the docs), longest first, before the many short ones: each worker takes
# its next test only when it has two left (pytest_xdist_make_scheduler), so the run ends
# on short tests on both workers instead of one finishing a long test while the other
# waits.
RUN_FIRST = (
    "test_scan", "test_functional",
    "test_benchmarks", "test_loop", "test_docs", "test_site", "test_cli", "test_metadrive",
    "test_tuning", "test_agents", "test_exact_gradients", "test_evaluation",
    "test_segment_collector", "test_recipes", "test_callbacks", "test_tutorials",
)  # fmt: skip


# Tests that share an expensive session- or class-scoped fixture, by the start of their
# ids: each group runs in one test process, which builds the fixture once, instead of
# every process that is handed one of them building its own (the gridworld's gradient
# estimates: 20-30 s each in the suite). pytest-xdist's `xdist_group` mark is meant for
# this, but under pytest 9.2 it no longer groups anything (pytest-xdist#1386).
SHARED_FIXTURES = {
    "gridworld": tuple(
        f"tests/test_exact_gradients.py::{name}::"
        for name in (
            "TestGridworldGradient",
            "TestGridworldGroupGradient",
            "TestNaturalGradientDirection",
            "TestGridworldNoiseStatistics",
            "TestCollectedEpisodes",
        )
    ),
    # The kernels' tests, which compile every signature of the numba kernels (see
    # RUN_FIRST): in two processes at once, each compiled many of them itself (CI starts
    # with an empty cache), 40 % more CPU than in one.
    "kernels": ("tests/test_scan.py::", "tests/test_functional.py::"),
    # One local Ray instance (pytest_runtest_setup below): its start and stop cost
    # 5-6 s of CPU each. The docs' page on composing trains on Ray as a user would.
    "ray": (
        "tests/test_docs.py::test_page_code_runs[composing.md]",
        "tests/test_benchmarks.py::test_distributed",
        "tests/test_loop.py::TestTrain::test_workers_freeze_their_imports_get_new_weights_and_are_replaced_when_lost[True]",
        "tests/test_loop.py::TestTrain::test_ray_workers_that_cannot_join_the_weight_sync_say_why",
        "tests/test_evaluation.py::test_episode_workers_on_ray_actors_play_each_share_in_order_and_report_a_failure",
    ),
}


def pytest_collection_modifyitems(items):
    missing = [name for name in RUN_FIRST if not Path(__file__).with_name(f"{name}.py").is_file()]
    if missing:  # a renamed file would silently fall back to the end of the run
        raise pytest.UsageError(f"tests/conftest.py RUN_FIRST names no test file: {missing}")
    root = Path(__file__).parents[1]
    unused = []
    for prefix in (prefix for prefixes in SHARED_FIXTURES.values() for prefix in prefixes):
        file, *names = prefix.rstrip(":").split("::")
        if not (root / file).is_file():
            unused.append(prefix)
            continue
        name = names[-1].split("[")[0] if names else ""  # a class, a test function or method
        if name and not re.search(rf"^\s*(class|def) {name}\b", (root / file).read_text(), re.M):
            unused.append(prefix)
    if unused:  # a renamed test would silently run apart again
        raise pytest.UsageError(f"tests/conftest.py SHARED_FIXTURES names no test: {unused}")
    rank = {name: i for i, name in enumerate(RUN_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))  # stable: files stay whole


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook
def pytest_xdist_make_scheduler(config, log):
    """pytest-xdist's load scheduling (`-n`), with the groups of SHARED_FIXTURES: every
    other test is a unit of its own, and a process is handed the next unit in the
    order of the run when it has two tests or fewer left."""
    if config.getvalue("dist") != "load":  # another --dist asked for: xdist's own
        return None
    from xdist.scheduler import LoadScopeScheduling

    class SharedFixtureScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            for group, prefixes in SHARED_FIXTURES.items():
                if nodeid.startswith(prefixes):
                    return group
            return nodeid

    return SharedFixtureScheduling(config, log)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    """The tests of SHARED_FIXTURES["ray"] run on one local Ray instance of 2 CPUs,
    started as a training with --ray starts it (its actors import what this process
    imports) before the first of them and stopped after the last."""
    if item.nodeid.startswith(SHARED_FIXTURES["ray"]) and importlib.util.find_spec("ray"):
        from rl_pg.training.cluster import start_ray

        start_ray(2)  # nothing if it runs


def pytest_runtest_teardown(item, nextitem):
    ray_tests = SHARED_FIXTURES["ray"]
    last = nextitem is None or not nextitem.nodeid.startswith(ray_tests)
    if item.nodeid.startswith(ray_tests) and last:
        ray = sys.modules.get("ray")
        if ray is not None and ray.is_initialized():
            ray.shutdown()


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Each test leaves this process with one torch thread, as it found it. Closing
    TorchRL's ParallelEnv, or numba starting its OpenMP threads in a test that calls a
    kernel itself, set it to the core count, and every later test in this process then
    spent two to six times the CPU (two processes of two threads on two cores)."""
    yield
    if torch.get_num_threads() != 1:
        torch.set_num_threads(1)


@pytest.fixture
def local_ray():
    """Ray, initialised (for the tests of SHARED_FIXTURES["ray"])."""
    ray = pytest.importorskip("ray")
    assert ray.is_initialized(), "a test that takes local_ray belongs to SHARED_FIXTURES['ray']"
    return ray


def pytest_collection_finish(session):
    # What the imports and the collection built (torch, TorchRL, MetaDrive, ..., the
    # tests: some 400,000 tracked objects) lives as long as this process, yet every full
    # collection walks it: the ones the allocations trigger, and the gc.collect() that
    # MetaDrive calls twice at each engine's close (0.3 s each here, 0.6 s a close).
    # Frozen, as the rl-pg command freezes its own (rl_pg._process.frozen_heap): the
    # collector goes on collecting what the tests make. About a sixth of the CPU time
    # of tests/test_metadrive.py, test_callbacks.py and test_selection.py.
    gc.freeze()


def make_categorical_actor(
    n_obs: int = N_OBS, n_act: int = N_ACT, observation_key="observation"
) -> ProbabilisticActor:
    return ProbabilisticActor(
        TensorDictModule(nn.Linear(n_obs, n_act), [observation_key], ["logits"]),
        in_keys=["logits"],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )


def make_one_hot_actor(n_obs: int = N_OBS, n_act: int = N_ACT) -> ProbabilisticActor:
    return ProbabilisticActor(
        TensorDictModule(nn.Linear(n_obs, n_act), ["observation"], ["logits"]),
        in_keys=["logits"],
        distribution_class=OneHotCategorical,
        return_log_prob=True,
    )


def make_gaussian_actor(
    n_obs: int = N_OBS,
    n_act: int = N_ACT,
    distribution_class=TanhNormal,
    observation_key: str = "observation",
) -> ProbabilisticActor:
    """A Gaussian policy that, like TorchRL's test actors, declares no action bounds."""
    net = nn.Sequential(nn.Linear(n_obs, 2 * n_act), NormalParamExtractor())
    return ProbabilisticActor(
        TensorDictModule(net, [observation_key], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=distribution_class,
        return_log_prob=True,
        spec=Unbounded(n_act),
    )


class _TwoHeads(nn.Module):
    def __init__(self, n_obs: int) -> None:
        super().__init__()
        self.linear = nn.Linear(n_obs, 5)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.linear(observation)
        return out[..., :2], out[..., 2:]


def make_composite_actor(n_obs: int = N_OBS, action: str | None = "action"):
    """Two categorical heads, of 2 and 3 choices, as one action (tensordict's
    CompositeDistribution): the action is ``(action, "a")`` and ``(action, "b")``, or
    ``"a"`` and ``"b"`` with ``action=None``."""
    from tensordict.nn import CompositeDistribution
    from tensordict.nn import ProbabilisticTensorDictModule as Head
    from tensordict.nn import ProbabilisticTensorDictSequential as Policy

    heads = {"a": torch.distributions.Categorical, "b": torch.distributions.Categorical}
    names = {k: k if action is None else (action, k) for k in heads}
    return Policy(
        TensorDictModule(_TwoHeads(n_obs), ["observation"],
                         [("params", k, "logits") for k in heads]),
        Head(
            in_keys=["params"], out_keys=[names[k] for k in heads],
            distribution_class=CompositeDistribution,
            distribution_kwargs={"distribution_map": heads, "name_map": names},
        ),
    )  # fmt: skip


def make_critic(n_obs: int = N_OBS, observation_key="observation") -> ValueOperator:
    return ValueOperator(nn.Linear(n_obs, 1), in_keys=[observation_key])


def make_batch(
    action: torch.Tensor, *, n_obs: int = N_OBS, p_done: float = 0.2, seed: int = 0
) -> TensorDict:
    """A ``[B, T]`` collector-like batch for the given actions."""
    generator = torch.Generator().manual_seed(seed)
    shape = action.shape[:2]
    done = torch.rand(*shape, 1, generator=generator) < p_done
    return TensorDict(
        {
            "observation": torch.randn(*shape, n_obs, generator=generator),
            "action": action,
            "next": {
                "observation": torch.randn(*shape, n_obs, generator=generator),
                "reward": torch.randn(*shape, 1, generator=generator),
                "done": done,
                "terminated": done.clone(),
            },
        },
        batch_size=shape,
    )


@pytest.fixture
def categorical_actor():
    torch.manual_seed(0)
    return make_categorical_actor()


@pytest.fixture
def critic():
    torch.manual_seed(1)
    return make_critic()


@pytest.fixture
def categorical_batch():
    generator = torch.Generator().manual_seed(2)
    return make_batch(torch.randint(N_ACT, (3, 7), generator=generator))


def run_weights(run_dir: Path) -> dict:
    """The loss's parameters and buffers in a run directory's checkpoint, and those of
    its policy average (``policy_ema``) if it keeps one."""
    saved = load_checkpoint(run_dir / "checkpoint.pt")
    average = averaged_weights(saved) or {}
    return {**saved["loss"], **{f"policy_average.{k}": v for k, v in average.items()}}


def averaged_weights(saved: dict) -> dict | None:
    """The ``AveragedModel`` state a checkpoint keeps (``policy_ema``), None without."""
    return callback_states(saved).get(POLICY_AVERAGE, {}).get("weights")


def assert_same_run(summary: dict, run_dir: Path, straight_dir: Path) -> None:
    """``run_dir`` (resumed) ended exactly like the uninterrupted run in ``straight_dir``."""
    expected = json.loads((straight_dir / "summary.json").read_text())
    for key in ("frames", "updates", "eval_mean_return"):
        assert summary[key] == expected[key]
    for key, value in run_weights(straight_dir).items():
        assert torch.equal(value, run_weights(run_dir)[key]), key


def hide_module(monkeypatch, name: str) -> None:
    """Makes ``importlib.util.find_spec`` report ``name`` as not installed, as on a
    machine without it."""
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda module, *args: None if module == name else find_spec(module, *args),
    )
