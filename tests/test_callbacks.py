"""rl_pg.training.callbacks: hooks of the loop, their state across a resume, and the
gradient-noise measurement (--grad-stats)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from conftest import assert_same_run, averaged_weights, run_weights
from test_loop import _cfg as trainer_cfg
from test_loop import _train

from rl_pg.checkpoint import load_checkpoint, save_checkpoint
from rl_pg.envs import GridWorldEnv
from rl_pg.training import Callback, TrainConfig, read_run, scalar_log_rows
from rl_pg.training.callbacks import Callbacks, GradientNoise, KeepCheckpoints, StopWhenSolved
from rl_pg.training.checkpoints import POLICY_AVERAGE
from rl_pg.training.curves import read_curve
from rl_pg.training.loop import from_config
from rl_pg.training.selection import Confirmation, PolicyAverage


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
        average, confirmation = from_config(
            _cfg(tmp_path, policy_ema=0.9, confirm_episodes=5, threshold=0.5,
                 stop_when_solved=False)
        )  # fmt: skip
        assert isinstance(average, PolicyAverage) and average.decay == 0.9
        assert isinstance(confirmation, Confirmation)
        assert (confirmation.episodes, confirmation.threshold) == (5, 0.5)

    def test_policy_average_and_confirmation_as_their_flags_do(self, tmp_path):
        base = {"total_updates": 12, "eval_interval": 100}
        flag = _train(_cfg(tmp_path, "flag", policy_ema=0.8, confirm_episodes=4, **base))
        own = _train(_cfg(tmp_path, "own", **base), callbacks=[PolicyAverage(0.8), Confirmation(4)])
        plain = _train(_cfg(tmp_path, "plain", **base))
        assert read_curve(tmp_path / "own", "confirm/score")[1].size >= 1
        for key in ("best_confirmed", "best_at_frames", "best_eval_mean_return"):
            assert flag[key] == own[key], key
        assert plain["best_confirmed"] is None is not own["best_confirmed"]
        for checkpoint in ("checkpoint.pt", "best.pt"):
            flag_saved, own_saved = (
                load_checkpoint(tmp_path / r / checkpoint) for r in ("flag", "own")
            )
            for key, value in averaged_weights(flag_saved).items():
                assert torch.equal(value, averaged_weights(own_saved)[key]), key
        with pytest.raises(ValueError, match="decay"):
            PolicyAverage(1.0)
        with pytest.raises(ValueError, match=r"episodes must be an integer >= 1"):
            Confirmation(0)

    def test_a_callback_of_your_own_decides_what_best_pt_keeps(self, tmp_path):
        class KeepLatest(Callback):
            def keeps_best(self, run, result):
                return True

        summary = _train(
            _cfg(tmp_path, total_updates=12, eval_interval=100), callbacks=[KeepLatest()]
        )
        frames, _ = read_curve(tmp_path / "run", "eval/mean_return")
        best = read_run(tmp_path / "run", which="best")
        assert best["state"]["frames"] == frames[-1] == summary["frames"]
        for key, value in best["loss"].items():
            assert torch.equal(value, read_run(tmp_path / "run")["loss"][key]), key

    def test_a_checkpoint_keeping_its_average_at_the_top_level_resumes_and_plays(self, tmp_path):
        # Runs checkpointed before the average was a callback kept it at the top level.
        straight = _train(_cfg(tmp_path, "straight", total_updates=6, policy_ema=0.8))
        _train(_cfg(tmp_path, "old", total_updates=3, policy_ema=0.8))
        path = tmp_path / "old" / "checkpoint.pt"
        saved = load_checkpoint(path)
        saved[POLICY_AVERAGE] = saved["callbacks"].pop(POLICY_AVERAGE)["weights"]
        save_checkpoint(saved, path)
        played = read_run(tmp_path / "old")
        assert averaged_weights(played) is not None  # read where the old layout kept it
        resumed = _train(_cfg(tmp_path, "old", total_updates=6, policy_ema=0.8, resume=True))
        assert_same_run(resumed, tmp_path / "old", tmp_path / "straight")
        for key, value in run_weights(tmp_path / "straight").items():
            assert torch.equal(value, run_weights(tmp_path / "old")[key]), key
        assert straight["updates"] == 6

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
        with pytest.raises(ValueError, match=r"every must be an integer >= 1"):
            KeepCheckpoints(0)

    def test_stop_when_solved_stops_at_the_first_solved_evaluation(self, tmp_path):
        # Reaching the threshold solves: the optimal return itself, exactly.
        threshold = GridWorldEnv().optimal_return
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

    def test_with_confirmation_solved_means_a_checkpoint_held_both_ways(self, tmp_path):
        # The gridworld's shortest path returns 0.5: greedy play finds it long before
        # sampled play does, so the first greedy pass is not yet done.
        base = {"total_updates": 400, "eval_interval": 1, "threshold": 0.3, "lr": 0.05}
        greedy = _train(_cfg(tmp_path, "greedy", stop_when_solved=True, **base))
        held = _train(_cfg(tmp_path, "held", stop_when_solved=True, confirm_episodes=20, **base))
        assert greedy["updates"] < 400 and held["updates"] < 400
        assert held["best_confirmed"] >= 0.3  # the lower of greedy and sampled
        assert held["updates"] > greedy["updates"]  # later than the first greedy pass
        assert held["solved_at_frames"] == greedy["solved_at_frames"]  # same run until then
        (callback,) = from_config(_cfg(tmp_path, confirm_episodes=5, threshold=0.3))[1:]
        assert isinstance(callback, StopWhenSolved) and callback.confirmed


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

    @pytest.mark.parametrize("baseline", ["leave_one_out", "greedy"])
    def test_a_grouped_run_is_measured_by_group_with_the_group_estimators(self, tmp_path, baseline):
        size = 4 - (baseline == "greedy")  # 8 environments: two groups
        cfg = _cfg(tmp_path, baseline=baseline, group_size=size, grad_stats=1)
        _train(replace(cfg, total_updates=2))
        scalars = tmp_path / "run" / "logs" / "csv" / "scalars" / "grad"
        measured = {p.name for p in scalars.iterdir()}
        groups = 2
        expected = {"loss", "reward_to_go", "leave_one_out", "group_mean", "group_mean_scaled"}
        assert expected | ({"greedy"} if baseline == "greedy" else set()) <= measured
        assert ("greedy" in measured) == (baseline == "greedy")
        for name in measured:
            units = scalar_log_rows((scalars / name / "units.csv").read_text())
            assert [u for _, u in units] == [groups, groups], name

    def test_grad_stats_may_change_on_resume(self, tmp_path):
        cfg = _cfg(tmp_path, total_updates=2)
        _train(cfg)
        _train(replace(cfg, resume=True, total_updates=4, grad_stats=1))
        scalars = tmp_path / "run" / "logs" / "csv" / "scalars" / "grad" / "reward_to_go"
        assert len(scalar_log_rows((scalars / "snr.csv").read_text())) == 2

    def test_rejects_a_bad_interval(self):
        with pytest.raises(ValueError, match=r"every must be an integer >= 1"):
            GradientNoise(0)
