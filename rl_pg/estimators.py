"""Monte-Carlo return estimators as TorchRL value estimators.

[`RewardToGo`][rl_pg.RewardToGo] and [`DiscountedReturn`][rl_pg.DiscountedReturn] plug
in wherever TorchRL expects a `torchrl.objectives.value.ValueEstimatorBase`
(``loss.make_value_estimator``, a standalone call on collector output, ...). Both are
registered with TorchRL under the names ``"reward_to_go"`` and ``"discounted_return"``.
"""

from __future__ import annotations

from contextlib import nullcontext

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, dispatch
from torchrl.objectives.utils import hold_out_net, register_value_estimator
from torchrl.objectives.value import ValueEstimatorBase

from rl_pg._checks import check_bool, check_int, check_real
from rl_pg.functional import discounted_return, reward_to_go
from rl_pg.lean import plain_layers, run_plain

__all__ = ["DiscountedReturn", "MonteCarloReturn", "RewardToGo"]

REUSE_MIN_WORK = 1 << 21
"""Steps times value-network parameters from which the estimator looks for next
observations it can take from the following step instead of running the network on
them: below it, the check costs about what the pass it saves does."""


class MonteCarloReturn(ValueEstimatorBase):
    """What [`RewardToGo`][rl_pg.estimators.RewardToGo] and
    [`DiscountedReturn`][rl_pg.estimators.DiscountedReturn] share: only the return
    function differs. A loss recognises its estimators as its subclasses."""

    _returns = staticmethod(reward_to_go)

    def __init__(
        self,
        *,
        gamma: float | torch.Tensor,
        value_network: TensorDictModule | None = None,
        time_dim: int | None = None,
        differentiable: bool = False,
        device: torch.device | None = None,
        deactivate_vmap: bool = False,
    ) -> None:
        if value_network is not None and not isinstance(value_network, TensorDictModuleBase):
            raise TypeError(
                f"value_network must be a TensorDictModule writing the state value (e.g. "
                f"torchrl.modules.ValueOperator), got {type(value_network).__name__}."
            )
        if isinstance(gamma, torch.Tensor) and gamma.numel() != 1:
            raise ValueError(
                f"gamma must be a number or a one-element tensor, got shape "
                f"{tuple(gamma.shape)}. For per-step discounts call rl_pg.functional."
            )
        gamma = check_real("gamma", gamma, low=0, high=1)
        time_dim = check_int("time_dim", time_dim, optional=True)
        super().__init__(
            value_network=value_network,
            differentiable=check_bool("differentiable", differentiable),
            device=device,
            deactivate_vmap=check_bool("deactivate_vmap", deactivate_vmap),
        )
        # float64 so that .item() gives back the number the user wrote.
        self.register_buffer("gamma", torch.tensor(gamma, dtype=torch.float64, device=self._device))
        self.time_dim = time_dim
        self._network_size: int | None = None  # the value network's parameters, counted once

    @property
    def in_keys(self):
        keys = [("next", self.tensor_keys.reward), ("next", self.tensor_keys.done)]
        keys.append(("next", self.tensor_keys.terminated))
        if self.value_network is not None:
            network_keys = list(self.value_network.in_keys)
            keys += network_keys + [("next", key) for key in network_keys]
        return keys

    @dispatch
    def forward(
        self,
        tensordict: TensorDictBase,
        *,
        params: TensorDictBase | None = None,
        target_params: TensorDictBase | None = None,
    ) -> TensorDictBase:
        """Writes the return (``value_target``) and the ``advantage`` into ``tensordict``.

        Args:
            tensordict (TensorDictBase): collector output ``[*B, T]`` (time last unless
                ``time_dim`` says otherwise) or a flat ``[N]`` batch of episodes laid back
                to back, with ``("next", "reward")``, ``("next", "done")`` and, optionally,
                ``("next", "terminated")``; plus the value network's inputs at the root
                and under ``"next"`` when there is a value network.

        Keyword Args:
            params (TensorDictBase, optional): parameters for a functional value network.
                Defaults to ``None``.
            target_params (TensorDictBase, optional): parameters used for the bootstrap
                values. Defaults to ``params``.

        Returns:
            ``tensordict``, updated in place.
        """
        self.estimate(tensordict, params=params, target_params=target_params)
        return tensordict

    def estimate(
        self,
        tensordict: TensorDictBase,
        *,
        params: TensorDictBase | None = None,
        target_params: TensorDictBase | None = None,
        value_graph: bool = False,
    ) -> torch.Tensor | None:
        """``forward``'s work. With ``value_graph=True`` and a value network called in
        one plain pass, returns ``V(s_t)`` still attached to the network's parameters
        (the entries written are detached all the same), so that a loss can regress it
        without calling the network again; otherwise returns None."""
        if tensordict.batch_dims < 1:
            raise ValueError(
                f"{type(self).__name__} needs a tensordict with a time dimension, got "
                f"batch_size={tuple(tensordict.batch_size)}. Give the data a batch size such "
                f"as [T] or [B, T]."
            )
        value = next_value = graph = None
        if self.value_network is not None:
            if params is not None:
                params = params.detach()
                if target_params is None:
                    target_params = params.clone(False)
            held = params is None and target_params is None
            if held and self._plain_calls(tensordict):
                value, next_value, graph = self._values(tensordict, value_graph)
            else:
                with hold_out_net(self.value_network) if held else nullcontext():
                    value, next_value, _ = self._call_value_nets(
                        data=tensordict,
                        params=params,
                        next_params=target_params,
                        single_call=False,
                        value_key=self.tensor_keys.value,
                        detach_next=True,
                        vmap_randomness=self.vmap_randomness,
                    )
        if value is not None:
            self._check_value_shape(value, tensordict)
        with torch.set_grad_enabled(self.differentiable and torch.is_grad_enabled()):
            value_target = self.value_estimate(tensordict, next_value=next_value)
            advantage = value_target if value is None else value_target - value
        tensordict.set(self.tensor_keys.value_target, value_target)
        tensordict.set(self.tensor_keys.advantage, advantage)
        return graph

    def _plain_calls(self, tensordict: TensorDictBase) -> bool:
        """Whether one call of the value network on the root and ``"next"`` entries
        together gives what TorchRL's vmapped pair of calls would (a network without
        recurrent state, inputs that are plain tensors, no chunking)."""
        if self.value_chunk_size is not None or self.num_chunks is not None:
            return False
        keys = list(self.value_network.in_keys)
        if "is_init" in keys:
            return False
        return all(
            isinstance(tensordict.get(key, None), torch.Tensor)
            and isinstance(tensordict.get(("next", key), None), torch.Tensor)
            for key in keys
        )

    def _values(self, tensordict: TensorDictBase, graph: bool = False):
        """``V(s_t)``, ``V(s_{t+1})`` (both detached) and, with ``graph``, ``V(s_t)``
        attached to the network's parameters.

        Without ``graph``, one call of the value network on both sets of inputs laid end
        to end: cheaper than TorchRL's ``vmap`` over the pair for the small networks and
        batches of on-policy training. With it, ``V(s_t)`` is computed with gradients
        and ``V(s_{t+1})`` without, so that the backward pass covers only the steps a
        value loss regresses. Either way, in a large enough segment collected in time
        order, ``V(s_{t+1})`` is read from the following step's ``V(s_t)`` wherever the
        episode goes on (see ``_next_steps_to_evaluate``).
        """
        keys = list(self.value_network.in_keys)
        data = self._sanitize_next_obs_nan(tensordict, keys)  # as TorchRL's calls do
        value_key = self.tensor_keys.value
        layers = plain_layers(self.value_network)

        def values_at(entries: dict, shape) -> torch.Tensor:
            if layers is not None:  # the networks on the tensors: no TensorDict around them
                return run_plain(layers, entries)[value_key]
            return self.value_network(TensorDict(entries, batch_size=shape)).get(value_key)

        def inputs(*prefix):
            return {key: data.get((*prefix, key)) for key in keys}

        need = None if self.differentiable else self._next_steps_to_evaluate(tensordict, data)
        if graph or need is not None:
            with nullcontext() if graph else torch.no_grad():
                attached = values_at(inputs(), tensordict.shape)
            value = attached.detach()
            with torch.no_grad():
                if need is not None and value.shape[: tensordict.ndim] == tensordict.shape:
                    # Where an episode goes on within the segment, V(s_{t+1}) is the
                    # following step's V(s_t): the network runs on the other next
                    # observations only (each row's last step, the episodes' ends).
                    rows = need.reshape(-1).nonzero().squeeze(1)
                    ends = {
                        key: data.get(("next", key)).flatten(0, tensordict.ndim - 1)[rows]
                        for key in keys
                    }
                    next_value = value.roll(-1, tensordict.ndim - 1)
                    flat = next_value.view(-1, *value.shape[tensordict.ndim :])
                    flat[rows] = values_at(ends, rows.shape)
                else:
                    next_value = values_at(inputs("next"), tensordict.shape)
            attached = attached if graph else None
        else:
            n = tensordict.shape[0]
            both = {key: torch.cat([data.get(key), data.get(("next", key))]) for key in keys}
            # Out of the graph as TorchRL holds it: gradients may reach the inputs (a
            # differentiable estimator), never the network's parameters.
            held = hold_out_net(self.value_network) if self.differentiable else torch.no_grad()
            with held:
                values = values_at(both, [2 * n, *tensordict.shape[1:]])
            attached, value, next_value = None, values[:n], values[n:].detach()
        tensordict.set(value_key, value)
        tensordict.set(("next", value_key), next_value)
        return value, next_value, attached

    def _next_steps_to_evaluate(self, tensordict: TensorDictBase, data: TensorDictBase):
        """The steps whose next observation the value network must see, as a mask of
        the batch's shape, or None to run it on all of them.

        A segment collected in time order (time the last batch dimension) shows each
        next observation again as the following step's observation, unless an episode
        ended in between; that is checked, entry by entry, before anything is reused.
        """
        steps = tensordict.shape[-1] if tensordict.batch_dims else 0
        if steps < 2 or self._get_time_dim(None, tensordict) != tensordict.ndim - 1:
            return None
        if self._network_size is None:
            self._network_size = sum(p.numel() for p in self.value_network.parameters())
        if tensordict.numel() * self._network_size < REUSE_MIN_WORK:
            return None
        done = tensordict.get(("next", self.tensor_keys.done), None)
        if not isinstance(done, torch.Tensor) or done.numel() != tensordict.numel():
            return None
        done = done.reshape(tensordict.shape)
        ends = (done if done.dtype == torch.bool else done != 0)[..., :-1]
        time_dim = tensordict.ndim - 1
        for key in self.value_network.in_keys:
            root, next_ = data.get(key), data.get(("next", key))
            if root.shape != next_.shape or root.shape[: tensordict.ndim] != tensordict.shape:
                return None
            same = next_.narrow(time_dim, 0, steps - 1) == root.narrow(time_dim, 1, steps - 1)
            if not bool((same.reshape(*ends.shape, -1).all(-1) | ends).all()):
                return None
        return torch.cat([ends, torch.ones_like(ends[..., :1])], -1)

    def value_estimate(
        self,
        tensordict: TensorDictBase,
        target_params: TensorDictBase | None = None,
        next_value: torch.Tensor | None = None,
        time_dim: int | None = None,
        **kwargs,
    ) -> torch.Tensor:
        """The return of every step, bootstrapped from ``next_value`` where episodes are cut."""
        reward = self._read(tensordict, ("next", self.tensor_keys.reward))
        done = self._read(tensordict, ("next", self.tensor_keys.done))
        terminated = tensordict.get(("next", self.tensor_keys.terminated), None)
        time_dim = self._get_time_dim(time_dim, tensordict)
        if done.shape != reward.shape:
            done = self._expand(done, reward, "done")
        if terminated is not None and terminated.shape != reward.shape:
            terminated = self._expand(terminated, reward, "terminated")
        return type(self)._returns(
            reward,
            done,
            self.gamma.item(),
            time_dim=time_dim,
            terminated=terminated,
            next_value=next_value,
        )

    def _check_value_shape(self, value: torch.Tensor, tensordict: TensorDictBase) -> None:
        reward = self._read(tensordict, ("next", self.tensor_keys.reward))
        if value.shape != reward.shape:
            raise ValueError(
                f"The value network writes {self.tensor_keys.value!r} of shape "
                f"{tuple(value.shape)}, but the rewards are {tuple(reward.shape)}: it must "
                f"write one value per step, shaped like the reward (e.g. a final layer "
                f"with out_features=1, without squeezing it)."
            )

    @staticmethod
    def _read(tensordict: TensorDictBase, key) -> torch.Tensor:
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"The input tensordict has no entry {key!r}. Collect it with the environment "
                f"or rename the estimator's keys with set_keys(...)."
            )
        return value

    @staticmethod
    def _expand(mask: torch.Tensor, reward: torch.Tensor, name: str) -> torch.Tensor:
        try:
            return mask.expand_as(reward)
        except RuntimeError as err:
            raise ValueError(
                f"{name} of shape {tuple(mask.shape)} does not match reward of shape "
                f"{tuple(reward.shape)}."
            ) from err


