"""Pong pre-processing: binarised 80x80 frames, fed as differences of frames."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite
from torchrl.envs.transforms import Transform

from rl_pg._checks import check_bool, check_key

__all__ = ["FrameDifference"]


class FrameDifference(Transform):
    """Turns Atari Pong frames into the difference of two binarised 80x80 frames.

    Each ``[210, 160, 3]`` frame is cropped to rows 35-195, every second row and column
    of its first colour channel is kept (80 x 80), the background values 144 and 109
    become 0 and everything else 1. The observation is the current processed frame
    minus the previous one (all zeros right after a reset), flattened to 6 400 values,
    so a single frame shows where things move. The previous frame travels with the
    data (``prev_key``), which keeps the transform stateless and batch-safe.

    Keyword Args:
        in_key (str): the pixels entry. Defaults to ``"pixels"`` (``GymEnv``'s name
            for image observations; batched gymnasium envs call them ``"observation"``).
        out_key (str): the difference entry; may be ``in_key``, replacing the frames.
            Defaults to ``"observation"``.
        prev_key (str): where the previous processed frame is kept. Defaults to
            ``"previous_frame"``.
        keep_pixels (bool): keep the raw frames (for rendering). Defaults to ``False``.

    Examples:
        >>> import torch
        >>> from rl_pg.frame_difference import FrameDifference
        >>> frame = torch.full((210, 160, 3), 144, dtype=torch.uint8)
        >>> frame[101, 40] = 236  # one ball pixel, on a kept row and column
        >>> processed = FrameDifference.process(frame)
        >>> processed.shape, processed.sum().item(), processed[33, 20].item()
        (torch.Size([80, 80]), 1.0, 1.0)
    """

    BACKGROUND = (144, 109)

    def __init__(
        self,
        *,
        in_key: str = "pixels",
        out_key: str = "observation",
        prev_key: str = "previous_frame",
        keep_pixels: bool = False,
    ) -> None:
        in_key, out_key = check_key("in_key", in_key), check_key("out_key", out_key)
        prev_key = check_key("prev_key", prev_key)
        keep_pixels = check_bool("keep_pixels", keep_pixels)
        super().__init__(in_keys=[in_key], out_keys=[out_key, prev_key])
        self.in_key, self.out_key, self.prev_key = in_key, out_key, prev_key
        # Raw frames are dropped unless asked for, or overwritten when in_key == out_key.
        self.drop_pixels = not keep_pixels and in_key != out_key
        if keep_pixels and in_key == out_key:
            raise ValueError("keep_pixels=True needs an out_key other than in_key.")

    @classmethod
    def process(cls, pixels: torch.Tensor) -> torch.Tensor:
        """``[*B, 210, 160, 3]`` uint8 frames to ``[*B, 80, 80]`` float 0/1 frames."""
        if pixels.shape[-3:] != (210, 160, 3):
            raise ValueError(
                f"FrameDifference expects Atari frames of shape [*B, 210, 160, 3], got "
                f"{tuple(pixels.shape)}."
            )
        frame = pixels[..., 35:195:2, ::2, 0]
        background = (frame == cls.BACKGROUND[0]) | (frame == cls.BACKGROUND[1])
        return (~background & (frame != 0)).float()

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        frame = self.process(tensordict_reset.get(self.in_key))
        tensordict_reset.set(self.out_key, torch.zeros_like(frame).flatten(-2))
        tensordict_reset.set(self.prev_key, frame)
        if self.drop_pixels:
            tensordict_reset.exclude(self.in_key, inplace=True)
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase):
        frame = self.process(next_tensordict.get(self.in_key))
        previous = tensordict.get(self.prev_key)
        next_tensordict.set(self.out_key, (frame - previous).flatten(-2))
        next_tensordict.set(self.prev_key, frame)
        if self.drop_pixels:
            next_tensordict.exclude(self.in_key, inplace=True)
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        pixels = observation_spec[self.in_key]
        batch = pixels.shape[:-3]
        device = pixels.device
        observation_spec[self.out_key] = Bounded(-1.0, 1.0, (*batch, 6400), device=device)
        observation_spec[self.prev_key] = Bounded(0.0, 1.0, (*batch, 80, 80), device=device)
        if self.drop_pixels:
            del observation_spec[self.in_key]
        return observation_spec
