"""A one-step, many-armed bandit as a batched TorchRL environment."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rl_pg._checks import check_batch_size, check_int

__all__ = ["BanditEnv"]


class BanditEnv(EnvBase):
    """A one-step bandit: one constant state ``[1.0]``, ``num_arms`` actions.

    Arm 0 pays 1.0, arms ``1 .. num_arms/2 - 1`` pay 0.9, the others 0.0; every step
    ends the episode. The trap it shows: many arms pay almost the best, so
    a policy without a baseline often settles on a 0.9 arm.

    Keyword Args:
        num_arms (int): number of actions, at least 2. Defaults to ``100``.
        batch_size (int or tuple of int): independent copies stepped together.
            Defaults to ``()``.
        device (torch.device, optional): where tensors live. Defaults to ``"cpu"``.

    Examples:
        >>> import torch
        >>> from rl_pg.envs import BanditEnv
        >>> env = BanditEnv(num_arms=4, batch_size=3)
        >>> td = env.reset()
        >>> td["action"] = torch.tensor([0, 1, 3])
        >>> env.step(td)["next", "reward"].squeeze(-1)
        tensor([1.0000, 0.9000, 0.0000])
    """

    batch_locked = True

    def __init__(
        self,
        *,
        num_arms: int = 100,
        batch_size: int | tuple[int, ...] = (),
        device: torch.device | str | None = "cpu",
    ) -> None:
        num_arms = check_int("num_arms", num_arms, low=2)
        batch_size = torch.Size(check_batch_size(batch_size))
        super().__init__(batch_size=batch_size, device=device)
        self.num_arms = num_arms
        rewards = torch.zeros(num_arms, device=self.device)
        rewards[0] = 1.0
        rewards[1 : num_arms // 2] = 0.9
        self.register_buffer("arm_rewards", rewards)
        self.observation_spec = Composite(
            observation=Unbounded((*batch_size, 1), device=self.device), shape=batch_size
        )
        self.action_spec = Categorical(num_arms, shape=batch_size, device=self.device)
        self.reward_spec = Unbounded((*batch_size, 1), device=self.device)
        self.done_spec = Composite(
            {
                key: Categorical(2, (*batch_size, 1), dtype=torch.bool, device=self.device)
                for key in ("done", "terminated", "truncated")
            },
            shape=batch_size,
        )

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        shape = self.batch_size
        return TensorDict(
            {
                "observation": torch.ones(*shape, 1, device=self.device),
                **self.full_done_spec.zero(),
            },
            batch_size=shape,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict["action"]
        shape = self.batch_size
        done = torch.ones(*shape, 1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {
                "observation": torch.ones(*shape, 1, device=self.device),
                "reward": self.arm_rewards[action].unsqueeze(-1),
                "done": done,
                "terminated": done.clone(),
                "truncated": torch.zeros_like(done),
            },
            batch_size=shape,
            device=self.device,
        )

    def _set_seed(self, seed: int | None) -> None:
        """The bandit is deterministic: seeding has nothing to do."""
