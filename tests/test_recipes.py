"""The recipes' main() on a tiny budget."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))

import cartpole  # noqa: E402


class TestCartPole:
    def test_main_trains_and_evaluates(self, tmp_path):
        cfg = cartpole.Config(
            total_frames=3_000, eval_interval=1_000, eval_episodes=2, run_dir=tmp_path
        )
        result = cartpole.main(cfg)
        assert 3_000 <= result["frames"] < 3_500
        assert result["eval_mean_return"] > 0
        assert result["solved_at_frames"] is None  # far too few frames to balance 500 steps
