"""Turn a bounded continuous action space into discrete choices."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import torch
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Categorical, Composite, MultiCategorical, MultiOneHot, OneHot
from torchrl.envs.transforms import Transform

from rl_pg._checks import check_bool, check_choice, check_int, check_key, check_tensor

__all__ = ["DiscretizeAction"]

_MODES = ("joint", "per_dim")


class DiscretizeAction(Transform):
    """A TorchRL transform that lets a discrete policy drive a ``Box`` action space.

    The policy picks **one** index among ``N`` action vectors (``mode="joint"``), or one
    value per action dimension (``mode="per_dim"``, a multi-categorical action); the
    transform hands the matching continuous vector to the environment. The action
    spec seen by the policy becomes `torchrl.data.Categorical` (or
    `torchrl.data.OneHot` with ``one_hot=True``; ``MultiCategorical`` /
    ``MultiOneHot`` per dimension).

    The action vectors are either

    * a joint grid, ``counts=(n_1, ..., n_d)``: dimension ``k`` takes ``n_k`` evenly
      spaced values from its low to its high bound inclusive (the midpoint when
      ``n_k = 1``); index ``i`` is the row-major (first dimension slowest) position in
      the grid, so ``counts=(3, 3)`` on ``[-1, 1]^2`` gives the 9 actions
      ``(x, y)`` with ``index = 3 * i_x + i_y``; or
    * an explicit table, ``actions=[[...], ...]`` of shape ``[N, d]``, each row inside
      the bounds.

    Keyword Args:
        counts (int or sequence of int, optional): values per dimension (an int applies
            to every dimension). Exactly one of ``counts`` and ``actions``.
        actions (tensor or nested sequence, optional): the ``[N, d]`` table of actions.
        mode (str): ``"joint"`` (one choice among all rows) or ``"per_dim"`` (one value per
            dimension; needs ``counts``). Defaults to ``"joint"``.
        one_hot (bool): one-hot instead of index actions. Defaults to ``False``.
        action_key (NestedKey): the action entry. Defaults to ``"action"``.

    Raises:
        ValueError: for counts < 1, both or neither of ``counts`` / ``actions``, an
            unknown ``mode``, ``per_dim`` with a table, a table holding NaN or inf; once
            the environment's spec is known, for infinite bounds, a table of the wrong
            width or outside the bounds, or ``counts`` of the wrong length; and when
            mapping, for out-of-range or fractional indices, rows that are not exactly
            one-hot, and non-finite continuous actions.
        TypeError: for a non-integer count, a non-boolean ``one_hot``, a malformed
            ``action_key``, or when the action spec is not a bounded continuous spec.

    Examples:
        >>> import torch
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from rl_pg import DiscretizeAction
        >>> env = TransformedEnv(GymEnv("Pendulum-v1"), DiscretizeAction(counts=5))
        >>> env.action_spec.n
        5
        >>> env.transform.table.squeeze(-1)
        tensor([-2., -1.,  0.,  1.,  2.])
        >>> env.transform.to_index(torch.tensor([[0.9], [-1.6]]))
        tensor([3, 0])
        >>> env.rollout(3)["action"].shape
        torch.Size([3])
    """

    def __init__(
        self,
        *,
        counts: int | Sequence[int] | None = None,
        actions: torch.Tensor | Sequence[Sequence[float]] | None = None,
        mode: str = "joint",
        one_hot: bool = False,
        action_key: NestedKey = "action",
    ) -> None:
        if (counts is None) == (actions is None):
            raise ValueError(
                "Pass exactly one of counts= (a grid) or actions= (a table of action vectors)."
            )
        check_choice("mode", mode, _MODES)
        if mode == "per_dim" and actions is not None:
            raise ValueError(
                "mode='per_dim' discretises each dimension: it needs counts=, not actions=."
            )
        if counts is not None:
            scalar = isinstance(counts, str) or getattr(counts, "ndim", 1) == 0
            counts_list = list(counts) if hasattr(counts, "__iter__") and not scalar else [counts]
            if not counts_list:
                raise ValueError("counts must hold at least one integer >= 1, got an empty list.")
            counts = [check_int(f"counts[{i}]", c, low=1) for i, c in enumerate(counts_list)]
        if actions is not None:
            try:
                actions = torch.as_tensor(actions, dtype=torch.float32)
            except (TypeError, ValueError, RuntimeError) as err:
                raise TypeError(
                    f"actions must be an [N, action_dim] table of numbers, got {actions!r}."
                ) from err
            if actions.ndim != 2 or actions.shape[0] == 0 or actions.shape[1] == 0:
                raise ValueError(
                    f"actions must be a non-empty [N, action_dim] table, got shape "
                    f"{tuple(actions.shape)}."
                )
            if not bool(torch.isfinite(actions).all()):
                row = int((~torch.isfinite(actions)).any(1).nonzero()[0])
                raise ValueError(
                    f"actions row {row} {actions[row].tolist()} is not finite: every action "
                    f"vector must be a real point of the action space."
                )
        one_hot = check_bool("one_hot", one_hot)
        action_key = check_key("action_key", action_key)
        super().__init__(in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.action_key = action_key
        self.counts = counts
        self.mode = mode
        self.one_hot = one_hot
        self._given_actions = actions
        # Known once the environment's spec is: buffers, so that .to(device) moves them.
        self.register_buffer("table", None, persistent=False)
        self.register_buffer("low", None, persistent=False)
        self.register_buffer("high", None, persistent=False)
        self.values: list[torch.Tensor] | None = None

    # -------------------------------------------------------------- the spec ---
    def transform_action_spec(self, action_spec: Composite) -> Composite:
        spec = action_spec[self.action_key]
        self._build(spec)
        batch_shape = spec.shape[:-1]
        n_dims = spec.shape[-1]
        device = spec.device
        if self.mode == "joint":
            n = self.table.shape[0]
            new = (
                OneHot(n, shape=(*batch_shape, n), device=device)
                if self.one_hot
                else Categorical(n, shape=batch_shape, device=device)
            )
        else:
            nvec = torch.as_tensor(self._counts_for(n_dims))
            new = (
                MultiOneHot(nvec, shape=(*batch_shape, int(nvec.sum())), device=device)
                if self.one_hot
                else MultiCategorical(
                    nvec, shape=(*batch_shape, n_dims), device=device, remove_singleton=False
                )
            )
        action_spec = action_spec.clone()
        action_spec[self.action_key] = new
        return action_spec

    def _build(self, spec) -> None:
        """Builds the action table from the environment's (inner) action spec."""
        if not isinstance(spec, Bounded) or not spec.dtype.is_floating_point:
            raise TypeError(
                f"DiscretizeAction needs a bounded continuous action spec at "
                f"{self.action_key!r}, got {type(spec).__name__} of dtype {spec.dtype}."
            )
        if spec.shape == torch.Size([]):
            raise TypeError(
                f"DiscretizeAction needs a vector action (shape [..., d]), got a scalar spec "
                f"at {self.action_key!r}."
            )
        low = spec.space.low.reshape(-1, spec.shape[-1])[0].float()
        high = spec.space.high.reshape(-1, spec.shape[-1])[0].float()
        if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
            raise ValueError(
                f"DiscretizeAction needs finite bounds, got low={low.tolist()} "
                f"high={high.tolist()}; clip the action space first."
            )
        n_dims = low.numel()
        if self._given_actions is not None:
            table = self._given_actions
            if table.shape[1] != n_dims:
                raise ValueError(
                    f"actions has {table.shape[1]} columns but the action space has {n_dims} "
                    f"dimensions; give one column per dimension."
                )
            outside = (table < low) | (table > high)
            if outside.any():
                row = int(outside.any(1).nonzero()[0])
                raise ValueError(
                    f"actions row {row} {table[row].tolist()} lies outside the bounds "
                    f"low={low.tolist()} high={high.tolist()}."
                )
            self.values = None
        else:
            self.values = [
                torch.linspace(lo, hi, n) if n > 1 else torch.tensor([(lo + hi) / 2])
                for lo, hi, n in zip(
                    low.tolist(), high.tolist(), self._counts_for(n_dims), strict=True
                )
            ]
            table = torch.tensor(list(itertools.product(*(v.tolist() for v in self.values))))
        self.table = table.to(spec.device)
        self.low, self.high = low.to(spec.device), high.to(spec.device)
        self.n_dims = n_dims

    def _counts_for(self, n_dims: int) -> list[int]:
        if len(self.counts) == 1:
            return self.counts * n_dims
        if len(self.counts) != n_dims:
            raise ValueError(
                f"counts has {len(self.counts)} entries but the action space has {n_dims} "
                f"dimensions; give one count per dimension or a single int."
            )
        return self.counts

    def _ensure_built(self) -> None:
        if self.table is None:
            if self.parent is None:
                raise RuntimeError(
                    "DiscretizeAction learns its bounds from the environment: append it to an "
                    "env (TransformedEnv(env, DiscretizeAction(...))) before mapping actions."
                )
            # The parent is the environment before this transform: its spec is the box.
            self._build(self.parent.full_action_spec[self.action_key])

    # ------------------------------------------------------------- mappings ---
    def _inv_apply_transform(self, action: torch.Tensor) -> torch.Tensor:
        return self.to_continuous(action)

    def to_continuous(self, action: torch.Tensor) -> torch.Tensor:
        """Maps discrete actions (indices or one-hot, per ``mode``) to action vectors.

        Args:
            action (torch.Tensor): ``[*B]`` indices (``[*B, N]`` one-hot) in joint mode;
                ``[*B, d]`` indices (``[*B, sum(counts)]`` one-hot) per dimension.

        Returns:
            The ``[*B, d]`` continuous actions.

        Examples:
            >>> import torch
            >>> from torchrl.envs import GymEnv, TransformedEnv
            >>> from rl_pg import DiscretizeAction
            >>> pendulum = TransformedEnv(GymEnv("Pendulum-v1"), DiscretizeAction(counts=3))
            >>> pendulum.transform.to_continuous(torch.tensor([0, 2]))
            tensor([[-2.],
                    [ 2.]])
        """
        self._ensure_built()
        check_tensor("action", action, hint="Pass the policy's discrete action tensor.")
        if self.mode == "joint":
            n = self.table.shape[0]
            index = _one_hot_index(action, n) if self.one_hot else _as_index(action)
            self._check_range(index, n)
            return self.table[index]
        sizes = [v.numel() for v in self.values]
        if self.one_hot:
            if action.ndim == 0 or action.shape[-1] != sum(sizes):
                raise ValueError(
                    f"Per-dimension one-hot actions have {sum(sizes)} columns ({sizes} per "
                    f"dimension), got shape {tuple(action.shape)}."
                )
            chunks = action.split(sizes, dim=-1)
            index = torch.stack(
                [_one_hot_index(c, n) for c, n in zip(chunks, sizes, strict=True)], -1
            )
        else:
            index = _as_index(action)
            if index.ndim == 0 or index.shape[-1] != len(sizes):
                raise ValueError(
                    f"Per-dimension actions hold one index per dimension ([*B, {len(sizes)}]), "
                    f"got shape {tuple(action.shape)}."
                )
        columns = []
        for k, values in enumerate(self.values):
            self._check_range(index[..., k], values.numel())
            columns.append(values.to(self.table.device)[index[..., k]])
        return torch.stack(columns, -1)

    def to_index(self, action: torch.Tensor) -> torch.Tensor:
        """Maps continuous actions to the nearest discrete action (indices, per ``mode``).

        Distances are measured with each dimension scaled by its range, so that
        dimensions with different bounds weigh the same. Ties go to the lower index.

        Args:
            action (torch.Tensor): ``[*B, d]`` continuous actions.

        Returns:
            ``[*B]`` indices in joint mode, ``[*B, d]`` per dimension.
        """
        self._ensure_built()
        check_tensor("action", action, hint="Pass continuous actions as a tensor.")
        if action.shape[-1:] != torch.Size([self.n_dims]):
            raise ValueError(
                f"to_index expects actions of shape [*B, {self.n_dims}], got {tuple(action.shape)}."
            )
        if action.is_complex() or not bool(torch.isfinite(action).all()):
            raise ValueError(
                "to_index got non-finite actions: NaN or inf has no nearest discrete action."
            )
        scale = (self.high - self.low).clamp_min(1e-12)
        if self.mode == "joint":
            distance = (((action.unsqueeze(-2) - self.table) / scale) ** 2).sum(-1)
            return distance.argmin(-1)
        return torch.stack(
            [
                (action[..., k : k + 1] - values.to(action.device)).abs().argmin(-1)
                for k, values in enumerate(self.values)
            ],
            -1,
        )

    @staticmethod
    def _check_range(index: torch.Tensor, n: int) -> None:
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= n):
            raise ValueError(
                f"Discrete action index out of range: got values in "
                f"[{int(index.min())}, {int(index.max())}], expected [0, {n - 1}]."
            )

    def __repr__(self) -> str:
        source = f"counts={self.counts}" if self.counts is not None else "actions=<table>"
        return (
            f"{type(self).__name__}({source}, mode={self.mode!r}, one_hot={self.one_hot}, "
            f"action_key={self.action_key!r})"
        )


