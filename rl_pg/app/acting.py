"""A trained agent in two lines: load it, and ask it for actions.

    from rl_pg.app import Agent
    agent = Agent.load("runs/cartpole-seed0")       # a run, checkpoint or agent file
    action = agent.act(observation)                  # as the environment gives it

``Agent.load("cartpole", pretrained=True)`` loads the agent shipped with rl_pg,
``Agent.load("me/rl_pg-cartpole", hub=True)`` one shared on the Hugging Face Hub.
``act`` takes what the environment returns (a gymnasium observation: an array, a
number, a dict; or a batch of them from a vector environment) and gives back what its
``step`` takes (an ``int`` or an array; a driving agent's ``[acceleration, steering]``
rather than its discrete choice). For TorchRL users, ``agent.policy`` is the actor
module and ``agent.make_env()`` the environment it was trained on, so
``agent.make_env().rollout(1000, agent.policy)`` plays an episode.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rl_pg.app.sources import agent_path
from rl_pg.recipes import recipe_of
from rl_pg.training import load_models, read_run
from rl_pg.training.config import TrainConfig
from rl_pg.training.recipe import Recipe

__all__ = ["Agent"]


class Agent:
    """A trained agent that acts on its environment's observations.

    Build one with [`Agent.load`][rl_pg.app.acting.Agent.load].

    Attributes:
        recipe (Recipe): the recipe that trained it.
        config (TrainConfig): the run's config (one environment).
        policy (TensorDictModule): the actor, with the deployed weights (a
            ``--policy-ema`` run's average, as its evaluations played).
        frames (int or None): the frames it was trained on.

    Examples:
        >>> import gymnasium as gym
        >>> from rl_pg.app import Agent
        >>> agent = Agent.load("cartpole", pretrained=True)
        >>> env = gym.make("CartPole-v1")
        >>> observation, _ = env.reset(seed=0)
        >>> total, done = 0.0, False
        >>> while not done:
        ...     action = agent.act(observation)
        ...     observation, reward, terminated, truncated, _ = env.step(action)
        ...     total, done = total + reward, terminated or truncated
        >>> total
        500.0
    """

    def __init__(self, recipe: Recipe, config: TrainConfig, saved: dict[str, Any]) -> None:
        self.recipe, self.config = recipe, config
        self.frames: int | None = saved.get("state", {}).get("frames")
        env = self.make_env()
        try:
            self.policy, critic = recipe.make_models(env, config)
            load_models(saved, self.policy, critic)
        finally:
            env.close()  # its specs and transforms stay readable; simulators such as
            # MetaDrive allow one open environment per process, which may be the user's
        self.policy.eval()
        self._env = env
        self._base = env.base_env if isinstance(env, TransformedEnv) else env
        self._previous: TensorDictBase | None = None
        # The entries it reads: the policy's, or those its transforms make them from.
        reads = set(self.policy.in_keys)
        if isinstance(env, TransformedEnv):
            reads |= set(env.transform.in_keys)
        self._reads = [key for key in self._base.observation_spec.keys(True, True) if key in reads]

    @classmethod
    def load(
        cls,
        source: str | Path,
        *,
        checkpoint: Literal["best", "last"] = "best",
        pretrained: bool = False,
        hub: bool = False,
    ) -> Agent:
        """Loads a trained agent.

        Args:
            source (str or Path): a run directory, checkpoint or agent file; with
                ``pretrained``, a recipe's name; with ``hub``, a Hugging Face Hub
                repository (``owner/name``).

        Keyword Args:
            checkpoint (str): of a run directory, ``"best"`` (``best.pt``, what
                ``rl-pg play`` deploys) or ``"last"``. Defaults to ``"best"``.
            pretrained (bool): the agent rl_pg ships for the recipe ``source`` names.
                Defaults to ``False``.
            hub (bool): the agent of the Hub repository ``source`` names (needs
                ``rl_pg[hub]``). Defaults to ``False``.

        Raises:
            CheckpointError: nothing loadable at ``source`` (the message says what is
                there and what to give instead).
            ValueError: no agent shipped for that recipe, or the recipe that trained it
                cannot be rebuilt.
        """
        path = agent_path(source, pretrained=pretrained, hub=hub)
        saved = read_run(path, which=checkpoint)
        recipe = recipe_of(saved, path)
        return cls(recipe, recipe.config.from_stored(saved["config"], num_envs=1), saved)

    def make_env(self) -> EnvBase:
        """The environment the agent was trained on, one copy, as a TorchRL env (its
        observation and action transforms included): ``agent.policy`` acts on it."""
        make = self.recipe.make_play_env or self.recipe.make_env
        return make(self.config)

    def reset(self) -> None:
        """Forgets the episode so far: call it when a new episode starts, for agents
        whose observation spans steps (Pong's agent sees the difference of two frames).
        The agents of the other recipes see one observation at a time."""
        self._previous = None

    def act(self, observation: Any, *, sample: bool = False) -> Any:
        """The action for ``observation``.

        Args:
            observation: what the environment returned (one environment's, or a batch
                of them along leading dimensions). A TensorDict from
                ``agent.make_env()`` is acted on the TorchRL way: the action is written
                into it, and it is returned.

        Keyword Args:
            sample (bool): sample the action from the policy instead of taking its
                most probable one. Defaults to ``False`` (greedy, as ``rl-pg play``).

        Returns:
            What the environment's ``step`` takes: an ``int`` or an array (a batch:
            one per observation).

        Raises:
            ValueError: the observation does not fit the agent's environment (the
                message names the expected entries and shapes).
        """
        if not isinstance(sample, (bool, np.bool_)):
            raise TypeError(f"sample must be True or False, got {sample!r}.")
        exploration = ExplorationType.RANDOM if sample else ExplorationType.DETERMINISTIC
        device = next(self.policy.parameters()).device
        with set_exploration_type(exploration), torch.no_grad():
            if isinstance(observation, TensorDictBase):
                return self.policy(observation)
            data = self._observe(observation).to(device)
            if isinstance(self._env, TransformedEnv):  # e.g. Pong's frame difference
                transform = self._env.transform
                if self._previous is None or self._previous.batch_size != data.batch_size:
                    data = transform._reset(data.empty(), data)
                else:
                    data = transform._step(self._previous, data)
            data = self.policy(data)
            self._previous = data
            if isinstance(self._env, TransformedEnv):  # e.g. a driving agent's choice
                data = self._env.transform.inv(data.clone(False))  # → its action vector
        action = data.get(self._env.action_key).cpu()
        if hasattr(self._base, "read_action"):  # gymnasium's form
            action = self._base.read_action(action)
        else:
            action = action.numpy()
        return action.item() if isinstance(action, np.ndarray) and action.ndim == 0 else action

    def _observe(self, observation: Any) -> TensorDictBase:
        """``observation`` as a TensorDict of the base environment's entries."""
        specs = self._base.observation_spec
        if (
            isinstance(observation, tuple)
            and len(observation) == 2
            and isinstance(observation[1], dict)
        ):
            raise ValueError(
                f"The {self.recipe.name} agent got an (observation, info) pair, what "
                f"env.reset() returns: give it the observation (obs, info = env.reset())."
            )
        if isinstance(observation, dict):
            values = dict(observation)
        elif len(self._reads) == 1:
            values = {self._reads[0]: observation}
        else:
            raise ValueError(
                f"The {self.recipe.name} agent reads a dict of observations: "
                f"{_expected(specs, self._reads)}; got {_describe(observation)}."
            )
        batch = None
        for key in self._reads:
            spec = specs[key]
            if key not in values:
                raise ValueError(
                    f"The {self.recipe.name} agent's observation has no {key!r} entry: "
                    f"{_expected(specs, self._reads)}."
                )
            try:
                value = torch.as_tensor(np.asarray(values[key]))
            except (TypeError, ValueError) as err:
                raise ValueError(
                    f"The {self.recipe.name} agent reads numbers under {key!r}, got "
                    f"{_describe(values[key])} ({str(err).split('. ')[0].rstrip('.')})."
                ) from err
            if value.is_floating_point() and not torch.isfinite(value).all():
                bad = int((~torch.isfinite(value)).sum())
                raise ValueError(
                    f"The {self.recipe.name} agent's observation under {key!r} holds {bad} "
                    f"NaN or infinite value(s): its action would be meaningless. Check "
                    f"what the environment returned."
                )
            shape = tuple(spec.shape)[
                self._base.batch_dims :
            ]  # one copy's (the env may be batched)
            if value.ndim < len(shape) or tuple(value.shape[value.ndim - len(shape) :]) != shape:
                raise ValueError(
                    f"The {self.recipe.name} agent expects observations of shape {shape} "
                    f"(or a batch of them, [N, {', '.join(map(str, shape))}]) under "
                    f"{key!r}, got {tuple(value.shape)}: give it what its environment "
                    f"returns."
                )
            here = tuple(value.shape[: value.ndim - len(shape)])
            if batch is not None and here != batch:
                raise ValueError(
                    f"The {self.recipe.name} agent's observation entries disagree on the "
                    f"batch: {batch} and {here} (under {key!r})."
                )
            values[key], batch = value.to(spec.dtype), here
        return TensorDict({key: values[key] for key in self._reads}, batch_size=batch)


def _expected(specs, keys) -> str:
    entries = ", ".join(f"{key!r} of shape {tuple(specs[key].shape)}" for key in keys)
    return f"it expects {entries}"


def _describe(observation: Any) -> str:
    if isinstance(observation, dict):
        return f"a dict of {sorted(observation)}"
    shape = getattr(observation, "shape", None)
    return f"{type(observation).__name__}" + ("" if shape is None else f" of shape {tuple(shape)}")
