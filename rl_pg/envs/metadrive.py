"""MetaDrive offline and headless, over fixed sets of scenarios.

MetaDrive (``pip install "rl_pg[metadrive]"``, Python < 3.12) generates each driving
scenario (a road network and its traffic) from an integer, the scenario index. Its
engine downloads an ``assets`` folder (3-D models, textures, fonts) the first time an
environment resets, whatever is rendered. Headless runs on state observations read
none of those files, so [`MetaDriveScenarios`][rl_pg.envs.metadrive.MetaDriveScenarios]
skips that download, and only it, when the assets are absent and nothing is rendered
in 3-D; nothing is ever written into MetaDrive's installed package. A user who pulled
the assets (``python -m metadrive.pull_asset``) keeps everything MetaDrive offers,
3-D rendering and camera observations included.

Importing this module registers gymnasium ids (MetaDrive itself no longer does since
0.4.2), each a range of scenarios with a time limit of ``DEFAULT_HORIZON`` steps:

| id | scenarios | what for |
|---|---|---|
| ``MetaDrive-validation-v0`` | 0 - 999 | the driving tutorials' (as MetaDrive <= 0.4.1 had it) |
| ``MetaDrive-10env-v0`` | 1000 - 1009 | MetaDrive's former training sets |
| ``MetaDrive-100envs-v0`` | 1000 - 1099 | |
| ``MetaDrive-1000envs-v0`` | 1000 - 1999 | |
| ``rl_pg/MetaDrive-selection-v0`` | 10100 - 10199 | picking the checkpoint to deploy |
| ``rl_pg/MetaDrive-heldout-v0`` | 10000 - 10099 | scoring the deployed agent |

The last two share no scenario with the sets above or with each other, so that the
agent is scored on scenarios it was neither trained nor chosen on.
"""

from __future__ import annotations

import importlib.util
import itertools
import sys
from collections.abc import Sequence
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from torchrl.envs import EnvBase, GymEnv, TransformedEnv

from rl_pg._checks import check_int
from rl_pg.discretize import DiscretizeAction
from rl_pg.envs.gym import DRIVING_ACTIONS
from rl_pg.envs.info import InfoFlags, InfoValues
from rl_pg.envs.metadrive_assets import assets_pull_skipped
from rl_pg.evaluation import episode_shares

__all__ = [
    "DEFAULT_HORIZON",
    "HELD_OUT",
    "METADRIVE_FLAGS",
    "METADRIVE_VALUES",
    "SCENARIO_SETS",
    "SELECTION",
    "MetaDriveScenarios",
    "driving_actions",
    "metadrive_env",
    "require_metadrive",
    "split_scenarios",
]

DEFAULT_HORIZON = 1000
"""Steps (0.1 s of simulated time each) before an episode is truncated. MetaDrive sets
no limit; a uniformly random driver wanders for 500 to more than 5 000 steps, while a
route driven at full speed takes 100 to 300."""

HELD_OUT = "rl_pg/MetaDrive-heldout-v0"
"""The id of the held-out scenarios (10000 - 10099), which score a trained agent."""

SELECTION = "rl_pg/MetaDrive-selection-v0"
"""The id of the scenarios (10100 - 10199) that evaluations during training play to pick
the checkpoint to deploy, apart from those that score it."""

SCENARIO_SETS: dict[str, tuple[int, int]] = {
    "MetaDrive-validation-v0": (0, 1000),
    "MetaDrive-10env-v0": (1000, 10),
    "MetaDrive-100envs-v0": (1000, 100),
    "MetaDrive-1000envs-v0": (1000, 1000),
    HELD_OUT: (10_000, 100),
    SELECTION: (10_100, 100),
}
"""``id -> (first scenario index, number of scenarios)``."""

METADRIVE_FLAGS = ("arrive_dest", "crash", "out_of_road", "max_step")
"""MetaDrive's episode-end reasons: success, any collision, off the road, time limit."""

METADRIVE_VALUES = ("route_completion", "episode_speed")
"""Numbers read at an episode's end: the share of the route driven, and the average speed
over the episode in km/h."""

_INSTALL = 'pip install -c constraints.txt "rl_pg[metadrive]"'


