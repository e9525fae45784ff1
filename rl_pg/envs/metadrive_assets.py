"""Headless MetaDrive without its asset download: the engine's pull of 3-D models,
textures and fonts is skipped while an environment that renders nothing starts, and
only then (see [`rl_pg.envs.metadrive`][rl_pg.envs.metadrive])."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import gymnasium as gym

__all__ = ["assets_pull_skipped"]


@contextlib.contextmanager
def assets_pull_skipped(env: gym.Env) -> Iterator[None]:
    """Skips MetaDrive's asset download while ``env`` starts its engine, if it may.

    Only when the assets are absent and the environment renders nothing in 3-D
    (MetaDrive's own render-mode decision); otherwise MetaDrive behaves as it does.
    """
    from metadrive.constants import RENDER_MODE_NONE
    from metadrive.engine.asset_loader import AssetLoader
    from metadrive.engine.base_engine import BaseEngine

    headless = env.config["_render_mode"] == RENDER_MODE_NONE
    if BaseEngine.singleton is not None or not headless or os.path.exists(AssetLoader.asset_path):
        yield
        return
    pull = BaseEngine.__dict__["try_pull_asset"]
    BaseEngine.try_pull_asset = staticmethod(_no_asset_pull)
    try:
        yield
    finally:
        BaseEngine.try_pull_asset = pull


def _no_asset_pull() -> None:
    """Headless MetaDrive reads no asset: nothing to download."""