@register_value_estimator("reward_to_go", default_kwargs={"gamma": 0.99})
class RewardToGo(MonteCarloReturn):
    """Reward-to-go `G_t = Σ_{k≥t} γ^(k−t) r_k` as a TorchRL value estimator.

    Writes ``value_target`` (`G_t`) and ``advantage`` (`G_t − V(s_t)` with a
    value network, `G_t` without). Episodes that are truncated or cut by the batch
    bootstrap from the value network when there is one (see
    [`reward_to_go`][rl_pg.functional.reward_to_go]).

    Keyword Args:
        gamma (float): discount in ``[0, 1]``.
        value_network (TensorDictModule, optional): state-value network, used as baseline
            and for bootstrapping. Defaults to ``None``.
        time_dim (int, optional): the tensordict's time dimension. Defaults to ``None``:
            the dimension named ``"time"``, else the last one.
        differentiable (bool, optional): keep the graph through the value network.
            Defaults to ``False``.
        device (torch.device, optional): device of the ``gamma`` buffer. Defaults to
            ``torch.get_default_device()``.
        deactivate_vmap (bool, optional): call the value network without ``vmap``.
            Defaults to ``False``.

    Raises:
        TypeError: for a ``gamma`` that is not a real number, a ``time_dim`` that is not
            an integer, or a ``value_network`` that is not a TensorDict module.
        ValueError: for ``gamma`` outside ``[0, 1]``, data without a time dimension, and
            the bad inputs listed in [`reward_to_go`][rl_pg.functional.reward_to_go].
        KeyError: when a key it reads is missing (the message names it).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rl_pg import RewardToGo
        >>> data = TensorDict(
        ...     {"next": {"reward": torch.ones(1, 4, 1),
        ...               "done": torch.tensor([[0, 1, 0, 1]], dtype=torch.bool).unsqueeze(-1)}},
        ...     batch_size=[1, 4],
        ... )
        >>> RewardToGo(gamma=0.5)(data)["value_target"].squeeze(-1)
        tensor([[1.5000, 1.0000, 1.5000, 1.0000]])
    """


@register_value_estimator("discounted_return", default_kwargs={"gamma": 0.99})
class DiscountedReturn(MonteCarloReturn):
    """Whole-episode return `R(τ) = Σ_k γ^k r_k` at every step.

    The "no causality" estimator: every step of an episode gets the same target. With a
    value network the ``advantage`` is `R(τ) − V(s_t)`. Takes the keyword
    arguments of [`RewardToGo`][rl_pg.RewardToGo].

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rl_pg import DiscountedReturn
        >>> data = TensorDict(
        ...     {"next": {"reward": torch.tensor([1.0, 2.0, 3.0, 4.0]).unsqueeze(-1),
        ...               "done": torch.tensor([0, 1, 0, 1], dtype=torch.bool).unsqueeze(-1)}},
        ...     batch_size=[4],
        ... )
        >>> DiscountedReturn(gamma=0.5)(data)["advantage"].squeeze(-1)
        tensor([2., 2., 5., 5.])
    """

    _returns = staticmethod(discounted_return)