def require_metadrive() -> None:
    """Raises ``ModuleNotFoundError`` saying how to install MetaDrive, if it is missing."""
    if importlib.util.find_spec("metadrive") is not None:
        return
    if sys.version_info >= (3, 12):
        raise ModuleNotFoundError(
            "MetaDrive is not installed, and it publishes no package for Python "
            f"{sys.version_info[0]}.{sys.version_info[1]} (metadrive-simulator "
            "needs Python < 3.12): use a Python 3.10 or 3.11 environment for the "
            "MetaDrive recipe, or drive in highway-env instead (`rl-pg train highway`)."
        )
    raise ModuleNotFoundError(f"MetaDrive is not installed: `{_INSTALL}`.")


def driving_actions(order: Literal["tutorial", "swapped"] = "tutorial") -> list[list[float]]:
    """The 9 driving actions as MetaDrive receives them (``[steering, throttle]``).

    The driving tutorial wrote its table as (throttle, steering) pairs, throttle in
    {+1, 0, -1} and steering in {+0.6, 0, -0.6}, index ``3i + j``
    ([`DRIVING_ACTIONS`][rl_pg.envs.DRIVING_ACTIONS]), and handed each pair to MetaDrive
    as it was. MetaDrive reads ``[steering, throttle]``, so the tutorial's agent
    actually steered with +-1 and throttled with +-0.6. ``"tutorial"`` keeps that;
    ``"swapped"`` applies the table as it was written (steering +-0.6, full throttle
    and brake).

    Examples:
        >>> from rl_pg.envs.metadrive import driving_actions
        >>> driving_actions("tutorial")[1], driving_actions("swapped")[1]
        ([1.0, 0.0], [0.0, 1.0])
    """
    if order == "tutorial":
        return [list(pair) for pair in DRIVING_ACTIONS]
    if order == "swapped":
        return [[steering, throttle] for throttle, steering in DRIVING_ACTIONS]
    raise ValueError(f"order must be 'tutorial' or 'swapped', got {order!r}.")