def _as_index(action: torch.Tensor) -> torch.Tensor:
    """Integer indices; floats only when they are whole numbers (never truncated)."""
    if action.dtype == torch.bool or action.is_complex():
        raise TypeError(f"Discrete actions must be integer indices, got dtype {action.dtype}.")
    if action.is_floating_point():
        whole = torch.isfinite(action) & (action == action.round())
        if not bool(whole.all()):
            raise ValueError(
                f"Discrete actions must be whole numbers, got {action[~whole][0].item()!r}: an "
                f"index is never rounded. Pass the policy's integer action."
            )
    return action.long()


def _one_hot_index(one_hot: torch.Tensor, n: int) -> torch.Tensor:
    """The index of each one-hot row; rows that are not exactly one-hot are refused."""
    if one_hot.ndim == 0 or one_hot.shape[-1] != n:
        raise ValueError(f"One-hot actions have {n} columns, got shape {tuple(one_hot.shape)}.")
    # One-hot specs sample booleans, which comparisons and argmax treat as 0/1.
    values = one_hot.to(torch.float64) if one_hot.dtype == torch.bool else one_hot
    valid = ((values == 0) | (values == 1)).all(-1) & (values.sum(-1) == 1)
    if not bool(valid.all()):
        row = values[~valid][0]
        raise ValueError(
            f"One-hot actions must hold a single 1 and zeros elsewhere, got the row {row.tolist()}."
        )
    return values.argmax(-1)
