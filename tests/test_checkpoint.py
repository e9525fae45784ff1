"""Atomic checkpoints and their errors."""

from __future__ import annotations

import pytest
import torch

from rl_pg.checkpoint import CheckpointError, load_checkpoint, save_checkpoint


class TestCheckpoint:
    def test_round_trip(self, tmp_path):
        path = save_checkpoint({"weights": torch.arange(3.0)}, tmp_path / "c.pt")
        assert torch.equal(load_checkpoint(path)["weights"], torch.arange(3.0))

    def test_no_temporary_file_is_left(self, tmp_path):
        save_checkpoint({"a": 1}, tmp_path / "c.pt")
        save_checkpoint({"a": 2}, tmp_path / "c.pt")
        assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]

    def test_failed_write_keeps_the_previous_checkpoint(self, tmp_path):
        path = save_checkpoint({"a": 1}, tmp_path / "c.pt")
        with pytest.raises(AttributeError, match="Can't pickle local object"):
            save_checkpoint({"a": lambda: None}, path)
        assert load_checkpoint(path)["a"] == 1
        assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]

    def test_corrupted(self, tmp_path):
        path = save_checkpoint({"a": 1}, tmp_path / "c.pt")
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        with pytest.raises(CheckpointError, match="is corrupted and cannot be read"):
            load_checkpoint(path)
        assert path.read_bytes() == data[: len(data) // 2]  # left as it was

    def test_missing(self, tmp_path):
        with pytest.raises(CheckpointError, match="No checkpoint at"):
            load_checkpoint(tmp_path / "none.pt")

    def test_not_an_rl_pg_checkpoint(self, tmp_path):
        torch.save({"weights": 1}, tmp_path / "other.pt")
        with pytest.raises(CheckpointError, match="not an rl_pg checkpoint"):
            load_checkpoint(tmp_path / "other.pt")

    def test_other_format(self, tmp_path):
        torch.save({"format": 99}, tmp_path / "future.pt")
        with pytest.raises(CheckpointError, match="has checkpoint format 99"):
            load_checkpoint(tmp_path / "future.pt")