class MetaDriveScenarios(gym.Wrapper):
    """A MetaDrive driving environment over a fixed range of scenarios, gymnasium 1.x style.

    * ``reset(seed=s)`` seeds the choice of scenarios, so any seed is valid (MetaDrive's
      own ``reset(seed)`` takes a scenario index and fails outside its range); a plain
      ``reset()`` moves on to the next scenario: drawn uniformly at random
      (``order="random"``, for training) or the following index, wrapping around
      (``order="sequential"``, for evaluation: ``num_scenarios`` consecutive resets
      visit every scenario once). ``reset(options={"scenario": k})`` plays scenario
      ``k`` itself. ``info["scenario"]`` says which one is played.
    * Episodes are truncated after ``horizon`` steps (MetaDrive's ``horizon`` setting:
      ``truncated`` is true, ``terminated`` false).
    * ``info["episode_speed"]`` is the car's average speed over the episode so far, in
      km/h (from MetaDrive's per-step ``info["velocity"]``, in m/s): how fast a driver
      covers its route, which MetaDrive's own metrics do not say.
    * The asset download is skipped when the assets are absent and nothing is
      rendered in 3-D (see the module's documentation).
    * ``render_mode="rgb_array"``: ``render()`` returns MetaDrive's top-down view,
      which needs no assets.
    * MetaDrive runs one engine per process: a second environment alive in the same
      process raises an error that says so.

    Args:
        start_seed (int): the first scenario index.
        num_scenarios (int): how many consecutive scenarios.

    Keyword Args:
        order (str): ``"random"`` or ``"sequential"``. Defaults to ``"random"``.
        horizon (int): the time limit in steps. Defaults to ``DEFAULT_HORIZON``.
        render_mode (str, optional): ``"rgb_array"`` for top-down frames.
        topdown_size (int): width and height of the top-down frames, in pixels.
            Defaults to ``400``.
        config (dict, optional): any other MetaDrive setting (``traffic_density``, ...).

    Raises:
        ModuleNotFoundError: MetaDrive is not installed (the message says how).
        ValueError: a bad range, order, horizon or render mode, or MetaDrive settings
            that contradict the arguments.
    """

    metadata = {"render_modes": ["rgb_array"]}  # noqa: RUF012 (gymnasium's convention)

    def __init__(
        self,
        start_seed: int,
        num_scenarios: int,
        *,
        order: Literal["random", "sequential"] = "random",
        horizon: int = DEFAULT_HORIZON,
        render_mode: str | None = None,
        topdown_size: int = 400,
        config: dict[str, Any] | None = None,
    ) -> None:
        require_metadrive()
        start_seed = check_int("start_seed", start_seed, low=0)
        num_scenarios = check_int("num_scenarios", num_scenarios, low=1)
        horizon = check_int("horizon", horizon, low=1)
        self.topdown_size = check_int("topdown_size", topdown_size, low=16)
        if order not in ("random", "sequential"):
            raise ValueError(f"order must be 'random' or 'sequential', got {order!r}.")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(
                f"render_mode must be None or 'rgb_array' (top-down frames), got {render_mode!r}. "
                "For MetaDrive's 3-D window pass config={'use_render': True}."
            )
        config = dict(config or {})
        for name in ("start_seed", "num_scenarios", "horizon"):
            if name in config:
                raise ValueError(f"Pass {name} as an argument, not in config.")
        config.update(start_seed=start_seed, num_scenarios=num_scenarios, horizon=horizon)
        config.setdefault("log_level", 40)  # MetaDrive logs every episode end at INFO

        from metadrive.envs import MetaDriveEnv

        _leave_sigint_to_the_caller()
        super().__init__(MetaDriveEnv(config))
        self.scenarios = range(start_seed, start_seed + num_scenarios)
        self.order = order
        self._render_mode = render_mode
        self._rng = np.random.default_rng()
        self._next = 0  # position of the next scenario in `scenarios` (sequential order)
        self._speed_sum = 0.0  # m/s, summed over the episode's steps
        self._steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
            self._next = seed % len(self.scenarios)
        scenario = self._pick(options or {})
        self._check_one_engine()
        with assets_pull_skipped(self.env):
            observation, info = self.env.reset(seed=scenario)
        info["scenario"] = scenario
        self._speed_sum, self._steps = 0.0, 0
        info["episode_speed"] = 0.0
        return observation, info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        observation, reward, terminated, truncated, info = self.env.step(action)
        self._speed_sum += float(info["velocity"])
        self._steps += 1
        info["episode_speed"] = 3.6 * self._speed_sum / self._steps
        return observation, reward, terminated, truncated, info

    @property
    def render_mode(self) -> str | None:
        return self._render_mode

    def render(self) -> np.ndarray | None:
        if self._render_mode != "rgb_array":
            return self.env.render()
        size = (self.topdown_size, self.topdown_size)
        return self.env.render(mode="topdown", window=False, screen_size=size)

    def _pick(self, options: dict[str, Any]) -> int:
        if "scenario" in options:
            scenario = check_int("options['scenario']", options["scenario"], low=0)
            if scenario not in self.scenarios:
                raise ValueError(
                    f"Scenario {scenario} is not in this environment's scenarios "
                    f"{self.scenarios.start}-{self.scenarios.stop - 1}."
                )
            return scenario
        if self.order == "random":
            return self.scenarios[int(self._rng.integers(len(self.scenarios)))]
        scenario = self.scenarios[self._next]
        self._next = (self._next + 1) % len(self.scenarios)
        return scenario

    def _check_one_engine(self) -> None:
        from metadrive.engine.engine_utils import engine_initialized, get_global_config

        if engine_initialized() and get_global_config() is not self.env.config:
            raise RuntimeError(
                "Another MetaDrive environment is open in this process, and MetaDrive "
                "runs one per process: close it first (env.close()), or build this one "
                "in a process of its own (torchrl.envs.ParallelEnv(1, make_env, "
                "mp_start_method='spawn'), or collect with --workers 2 or more)."
            )


def _leave_sigint_to_the_caller() -> None:
    """Stops Panda3D's task manager from taking Ctrl-C over.

    For each frame it swaps in a SIGINT handler of its own and, after the frame, raises
    ``KeyboardInterrupt`` past the handler of whoever stepped the environment: a
    training run, which finishes its update and saves on Ctrl-C, would end without
    its last checkpoint whenever the signal fell inside a simulator step. Panda3D skips
    that swap where its task module has no ``signal`` (platforms without one); so do we.
    """
    import direct.task.Task as panda_tasks

    panda_tasks.signal = None


