"""What a recipe is: a config class and how to build the run's environments and models.

Training, deployment (``rl-pg play``), the tests, the benchmarks and the docs all
reach a recipe through this interface, and built-in recipes by name through
[`rl_pg.recipes.load`][rl_pg.recipes.load]. A recipe of your own is a ``Recipe`` in
an importable module::

    RECIPE = Recipe(
        name="my-task",
        config=MyConfig,                       # a TrainConfig subclass
        make_env=make_env,                     # (cfg, *, render=False) -> EnvBase
        make_models=make_models,               # (env, cfg) -> (actor, critic or None)
    )
    RECIPE.train(MyConfig(seed=1))

Its runs record the module, so ``rl-pg play RUN_DIR`` can rebuild them.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from rl_pg._checks import check_names
from rl_pg.evaluation import EvaluationEnv, evaluate, reported
from rl_pg.training.callbacks import Callback
from rl_pg.training.checkpoints import check_average, has_average, load_models
from rl_pg.training.config import TrainConfig
from rl_pg.training.loop import train
from rl_pg.training.metric import Metric
from rl_pg.training.seeds import fresh_seed
from rl_pg.training.threads import torch_threads

__all__ = ["Recipe"]

Models = tuple[TensorDictModuleBase, TensorDictModuleBase | None]


@dataclass(frozen=True)
class Recipe:
    """A training experiment, as ``train``, ``play`` and ``rl-pg`` use it.

    Args:
        name (str): what the run directory and the summary call it.
        config (type): its ``TrainConfig`` subclass; the defaults are the recipe's.
        make_env (callable): ``(cfg, *, render=False) -> EnvBase``, the training
            environment; with ``render=True``, one environment that renders RGB frames
            (for recordings). Module-level functions keep multi-process collection
            possible (they are pickled).
        make_models (callable): ``(env, cfg) -> (actor, critic or None)``.
        make_play_env (callable, optional): ``(cfg, *, render=False) -> EnvBase``, the
            one environment ``rl-pg play`` deploys an agent in, recorded or not, when it
            must differ from the training one (Pong plays as it evaluates, with sticky
            actions). Defaults to ``make_env``.
        make_eval_env (callable, optional): ``cfg -> EnvBase`` (or an
            [`EpisodeWorkers`][rl_pg.episode_workers.EpisodeWorkers], whose processes play
            whole episodes each) for the evaluations during training, which pick the
            best checkpoint. Defaults to ``make_env``.
        make_test_env (callable, optional): ``cfg -> EnvBase`` (or ``EpisodeWorkers``)
            that scores a trained agent (``rl-pg evaluate``), when it must differ
            from the one that picked the checkpoint (a fixed set of levels, say:
            scored on those it was chosen on, the best checkpoint looks better than it
            is). Defaults to ``make_eval_env``, which fresh seeds then keep apart.
        test_sets (dict, optional): ``{name: cfg -> EnvBase or EpisodeWorkers}``, other
            environments ``rl-pg evaluate --on NAME`` can score an agent on (MetaDrive:
            its training and selection scenarios, to compare with the held-out ones).
            Defaults to none.
        eval_flags (sequence of str): boolean entries evaluations report as rates
            (``("crashed",)``). Defaults to ``()``.
        eval_values (sequence of str): entries whose value at an episode's end
            evaluations average (``("route_completion",)``). Defaults to ``()``.
        prepare (callable, optional): ``cfg -> cfg``, run before training (a default
            that depends on the environment, for example).
        summarise (callable, optional): ``(cfg, run_dir) -> dict``, fields the recipe
            adds to the run's summary, read from its logs.
        commands (dict, optional): ``{flag: cfg -> dict}``: when the config's boolean
            field ``flag`` is set, the command line runs this (a comparison of several
            runs, say) instead of one training. Defaults to none.
    """

    name: str
    config: type[TrainConfig]
    make_env: Callable[..., EnvBase]
    make_models: Callable[[EnvBase, Any], Models]
    make_eval_env: Callable[[Any], EvaluationEnv] | None = None
    make_play_env: Callable[..., EnvBase] | None = None
    make_test_env: Callable[[Any], EvaluationEnv] | None = None
    test_sets: dict[str, Callable[[Any], EvaluationEnv]] = field(default_factory=dict)
    eval_flags: Sequence[str] = ()
    eval_values: Sequence[str] = ()
    prepare: Callable[[Any], Any] | None = None
    summarise: Callable[[Any, Any], dict[str, Any]] | None = None
    commands: dict[str, Callable[[Any], dict[str, Any]]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (isinstance(self.config, type) and issubclass(self.config, TrainConfig)):
            raise TypeError(
                f"Recipe {self.name!r}: config must be a TrainConfig subclass, got {self.config!r}."
            )
        object.__setattr__(self, "eval_flags", check_names("eval_flags", self.eval_flags))
        object.__setattr__(self, "eval_values", check_names("eval_values", self.eval_values))
        default = Metric.of(self.config)
        try:
            self.check_metric(default)
        except ValueError as err:
            raise ValueError(f"Recipe {self.name!r}, its config's default: {err}") from None
        names = {f.name for f in dataclasses.fields(self.config)}
        unknown = sorted(set(self.commands) - names)
        if unknown:
            raise ValueError(
                f"Recipe {self.name!r}: commands {unknown} are not fields of "
                f"{self.config.__name__}; each command is switched on by a bool field."
            )

    def check_metric(self, metric: Metric) -> Metric:
        """``metric`` if its evaluations report it (see
        [`reported`][rl_pg.evaluation.reported]); else a ValueError naming the entries
        they do."""
        return metric.check(reported(self.eval_flags, self.eval_values))

    @property
    def module(self) -> str:
        """The module that defines the recipe's functions (recorded in its runs)."""
        return self.make_env.__module__

    def test_env(self, cfg: TrainConfig, on: str | None = None) -> EvaluationEnv:
        """The environment that scores a trained agent (see ``make_test_env``), or with
        ``on``, the one of ``test_sets`` of that name."""
        if on is None:
            make = self.make_test_env or self.make_eval_env or self.make_env
            return make(cfg)
        if on not in self.test_sets:
            choices = (
                f"choose one of {sorted(self.test_sets)}"
                if self.test_sets
                else "it scores agents on its test environment only: leave --on out"
            )
            raise ValueError(f"Recipe {self.name!r} has no test set {on!r}: {choices}.")
        return self.test_sets[on](cfg)

    def evaluate_checkpoint(
        self,
        saved: dict[str, Any],
        *,
        episodes: int = 100,
        sample: bool = False,
        seed: int | None = None,
        action_stats: bool = False,
        on: str | None = None,
        trained_weights: bool = False,
    ) -> dict[str, Any]:
        """Plays a checkpoint of this recipe's (from
        [`read_run`][rl_pg.training.checkpoints.read_run]) on the test environment.

        Keyword Args:
            episodes (int): episodes to play. Defaults to ``100``.
            sample (bool): sample actions instead of acting greedily. Defaults to ``False``.
            seed (int, optional): seed of the environment and of sampled actions.
                Defaults to one no evaluation during training used
                ([`fresh_seed`][rl_pg.training.seeds.fresh_seed]), so the episodes are fresh.
            action_stats (bool): also report how a discrete policy acted (see
                [`evaluate`][rl_pg.evaluation.evaluate]). Defaults to ``False``.
            on (str, optional): play on this one of the recipe's ``test_sets`` instead.
            trained_weights (bool): of a run trained with ``policy_ema``, play the
                trained weights rather than their average (see
                [`load_models`][rl_pg.training.checkpoints.load_models]). Defaults to
                ``False``.

        Returns:
            The checkpoint's ``frames``, the ``mode`` (``"greedy"`` or ``"sampled"``),
            ``episodes``, ``seed`` (and ``on``, if given; ``weights``, ``"average"`` or
            ``"trained"``, if the checkpoint keeps an average), the evaluation's metrics
            and the ``seconds`` it took.
        """
        cfg = self.config.from_stored(saved["config"])
        check_average(saved, not trained_weights)  # before any simulator starts
        averaged = has_average(saved)
        seed = fresh_seed(cfg.seed) if seed is None else seed
        with torch_threads(cfg.threads):  # as the run's own evaluations played
            env = self.test_env(cfg, on)
            try:
                actor, critic = self.make_models(env, cfg)
                load_models(saved, actor, critic, average=not trained_weights)
                torch.manual_seed(seed)
                env.set_seed(seed)
                start = time.perf_counter()
                result = evaluate(
                    actor, env, episodes=episodes, deterministic=not sample,
                    flags=self.eval_flags, values=self.eval_values, action_stats=action_stats,
                )  # fmt: skip
                seconds = time.perf_counter() - start
            finally:
                env.close()  # some simulators (MetaDrive) allow one open environment per process
        return {
            "frames": saved.get("state", {}).get("frames"),
            "mode": "sampled" if sample else "greedy",
            "episodes": episodes,
            "seed": seed,
            **({} if on is None else {"on": on}),
            **({"weights": "trained" if trained_weights else "average"} if averaged else {}),
            **result,
            "seconds": seconds,
        }

    @property
    def description(self) -> str:
        """The first paragraph of the config's docstring, as one line."""
        paragraph = (self.config.__doc__ or self.name).strip().split("\n\n")[0]
        return " ".join(line.strip() for line in paragraph.splitlines())

    def train(
        self, cfg: TrainConfig | None = None, *, callbacks: Sequence[Callback] = ()
    ) -> dict[str, Any]:
        """Trains with ``cfg`` (default: the recipe's defaults) and ``callbacks`` of
        your own (see [`Callback`][rl_pg.training.callbacks.Callback]); returns the
        summary."""
        cfg = self.config() if cfg is None else cfg
        if not isinstance(cfg, self.config):
            raise TypeError(
                f"Recipe {self.name!r} trains with its own {self.config.__name__}, got "
                f"{type(cfg).__name__}."
            )
        if self.prepare is not None:
            cfg = self.prepare(cfg)
        # A command's flag (e.g. --compare) chose what to run, it is no setting of the
        # run: stored, it would make `rl-pg resume` run the command again inside it.
        cfg = dataclasses.replace(cfg, **{flag: False for flag in self.commands})
        eval_env = self.make_eval_env or self.make_env
        return train(
            cfg,
            recipe=self.name,
            recipe_module=self.module,
            make_env=partial(self.make_env, cfg),
            make_models=partial(_call_with_cfg, self.make_models, cfg),
            make_eval_env=partial(eval_env, cfg),
            eval_flags=self.eval_flags,
            eval_values=self.eval_values,
            summarise=None if self.summarise is None else partial(self.summarise, cfg),
            callbacks=callbacks,
        )

    def run(self, cfg: TrainConfig) -> dict[str, Any]:
        """What the command line does: the command whose flag is set, else ``train``;
        a resume always resumes the run (a command starts runs of its own)."""
        if cfg.resume:
            asked = [flag for flag in self.commands if getattr(cfg, flag)]
            if asked:
                print(
                    f"--{asked[0].replace('_', '-')} starts new runs and does not resume; "
                    f"resuming the run in {cfg.run_dir} instead.",
                    file=sys.stderr,
                )
            return self.train(cfg)
        for flag, command in self.commands.items():
            if getattr(cfg, flag):
                return command(cfg)
        return self.train(cfg)


def _call_with_cfg(make_models, cfg, env):
    return make_models(env, cfg)
