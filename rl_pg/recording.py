"""Play episodes one after the other and record them as a GIF or an MP4."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rl_pg._checks import check_real
from rl_pg.evaluation import check_playing

__all__ = ["check_recording", "play"]


def play(
    policy: TensorDictModuleBase,
    env: EnvBase,
    *,
    episodes: int,
    deterministic: bool = True,
    max_steps: int = 100_000,
    record: str | Path | None = None,
    fps: int = 30,
) -> list[float]:
    """Plays ``episodes`` episodes one after the other; optionally records them. An
    environment that steps several copies at once plays one episode in each copy per
    round, each with its own return.

    Keyword Args:
        episodes (int): number of episodes.
        deterministic (bool): act greedily rather than by sampling. Defaults to ``True``.
        max_steps (int): cap on an episode's length. Defaults to ``100_000``.
        record (str or Path, optional): a ``.gif`` or ``.mp4`` path; the environment must
            put its frames under ``"pixels"`` (e.g. ``GymEnv(..., from_pixels=True,
            pixels_only=False)``). Defaults to ``None``.
        fps (int): frames per second of the recording. Defaults to ``30``.

    Returns:
        The return of every episode.

    Raises:
        ValueError: for ``episodes < 1``, ``fps <= 0``, or a recording that cannot be
            made (of an environment that steps several copies at once, an extension
            other than ``.gif`` / ``.mp4``, a folder that cannot be created, an
            environment that gives no ``"pixels"``), checked before any episode is
            played.
        ModuleNotFoundError: an ``.mp4`` recording without ``imageio-ffmpeg``
            (``pip install "rl_pg[video]"``).

    Examples:
        >>> import torch
        >>> from rl_pg.envs import GridWorldEnv
        >>> from rl_pg.recording import play
        >>> from rl_pg.models import mlp_actor
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> env = GridWorldEnv(max_steps=5)
        >>> len(play(mlp_actor(env), env, episodes=2, deterministic=False))
        2
    """
    episodes, max_steps, deterministic = check_playing(episodes, max_steps, deterministic)
    copies = env.batch_size.numel()
    if copies > 1 and record is not None:
        raise ValueError(
            f"A recording shows one environment; this one steps {copies} copies together "
            f"(batch size {tuple(env.batch_size)}): build it with a single copy to record."
        )
    if record is not None:
        # Everything that could make the recording fail is checked before playing.
        fps = check_real("fps", fps, low=0, low_open=True)
        record = check_recording(record)
        if "pixels" not in env.observation_spec.keys():
            raise ValueError(
                "Recording needs frames under 'pixels': build the environment with "
                "from_pixels=True, pixels_only=False (this one does not render)."
            )
    returns, frames = [], []
    exploration = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    with set_exploration_type(exploration), torch.no_grad():
        while len(returns) < episodes:
            if copies > 1:  # each copy plays one episode: its own return, not the sum
                rollout = env.rollout(max_steps, policy, break_when_all_done=True)
                returns += _first_episode_returns(rollout)
                continue
            rollout = env.rollout(max_steps, policy, break_when_any_done=True)
            returns.append(rollout["next", "reward"].sum().item())
            if record is not None:  # every step's frame, and where the episode ended
                frames.extend(rollout["pixels"].numpy())
                frames.append(rollout["next", "pixels"][-1].numpy())
    returns = returns[:episodes]
    if record is not None:
        _write_video(record, frames, fps)
    return returns


def _first_episode_returns(rollout) -> list[float]:
    """The return of each copy's first episode in a batched rollout (``[*B, T]``): its
    rewards up to and including its first ``done``, whatever follows it."""
    done = rollout["next", "done"].reshape(-1, rollout.shape[-1]).int()
    reward = rollout["next", "reward"].reshape(-1, rollout.shape[-1])
    first = (done.cumsum(-1) - done) == 0  # no done before this step
    return (reward * first).sum(-1).tolist()


_VIDEO_FORMATS = (".gif", ".mp4")


def check_recording(path: str | Path) -> Path:
    """Checks that a recording can be written to ``path``; creates its folder.

    Raises:
        ValueError: an extension other than ``.gif`` and ``.mp4``, or a folder that
            cannot be created.
        ModuleNotFoundError: ``.mp4`` without ``imageio-ffmpeg`` installed.

    Examples:
        >>> from rl_pg.recording import check_recording
        >>> check_recording("episodes.avi")
        Traceback (most recent call last):
        ...
        ValueError: Cannot record to episodes.avi: the file name must end in .gif or .mp4.
    """
    path = Path(path)
    if path.suffix.lower() not in _VIDEO_FORMATS:
        raise ValueError(
            f"Cannot record to {path}: the file name must end in {' or '.join(_VIDEO_FORMATS)}."
        )
    if path.suffix.lower() == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ModuleNotFoundError(
            f"Recording {path} needs an MP4 encoder: pip install -c constraints.txt "
            f'"rl_pg[video]" (imageio-ffmpeg, which ships ffmpeg), or record a .gif.'
        )
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"Cannot record to {path}: its folder cannot be created ({err}).") from err
    if path.is_dir():
        raise ValueError(f"Cannot record to {path}: it is a folder; give a file name.")
    return path


def _write_video(path: Path, frames: list, fps: float) -> None:
    if path.suffix.lower() == ".gif":
        _write_gif(path, frames, fps)
    else:
        import imageio.v2 as imageio

        imageio.mimsave(path, frames, fps=fps)


def _write_gif(path: Path, frames: list, fps: float) -> None:
    """One 256-colour palette for the whole recording, taken from frames spread over it.

    A palette per frame (what imageio does) costs ~18 ms a frame at 600x400; one shared
    palette makes recording cost about as much as rendering.
    """
    from PIL import Image

    images = [Image.fromarray(np.ascontiguousarray(frame)) for frame in frames]
    sample = images[:: max(1, len(images) // 16)][:16]
    montage = Image.new("RGB", (sample[0].width, sample[0].height * len(sample)))
    for i, image in enumerate(sample):
        montage.paste(image.convert("RGB"), (0, i * sample[0].height))
    palette = montage.quantize(colors=256)
    gif = [
        image.convert("RGB").quantize(palette=palette, dither=Image.Dither.NONE) for image in images
    ]
    gif[0].save(path, save_all=True, append_images=gif[1:], duration=1000 / fps, loop=0)