def metadrive_env(
    env_id: str = "MetaDrive-validation-v0",
    *,
    actions: Literal["tutorial", "swapped"] | None = "tutorial",
    order: Literal["random", "sequential"] = "random",
    horizon: int = DEFAULT_HORIZON,
    flags: Sequence[str] = METADRIVE_FLAGS,
    render: bool = False,
    scenarios: range | None = None,
    config: dict[str, Any] | None = None,
) -> EnvBase:
    """A registered MetaDrive scenario set as a TorchRL environment.

    Args:
        env_id (str): one of ``SCENARIO_SETS``. Defaults to the tutorials'
            ``"MetaDrive-validation-v0"``.

    Keyword Args:
        actions (str, optional): the 9-action table (see
            [`driving_actions`][rl_pg.envs.metadrive.driving_actions]) the policy
            chooses from; ``None`` keeps MetaDrive's continuous ``[steering, throttle]``.
            Defaults to ``"tutorial"``.
        order (str): how scenarios follow each other (see
            [`MetaDriveScenarios`][rl_pg.envs.metadrive.MetaDriveScenarios]).
        horizon (int): the time limit in steps. Defaults to ``DEFAULT_HORIZON``.
        flags (sequence of str): MetaDrive's boolean ``info`` entries to expose.
            ``route_completion`` (a float, the share of the route driven) and
            ``episode_speed`` (the average speed so far, km/h) always are.
        render (bool): add top-down frames under ``"pixels"``. Defaults to ``False``.
        scenarios (range, optional): play only these scenarios of the set (e.g. one
            evaluation worker's part, see
            [`split_scenarios`][rl_pg.envs.metadrive.split_scenarios]); a scenario is
            the same map and traffic whichever range it is played from. Defaults to
            the whole set.
        config (dict, optional): other MetaDrive settings.

    Raises:
        ValueError: an id that is not one of ``SCENARIO_SETS``, or ``scenarios`` that
            are not a consecutive part of it.
        ModuleNotFoundError: MetaDrive is not installed.
    """
    whole = _scenario_range(env_id)
    require_metadrive()
    kwargs: dict[str, Any] = {"order": order, "horizon": horizon, "config": config}
    if scenarios is not None:
        if (
            not isinstance(scenarios, range)
            or scenarios.step != 1
            or len(scenarios) == 0
            or scenarios.start not in whole
            or scenarios[-1] not in whole
        ):
            raise ValueError(
                f"scenarios must be a non-empty range of consecutive scenarios of {env_id} "
                f"({whole!r}), got {scenarios!r}."
            )
        kwargs.update(start_seed=scenarios.start, num_scenarios=len(scenarios))
    if render:
        kwargs.update(from_pixels=True, pixels_only=False)
    env = GymEnv(env_id, **kwargs)
    env.set_info_dict_reader(InfoValues(METADRIVE_VALUES))
    if flags:
        env.set_info_dict_reader(InfoFlags(flags))
    if actions is None:
        return env
    return TransformedEnv(env, DiscretizeAction(actions=driving_actions(actions)))


def split_scenarios(env_id: str, parts: int, count: int | None = None) -> list[range]:
    """Cuts the first ``count`` scenarios of a set (all of them by default) into
    ``parts`` consecutive ranges, the first ones one longer when it does not divide
    evenly: the shares of an evaluation whose ``parts`` environments play those
    scenarios once, side by side (see [`evaluate`][rl_pg.evaluation.evaluate]).

    Examples:
        >>> from rl_pg.envs.metadrive import HELD_OUT, split_scenarios
        >>> split_scenarios(HELD_OUT, 3)
        [range(10000, 10034), range(10034, 10067), range(10067, 10100)]
        >>> split_scenarios(HELD_OUT, 2, count=5)
        [range(10000, 10003), range(10003, 10005)]
    """
    whole = _scenario_range(env_id)
    parts = check_int("parts", parts, low=1)
    count = len(whole) if count is None else check_int("count", count, low=1)
    if not parts <= count <= len(whole):
        raise ValueError(
            f"{env_id} has {len(whole)} scenarios: its first {count} cannot be cut into "
            f"{parts} parts (need parts <= count <= {len(whole)})."
        )
    ends = itertools.accumulate(episode_shares(count, parts), initial=whole.start)
    return [range(a, b) for a, b in itertools.pairwise(ends)]


def _scenario_range(env_id: str) -> range:
    if env_id not in SCENARIO_SETS:
        raise ValueError(
            f"Unknown MetaDrive scenario set {env_id!r}; choose one of {list(SCENARIO_SETS)}."
        )
    start, count = SCENARIO_SETS[env_id]
    return range(start, start + count)


def _register() -> None:
    for env_id, (start, count) in SCENARIO_SETS.items():
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point="rl_pg.envs.metadrive:MetaDriveScenarios",
                kwargs={"start_seed": start, "num_scenarios": count},
            )


_register()
