"""rl_pg.training.callbacks: hooks of the loop, their state across a resume, and the
gradient-noise measurement (--grad-stats)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from conftest import run_weights
from test_loop import _cfg as trainer_cfg
from test_loop import _train

from rl_pg.envs import GridWorldEnv
from rl_pg.training import Callback, TrainConfig, read_run, scalar_log_rows
from rl_pg.training.callbacks import (
    Callbacks,
    GradientNoise,
    KeepCheckpoints,
    StopWhenSolved,
    from_config,
)


def _cfg(tmp_path, name="run", **overrides) -> TrainConfig:
    return trainer_cfg(tmp_path, **{"run_dir": tmp_path / name, **overrides})


class Recorder(Callback):
    """Records the hooks called and counts updates; its count is its saved state."""

    def __init__(self, key=None):
        self.key = key
        self.calls: list[str] = []
        self.updates = 0
        self.loaded: dict | None = None

    def on_start(self, run):
        self.calls.append("start")

    def on_batch(self, run, batch):
        self.calls.append("batch")
        self.updates_before = run.state.updates

    def on_update(self, run, batch, metrics):
        assert run.state.updates == self.updates_before + 1
        assert "loss/actor" in metrics
        self.updates += 1
        self.calls.append("update")

    def on_evaluation(self, run, result):
        assert "eval/mean_return" in result
        self.calls.append("evaluation")

    def on_end(self, run):
        self.calls.append("end")

    def state_dict(self):
        return {"updates": self.updates}

    def load_state_dict(self, state):
        self.loaded = dict(state)
        self.updates = state["updates"]


class TestCallbacks:
    def test_hooks_are_called_in_order(self, tmp_path):
        recorder = Recorder()
        _train(_cfg(tmp_path, total_updates=2), callbacks=[recorder])
        hooks = [call for call in recorder.calls if call != "evaluation"]
        assert hooks == ["start", "batch", "update", "batch", "update", "end"]
        # Evaluations follow an update (the last one at the end of the run).
        assert recorder.calls[-2:] == ["evaluation", "end"]
        for i, call in enumerate(recorder.calls):
            if call == "evaluation":
                assert recorder.calls[i - 1] == "update"

    def test_state_survives_a_resume(self, tmp_path):
        cfg = _cfg(tmp_path, total_updates=3)
        _train(cfg, callbacks=[Recorder()])
        resumed = Recorder()
        summary = _train(replace(cfg, resume=True, total_updates=5), callbacks=[resumed])
        assert resumed.loaded == {"updates": 3}
        assert resumed.updates == 5 == summary["updates"]

    def test_stop_training_ends_the_run_with_its_checkpoint(self, tmp_path):
        class StopAtFour(Callback):
            def stop_training(self, run):
                return run.state.updates >= 4

        summary = _train(_cfg(tmp_path, total_updates=50), callbacks=[StopAtFour()])
        assert summary["updates"] == 4
        assert (tmp_path / "run" / "checkpoint.pt").exists()

    def test_on_end_runs_when_training_fails(self, tmp_path):
        recorder = Recorder()

        class Boom(Callback):
            def on_update(self, run, batch, metrics):
                raise RuntimeError("boom")

        with pytest.raises(RuntimeError, match="boom"):
            _train(_cfg(tmp_path), callbacks=[recorder, Boom()])
        assert recorder.calls[-1] == "end"

    def test_rejects_what_is_not_a_callback(self):
        with pytest.raises(TypeError, match="subclass Callback"):
            Callbacks([object()])

    def test_rejects_two_callbacks_with_one_key(self):
        with pytest.raises(ValueError, match=r"key\(s\) \['Recorder'\]"):
            Callbacks([Recorder(), Recorder()])
        Callbacks([Recorder(), Recorder(key="second")])  # distinct keys are fine


class TestBuiltIn:
    """The loop's optional behaviours are callbacks: passed in, they act as their flags."""

    def test_from_config(self, tmp_path):
        cfg = _cfg(tmp_path, keep_every=2, threshold=0.5, stop_when_solved=True)
        kinds = [type(c) for c in from_config(cfg)]
        assert kinds == [StopWhenSolved, KeepCheckpoints]
        assert from_config(replace(cfg, stop_when_solved=False, keep_every=None)) == []

    def test_keep_checkpoints_as_the_flag_does(self, tmp_path):
        _train(_cfg(tmp_path, "flag", total_updates=5, keep_every=2))
        _train(_cfg(tmp_path, "own", total_updates=5), callbacks=[KeepCheckpoints(2)])
        for name in ("update_2.pt", "update_4.pt"):
            flag, own = (read_run(tmp_path / r / "checkpoints" / name) for r in ("flag", "own"))
            assert flag["state"]["updates"] == own["state"]["updates"]
            for key, value in flag["loss"].items():
                assert torch.equal(value, own["loss"][key]), key
        assert sorted(p.name for p in (tmp_path / "own" / "checkpoints").iterdir()) == [
            "update_2.pt",
            "update_4.pt",
        ]
        with pytest.raises(ValueError, match="positive number of updates"):
            KeepCheckpoints(0)

    def test_stop_when_solved_stops_at_the_first_solved_evaluation(self, tmp_path):
        threshold = GridWorldEnv().optimal_return - 1e-6
        base = {"total_updates": 60, "eval_interval": 1, "threshold": threshold}
        flag = _train(_cfg(tmp_path, "flag", stop_when_solved=True, **base))
        own = _train(
            _cfg(tmp_path, "callback", stop_when_solved=False, **base),
            callbacks=[StopWhenSolved(threshold)],
        )
        never = _train(_cfg(tmp_path, "never", stop_when_solved=False, **base))
        assert flag["updates"] == own["updates"]
        assert flag["updates"] < never["updates"] == 60
        assert flag["frames"] == flag["solved_at_frames"] == own["solved_at_frames"]
        with pytest.raises(ValueError, match="threshold must be a finite number"):
            StopWhenSolved(float("nan"))  # it would never stop
        with pytest.raises(ValueError, match="Several callbacks have the key"):
            _train(_cfg(tmp_path, "both", stop_when_solved=True, **base),
                   callbacks=[StopWhenSolved(threshold)])  # fmt: skip


