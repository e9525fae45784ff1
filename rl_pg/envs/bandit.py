"""A one-step, many-armed bandit as a batched TorchRL environment."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rl_pg._checks import check_batch_size, check_bool, check_int

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
        render (bool): also give an image under ``"pixels"`` (``uint8``): one bar per
            arm, as high as it pays; after a pull, the pulled arm coloured (green for
            the best, orange for 0.9, red for nothing), for recordings. Defaults to
            ``False``.

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
        render: bool = False,
    ) -> None:
        num_arms = check_int("num_arms", num_arms, low=2)
        render = check_bool("render", render)
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
        self.render = render
        if render:
            for name, tensor in _arms_image(rewards.cpu()).items():
                self.register_buffer(name, tensor.to(self.device))
            self.observation_spec["pixels"] = Bounded(
                0, 255, (*batch_size, *self.image.shape), dtype=torch.uint8,
                device=self.device,
            )  # fmt: skip
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
                **({"pixels": self._pixels(None)} if self.render else {}),
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
                **({"pixels": self._pixels(action)} if self.render else {}),
            },
            batch_size=shape,
            device=self.device,
        )

    def _pixels(self, action: torch.Tensor | None) -> torch.Tensor:
        image = self.image.expand(*self.batch_size, *self.image.shape)
        if action is None:
            return image.clone()
        pulled = self.column_arm == action.unsqueeze(-1)  # [*B, W]
        shows = (pulled.unsqueeze(-2) & self.pull_shows).unsqueeze(-1)  # [*B, H, W, 1]
        return torch.where(shows, self.arm_colour[action][..., None, None, :], image)

    def _set_seed(self, seed: int | None) -> None:
        """The bandit is deterministic: seeding has nothing to do."""


_HEIGHT, _BAR, _MARGIN, _TOP = 160, 4, 8, 120  # bars 4 pixels wide; _TOP: a bar paying 1
_GREY, _BACKGROUND = (170, 170, 170), (246, 246, 240)
_COLOURS = ((200, 70, 60), (230, 150, 40), (70, 170, 90))  # pays nothing, less, the best


def _arms_image(rewards: torch.Tensor) -> dict[str, torch.Tensor]:
    """The bandit drawn: a bar per arm, as high as it pays; what a pull colours."""
    arms = len(rewards)
    width = arms * _BAR + 2 * _MARGIN
    columns = torch.arange(width) - _MARGIN
    arm = torch.where((columns >= 0) & (columns < arms * _BAR), columns // _BAR, -1)
    arm = torch.where(columns % _BAR == _BAR - 1, -1, arm)  # a gap between bars
    height = torch.where(arm >= 0, 2 + (_TOP * rewards[arm.clamp(min=0)]).long(), 0)
    rows = _HEIGHT - _MARGIN - torch.arange(_HEIGHT)[:, None]  # up from the base line
    bar = (rows >= 0) & (rows < height)
    mark = (rows >= _TOP + 10) & (rows < _TOP + 24) & (arm >= 0)  # above the pulled arm
    image = torch.tensor(_BACKGROUND, dtype=torch.uint8).expand(_HEIGHT, width, 3).clone()
    image[bar] = torch.tensor(_GREY, dtype=torch.uint8)
    kind = torch.where(rewards >= rewards.max(), 2, torch.where(rewards > 0, 1, 0))
    return {
        "image": image,
        "column_arm": arm,
        "pull_shows": bar | mark,
        "arm_colour": torch.tensor(_COLOURS, dtype=torch.uint8)[kind],
    }
