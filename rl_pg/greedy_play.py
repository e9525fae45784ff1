"""The greedy episode of each group, for the greedy-rollout baseline: a policy that
plays the last environment of every group greedily and the others as the policy does."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rl_pg._checks import check_int, check_key

__all__ = ["GreedyInGroups"]


class GreedyInGroups(TensorDictModuleBase):
    """A policy that plays the greedy episode of every group: it acts as ``policy``
    does in the first ``group_size`` environments of each group of ``group_size + 1``,
    and greedily (``ExplorationType.DETERMINISTIC``: the most probable action of a
    categorical policy, the mean of a Gaussian) in the last.

    The layout of [`EpisodeCollector`][rl_pg.episode_collector.EpisodeCollector]
    ``(..., group_size=K, greedy=True)``: give this policy to the collector of
    segments it wraps. The greedy environments' actions are the policy's greedy ones
    whatever the exploration type it is called under; the others' are left as the
    policy wrote them.

    Args:
        policy (TensorDictModuleBase): the policy (e.g. a ``ProbabilisticActor``).

    Keyword Args:
        group_size (int): sampled episodes per group, ``K >= 1``.
        action_key (NestedKey): where the policy writes its action. Defaults to
            ``"action"``.

    Raises:
        ValueError: in ``forward``, for a batch of environments whose number is not a
            multiple of ``group_size + 1``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> from rl_pg.groups import GreedyInGroups
        >>> actor = ProbabilisticActor(
        ...     TensorDictModule(torch.nn.Linear(1, 3), ["observation"], ["logits"]),
        ...     in_keys=["logits"], distribution_class=torch.distributions.Categorical,
        ... )
        >>> with torch.no_grad():
        ...     _ = actor.module[0].module.bias.copy_(torch.tensor([0.0, 2.0, 0.0]))
        ...     _ = actor.module[0].module.weight.zero_()
        >>> policy = GreedyInGroups(actor, group_size=2)
        >>> root = TensorDict({"observation": torch.ones(6, 1)}, batch_size=[6])
        >>> policy(root)["action"][[2, 5]]  # the greedy environments: the argmax
        tensor([1, 1])
    """

    def __init__(
        self, policy: TensorDictModuleBase, *, group_size: int, action_key="action"
    ) -> None:
        super().__init__()
        if not isinstance(policy, TensorDictModuleBase):
            raise TypeError(
                f"policy must be a TensorDictModule (e.g. a ProbabilisticActor), got "
                f"{type(policy).__name__}."
            )
        self.policy = policy
        self.group_size = check_int("group_size", group_size, low=1)
        self.action_key = check_key("action_key", action_key)
        self.in_keys = list(policy.in_keys)
        self.out_keys = list(policy.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.policy(tensordict)
        n = tensordict.batch_size[0] if tensordict.batch_dims else 1
        width = self.group_size + 1
        if tensordict.batch_dims == 0 or n % width:
            raise ValueError(
                f"GreedyInGroups acts greedily in the last of every {width} environments "
                f"(group_size={self.group_size}, plus the greedy one), but the batch has "
                f"batch size {tuple(tensordict.batch_size)}: build a multiple of {width} "
                f"environments."
            )
        action = out.get(self.action_key).clone()
        rows = torch.arange(self.group_size, n, width, device=action.device)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            greedy = self.policy(tensordict[rows].clone())
        action[rows] = greedy.get(self.action_key).to(action.device)
        out.set(self.action_key, action)
        return out