class TestGradientNoise:
    def test_from_config(self, tmp_path):
        assert from_config(_cfg(tmp_path)) == []
        (callback,) = from_config(_cfg(tmp_path, grad_stats=3))
        assert isinstance(callback, GradientNoise) and callback.every == 3

    def test_logs_every_estimator_and_changes_nothing(self, tmp_path):
        # Measured and unmeasured runs end with identical weights: no random number is
        # drawn and no state is touched by the measurement.
        plain = _cfg(tmp_path, "plain")
        measured = replace(plain, run_dir=tmp_path / "measured", grad_stats=2)
        _train(plain)
        _train(measured)
        for key, value in run_weights(tmp_path / "plain").items():
            assert torch.equal(value, run_weights(tmp_path / "measured")[key]), key
        scalars = tmp_path / "measured" / "logs" / "csv" / "scalars"
        for estimator in ("loss", "episode_return", "reward_to_go", "gae"):
            rows = scalar_log_rows((scalars / "grad" / estimator / "noise_scale.csv").read_text())
            assert len(rows) == 3  # updates 2, 4 and 6
        cost = scalar_log_rows((scalars / "time" / "grad_stats_s.csv").read_text())
        assert all(seconds > 0 for _, seconds in cost)
        assert not (tmp_path / "plain" / "logs" / "csv" / "scalars" / "grad").exists()

    def test_grad_stats_may_change_on_resume(self, tmp_path):
        cfg = _cfg(tmp_path, total_updates=2)
        _train(cfg)
        _train(replace(cfg, resume=True, total_updates=4, grad_stats=1))
        scalars = tmp_path / "run" / "logs" / "csv" / "scalars" / "grad" / "reward_to_go"
        assert len(scalar_log_rows((scalars / "snr.csv").read_text())) == 2

    def test_rejects_a_bad_interval(self):
        with pytest.raises(ValueError, match="positive number of updates"):
            GradientNoise(0)
