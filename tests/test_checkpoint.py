"""Atomic checkpoints and their errors."""

from __future__ import annotations

import hashlib
import io
import os
import stat

import numpy as np
import pytest
import torch

from rl_pg.checkpoint import (
    CheckpointError,
    clean_temporary_files,
    load_checkpoint,
    save_checkpoint,
    write_atomically,
)


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

    def test_truncated(self, tmp_path):
        path = save_checkpoint({"a": 1}, tmp_path / "c.pt")
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        with pytest.raises(CheckpointError, match="is corrupted: its contents do not match"):
            load_checkpoint(path)
        assert path.read_bytes() == data[: len(data) // 2]  # left as it was

    @pytest.mark.parametrize("where", ["start of the weights", "middle", "last byte"])
    def test_sixteen_overwritten_bytes_in_the_payload(self, tmp_path, where):
        # The weights deserialise fine when overwritten: only the checksum notices.
        path = save_checkpoint({"weights": torch.arange(1000.0)}, tmp_path / "c.pt")
        data = bytearray(path.read_bytes())
        weights_at = data.find(torch.arange(1000.0).numpy().tobytes()[:64])
        offset = {"start of the weights": weights_at, "middle": len(data) // 2}.get(
            where, len(data) - 16
        )
        data[offset : offset + 16] = bytes(16)
        path.write_bytes(bytes(data))
        with pytest.raises(CheckpointError, match="do not match the checksum"):
            load_checkpoint(path)

    def test_damaged_header(self, tmp_path):
        path = save_checkpoint({"a": 1}, tmp_path / "c.pt")
        data = bytearray(path.read_bytes())
        data[12:20] = bytes(8)  # inside the stored digest
        path.write_bytes(bytes(data))
        with pytest.raises(CheckpointError, match="do not match the checksum"):
            load_checkpoint(path)

    def test_file_shorter_than_its_header(self, tmp_path):
        from rl_pg.checkpoint import _HEADER

        path = save_checkpoint({"a": 1}, tmp_path / "c.pt")
        data = path.read_bytes()
        path.write_bytes(data[:20])
        with pytest.raises(CheckpointError, match="shorter than its header"):
            load_checkpoint(path)
        path.write_bytes(data[:_HEADER])  # the header whole, no payload: not shorter
        with pytest.raises(CheckpointError, match="do not match the checksum"):
            load_checkpoint(path)

    def test_a_write_makes_the_folders_it_goes_in(self, tmp_path):
        path = write_atomically(tmp_path / "new" / "deeper" / "c.json", "{}")
        assert path.read_text() == "{}"

    def test_a_weights_only_refusal_is_said_by_its_reason_in_one_line(self):
        from rl_pg.checkpoint import _first_line

        torch_message = (
            "Weights only load failed. This file can still be loaded, to do so you have "
            "two options.\n\nWeightsUnpickler error: Unsupported operand 149\n\nCheck the "
            "documentation of torch.load to learn more."
        )
        assert _first_line(RuntimeError(torch_message)) == "Unsupported operand 149"
        assert _first_line(ValueError("one\nline")) == "one line"

    def test_checkpoint_of_another_format_version(self, tmp_path):
        path = save_checkpoint({"a": 1}, tmp_path / "c.pt")
        data = bytearray(path.read_bytes())
        data[8:12] = (7).to_bytes(4, "little")
        path.write_bytes(bytes(data))
        with pytest.raises(CheckpointError, match="has checkpoint format 7, this rl_pg reads"):
            load_checkpoint(path)

    def test_checkpoint_written_before_checksums_loads_with_a_warning(self, tmp_path):
        torch.save({"format": 1, "a": 1}, tmp_path / "old.pt")
        with pytest.warns(UserWarning, match="before checkpoints carried a checksum"):
            assert load_checkpoint(tmp_path / "old.pt")["a"] == 1

    def test_garbage(self, tmp_path):
        (tmp_path / "c.pt").write_bytes(b"not a checkpoint at all")
        with pytest.raises(CheckpointError, match="is corrupted: it cannot be read"):
            load_checkpoint(tmp_path / "c.pt")

    def test_state_that_is_not_a_dict(self, tmp_path):
        with pytest.raises(TypeError, match="saves a dict of state, got list"):
            save_checkpoint([1, 2], tmp_path / "c.pt")
        assert not (tmp_path / "c.pt").exists()

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


class _RunsCode:
    """Unpickling this runs ``touch <path>``: what a file made to attack its reader does."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (os.system, (f"touch {self.path}",))


class TestNoCodeRuns:
    """A shared agent or checkpoint is data: loading it never runs its author's code."""

    @pytest.mark.parametrize("checksummed", [True, False], ids=["format 2", "format 1"])
    def test_a_file_whose_unpickling_runs_code_is_refused(self, tmp_path, checksummed):
        marker, path = tmp_path / "ran", tmp_path / "agent.pt"
        buffer = io.BytesIO()
        torch.save({"format": 2 if checksummed else 1, "policy": _RunsCode(marker)}, buffer)
        payload = buffer.getvalue()
        if checksummed:  # a checksum proves the file whole, not who wrote it
            header = b"RLPGCKPT" + (2).to_bytes(4, "little") + hashlib.sha256(payload).digest()
            payload = header + payload
        path.write_bytes(payload)
        with pytest.raises(
            CheckpointError, match=r"agent.pt holds more than tensors .* refers to \S*system"
        ):
            load_checkpoint(path)
        assert not marker.exists()
        assert path.read_bytes() == payload  # left as it was

    def test_what_could_not_be_loaded_again_is_not_saved(self, tmp_path):
        with pytest.raises(TypeError, match=r"the state holds builtins\.object"):
            save_checkpoint({"a": np.array([object()])}, tmp_path / "c.pt")
        assert not (tmp_path / "c.pt").exists()

    def test_numpy_data_of_earlier_versions_still_loads(self, tmp_path):
        # Checkpoints before weights-only loading held np.random.get_state()'s array.
        state = {"format": 1, "rng": np.random.get_state(), "x": np.float64(2.5)}
        torch.save(state, tmp_path / "old.pt")
        with pytest.warns(UserWarning, match="before checkpoints carried a checksum"):
            loaded = load_checkpoint(tmp_path / "old.pt")
        assert np.array_equal(loaded["rng"][1], state["rng"][1]) and loaded["x"] == 2.5


class TestTemporaryFiles:
    def test_a_killed_write_leaves_only_a_temporary_file_that_is_cleaned(self, tmp_path):
        save_checkpoint({"a": 1}, tmp_path / "c.pt")
        (tmp_path / ".c.pt.abc123.rl_pg-tmp").write_bytes(b"half a checkpoint")
        (tmp_path / "logs").mkdir()
        (tmp_path / "logs" / ".x.csv.q1.rl_pg-tmp").write_text("1,2\n")
        removed = clean_temporary_files(tmp_path)
        assert sorted(p.name for p in removed) == [".c.pt.abc123.rl_pg-tmp", ".x.csv.q1.rl_pg-tmp"]
        assert sorted(p.name for p in tmp_path.rglob("*")) == ["c.pt", "logs"]

    def test_write_atomically_replaces_the_whole_file(self, tmp_path):
        path = write_atomically(tmp_path / "a.txt", "first, longer text")
        write_atomically(path, b"second")
        assert path.read_bytes() == b"second"
        assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]

    @pytest.mark.skipif(not hasattr(os, "O_DIRECTORY"), reason="POSIX folders")
    def test_the_bytes_then_the_rename_are_flushed_to_disk(self, tmp_path, monkeypatch):
        # What a power cut would show; here, that each is asked of the disk, in order.
        synced, fsync = [], os.fsync
        monkeypatch.setattr(os, "fsync", lambda fd: (
            synced.append(stat.S_ISDIR(os.fstat(fd).st_mode)), fsync(fd)
        ))  # fmt: skip
        write_atomically(tmp_path / "s.json", "{}")
        assert synced == [False, True]  # the file's bytes, then the folder's entry for it

    @pytest.mark.skipif(not hasattr(os, "fchmod"), reason="POSIX permissions")
    def test_an_atomic_write_gets_the_permissions_of_an_ordinary_one(self, tmp_path):
        (tmp_path / "plain.txt").write_text("x")  # what open() gives under this umask
        written = write_atomically(tmp_path / "written.txt", "x")
        assert written.stat().st_mode == (tmp_path / "plain.txt").stat().st_mode
        written.chmod(0o640)  # a replaced file keeps its own
        write_atomically(written, "y")
        assert stat.S_IMODE(written.stat().st_mode) == 0o640
