"""rl_pg.training.selection: the evaluations during training, the best checkpoint they
keep, confirmation replays and the policy average that is evaluated instead of the
trained weights."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_same_run, averaged_weights, run_weights
from test_loop import _cfg, _train, make_grid, make_grid_models
from torch import nn

from rl_pg.checkpoint import CheckpointError
from rl_pg.evaluation import evaluate
from rl_pg.models import mlp_actor
from rl_pg.training import load_models, read_run, train
from rl_pg.training.console import format_summary
from rl_pg.training.curves import read_curve
from rl_pg.training.seeds import confirmation_seed, evaluation_seed


class TestBestCheckpoint:
    def test_best_holds_the_best_evaluation_and_plays_it_back(self, tmp_path):
        summary = _train(_cfg(tmp_path, total_updates=12, eval_interval=200))
        frames, evaluations = read_curve(tmp_path / "run", "eval/mean_return")
        evaluations = evaluations.tolist()
        assert len(evaluations) >= 3
        best = read_run(tmp_path / "run", which="best")
        first_best = evaluations.index(max(evaluations))
        assert best["state"]["best_eval"]["eval/mean_return"] == max(evaluations)
        assert summary["best_eval_mean_return"] == max(evaluations)
        assert summary["best_at_frames"] == best["state"]["frames"]
        assert best["state"]["frames"] == frames[first_best]
        actor = mlp_actor(make_grid(), hidden=(32,), activation=nn.ReLU)
        load_models(best, actor)
        env = make_grid()
        env.set_seed(evaluation_seed(0))  # the evaluation's start states
        result = evaluate(actor, env, episodes=1)
        assert result["mean_return"] == pytest.approx(max(evaluations))

    def test_a_policy_average_is_what_is_evaluated_kept_and_deployed(self, tmp_path):
        decay = 0.8
        cfg = _cfg(tmp_path, total_updates=6, eval_interval=200, policy_ema=decay, keep_every=1)
        _train(cfg)
        kept = [read_run(tmp_path / "run" / "checkpoints" / f"update_{n}.pt") for n in range(1, 7)]
        # After every update: average <- decay * average + (1 - decay) * trained weights.
        for before, after in itertools.pairwise(kept):
            for key, value in averaged_weights(after).items():
                if not key.startswith("module.") or not value.is_floating_point():
                    continue
                trained = after["loss"]["actor_network." + key.removeprefix("module.")]
                expected = decay * averaged_weights(before)[key] + (1 - decay) * trained
                torch.testing.assert_close(value, expected)
        last = kept[-1]
        assert int(averaged_weights(last)["n_averaged"]) == 7  # the initial copy + 6 updates
        actor = mlp_actor(make_grid(), hidden=(32,), activation=nn.ReLU)
        load_models(last, actor)
        for key, value in actor.state_dict().items():
            assert torch.equal(value, averaged_weights(last)["module." + key]), key
        assert not all(
            torch.equal(value, last["loss"]["actor_network." + key])
            for key, value in actor.state_dict().items()
        )  # the average is not the trained weights
        load_models(last, actor, average=False)  # ... which are one argument away
        for key, value in actor.state_dict().items():
            assert torch.equal(value, last["loss"]["actor_network." + key]), key
        plain = {k: v for k, v in last.items() if k != "callbacks"}
        with pytest.raises(CheckpointError, match=r"keeps no average.*leave average=False"):
            load_models(plain, actor, average=False)
        # Evaluations played the average: best.pt's plays back its evaluation's return.
        best = read_run(tmp_path / "run", which="best")
        load_models(best, actor)
        env = make_grid()
        env.set_seed(evaluation_seed(0))
        result = evaluate(actor, env, episodes=1)
        kept = best["state"]["best_eval"]["eval/mean_return"]
        assert result["mean_return"] == pytest.approx(kept)

    def test_confirmation_keeps_the_checkpoint_whose_replays_score_best(self, tmp_path):
        cfg = _cfg(tmp_path, total_updates=30, eval_interval=200, confirm_episodes=6)
        summary = _train(cfg)
        run = tmp_path / "run"
        frames, scores = read_curve(run, "confirm/score")
        assert len(scores) >= 2  # without a threshold, every new high is replayed
        _, greedy = read_curve(run, "confirm/greedy_mean_return")
        _, sampled = read_curve(run, "confirm/sampled_mean_return")
        torch.testing.assert_close(scores, np.minimum(greedy, sampled))
        best = read_run(run, which="best")
        winner = int(np.argmax(scores))
        assert summary["best_confirmed"] == best["state"]["best_confirmed"] == scores[winner]
        assert summary["best_at_frames"] == best["state"]["frames"] == frames[winner]
        # best.pt replays its confirmation: the lower of its greedy and sampled means
        actor = mlp_actor(make_grid(), hidden=(32,), activation=nn.ReLU)
        load_models(best, actor)
        replays = []
        for greedy_mode in (True, False):
            torch.manual_seed(confirmation_seed(0))
            env = make_grid()
            env.set_seed(confirmation_seed(0))
            replays.append(evaluate(actor, env, episodes=6, deterministic=greedy_mode))
        assert min(r["mean_return"] for r in replays) == pytest.approx(scores[winner])
        # each mode is what it says: the greedy replay plays greedily, the other samples
        assert greedy[winner] == pytest.approx(replays[0]["mean_return"])
        assert sampled[winner] == pytest.approx(replays[1]["mean_return"])
        assert not np.allclose(greedy, sampled)  # or the line above would prove nothing

    def test_evaluations_and_confirmations_log_the_seconds_they_took(self, tmp_path):
        import time

        from rl_pg.training.checkpoints import RunState
        from rl_pg.training.seeds import run_streams
        from rl_pg.training.selection import confirm, evaluate_run

        cfg = _cfg(tmp_path, eval_episodes=3)
        actor, _ = make_grid_models(make_grid())
        state = RunState(streams=run_streams(cfg.seed))
        logged = {}
        logger = type("Kept", (), {"log_scalar": lambda self, k, v, step: logged.update({k: v})})()
        start = time.perf_counter()
        evaluate_run(cfg, cfg.torch_device(), actor, make_grid(), {}, state, logger)
        confirm(cfg.torch_device(), actor, make_grid(), state, logger, episodes=3)
        elapsed = time.perf_counter() - start
        assert logged["time/eval_s"] > 0 and logged["time/confirm_s"] > 0
        assert logged["time/eval_s"] + logged["time/confirm_s"] <= elapsed

    def test_confirmation_changes_the_checkpoint_kept_not_the_run(self, tmp_path):
        common = {"total_updates": 8, "eval_interval": 200}
        plain = _train(_cfg(tmp_path, run_dir=tmp_path / "plain", **common))
        confirmed = _train(
            _cfg(tmp_path, run_dir=tmp_path / "confirmed", confirm_episodes=4, **common)
        )
        assert read_curve(tmp_path / "confirmed", "confirm/score")[1].size >= 1
        assert_same_run(confirmed, tmp_path / "confirmed", tmp_path / "plain")
        assert plain["best_confirmed"] is None

    def test_sampled_evaluations_change_no_training_and_repeat_their_draws(self, tmp_path):
        from rl_pg.training.checkpoints import RunState
        from rl_pg.training.seeds import run_streams
        from rl_pg.training.selection import evaluate_run

        common = {"total_updates": 8, "eval_interval": 100, "eval_episodes": 4}
        _train(_cfg(tmp_path, run_dir=tmp_path / "greedy", **common))
        _train(_cfg(tmp_path, run_dir=tmp_path / "sampled", eval_greedy=False, **common))
        # the run learns what it learns however (and how often) it is evaluated
        greedy, sampled = run_weights(tmp_path / "greedy"), run_weights(tmp_path / "sampled")
        for key, value in greedy.items():
            assert torch.equal(value, sampled[key]), key
        # every evaluation draws the same random numbers: one policy, one score
        actor, _ = make_grid_models(make_grid())
        load_models(read_run(tmp_path / "sampled"), actor)
        cfg = _cfg(tmp_path, eval_greedy=False, **common)
        state = RunState(streams=run_streams(cfg.seed))
        logger = type("Silent", (), {"log_scalar": lambda self, *a, **k: None})()
        scores = []
        for stream in (1, 2):
            torch.manual_seed(stream)  # wherever training's stream is
            evaluate_run(cfg, cfg.torch_device(), actor, make_grid(), {}, state, logger)
            scores.append(state.last_eval["eval/mean_return"])
            after = torch.rand(1)
            torch.manual_seed(stream)
            assert torch.equal(after, torch.rand(1))  # and it is left there
        assert scores[0] == scores[1]

    def test_only_evaluations_at_the_threshold_are_confirmed(self, tmp_path):
        summary = _train(
            _cfg(tmp_path, total_updates=6, eval_interval=200, confirm_episodes=4,
                 threshold=1e9, stop_when_solved=False)
        )  # fmt: skip
        assert not (tmp_path / "run" / "logs" / "csv" / "scalars" / "confirm").exists()
        assert summary["best_confirmed"] is None
        _, evaluations = read_curve(tmp_path / "run", "eval/mean_return")
        assert summary["best_eval_mean_return"] == max(evaluations.tolist())

    def test_which_must_be_last_or_best(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=1))
        with pytest.raises(ValueError, match="which must be 'last' or 'best'"):
            read_run(tmp_path / "run", which="first")

    def test_a_run_without_a_best_checkpoint_says_so(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=1))
        (tmp_path / "run" / "best.pt").unlink()
        with pytest.raises(CheckpointError, match=r"has no best\.pt .* which='last'"):
            read_run(tmp_path / "run", which="best")


class TestSelectionMetric:
    """A run keeps, confirms and judges its threshold on the evaluation entry it selects
    by (``--select-by``, ``--select-mode``), not always the mean return."""

    def test_best_is_the_best_evaluation_of_the_metric_even_where_the_return_disagrees(
        self, tmp_path
    ):
        # The longest evaluation episodes: the return's worst policy, the metric's best.
        cfg = _cfg(tmp_path, total_updates=12, eval_interval=200, select_by="mean_length")
        summary = _train(cfg)
        run = tmp_path / "run"
        frames, lengths = read_curve(run, "eval/mean_length")
        _, returns = read_curve(run, "eval/mean_return")
        kept = int(np.argmax(lengths))  # the first of the longest
        assert int(np.argmax(returns)) != kept  # the two disagree: the test tells them apart
        best = read_run(run, which="best")
        assert best["state"]["frames"] == summary["best_at_frames"] == frames[kept]
        assert summary["select_by"] == "mean_length" and summary["select_mode"] == "max"
        assert summary["best_eval_value"] == best["state"]["best_eval"]["eval/mean_length"]
        assert summary["best_eval_value"] == lengths[kept]
        assert summary["best_eval_mean_return"] == returns[kept]  # the return it was kept at
        assert summary["eval_value"] == lengths[-1]
        # the printed summary names the metric once, in words
        printed = format_summary(summary)
        line = (
            f"best checkpoint by mean_length: {lengths[kept]:.3f} at {int(frames[kept]):,} "
            f"frames (return {returns[kept]:.2f})"
        )
        assert line in printed and "select" not in printed and "eval value" not in printed
        assert "(best " not in printed  # the return's best is not what was kept
        plain = format_summary(_train(_cfg(tmp_path, run_dir=tmp_path / "plain")))
        assert "best checkpoint by" not in plain and "select" not in plain

    def test_the_lowest_is_best_when_the_mode_says_so(self, tmp_path):
        cfg = _cfg(tmp_path, total_updates=12, eval_interval=200, select_mode="min")
        summary = _train(cfg)
        frames, returns = read_curve(tmp_path / "run", "eval/mean_return")
        assert returns.min() < returns.max()
        assert summary["best_at_frames"] == frames[int(np.argmin(returns))]
        assert summary["best_eval_value"] == summary["best_eval_mean_return"] == returns.min()

    def test_confirmations_score_the_worse_of_greedy_and_sampled_on_the_metric(self, tmp_path):
        cfg = _cfg(tmp_path, total_updates=10, eval_interval=200, confirm_episodes=4,
                   select_by="mean_length", select_mode="min")  # fmt: skip
        summary = _train(cfg)
        run = tmp_path / "run"
        _, scores = read_curve(run, "confirm/score")
        _, greedy = read_curve(run, "confirm/greedy_mean_length")
        _, sampled = read_curve(run, "confirm/sampled_mean_length")
        assert len(scores) >= 1
        torch.testing.assert_close(scores, np.maximum(greedy, sampled))  # lower is better
        assert summary["best_confirmed"] == scores.min()
        assert not (run / "logs/csv/scalars/confirm/greedy_mean_return.csv").exists()

    def test_the_threshold_is_judged_on_the_metric(self, tmp_path):
        # Lengths of at most 30 steps: every evaluation is at or below the threshold.
        cfg = _cfg(tmp_path, total_updates=12, eval_interval=200, select_by="mean_length",
                   select_mode="min", threshold=30.0)  # fmt: skip
        summary = _train(cfg)
        assert summary["updates"] < 12 and summary["solved_at_frames"] is not None
        frames, _ = read_curve(tmp_path / "run", "eval/mean_length")
        assert summary["solved_at_frames"] == frames[0]

    def test_an_entry_the_evaluations_do_not_report_is_refused_before_any_environment(
        self, tmp_path
    ):
        def never(*args):  # an environment that must not be built
            raise AssertionError("an environment was built")

        cfg = _cfg(tmp_path, select_by="crashed_rate")
        with pytest.raises(ValueError, match=r"--select-by crashed_rate.*mean_return, std_return"):
            train(cfg, recipe="grid", make_env=never, make_models=make_grid_models)
        assert not (tmp_path / "run").exists()

    def test_an_entry_the_environment_never_sets_is_named_at_the_first_evaluation(self, tmp_path):
        cfg = _cfg(tmp_path, total_updates=2, eval_interval=100, select_by="crashed_rate")
        with pytest.raises(KeyError, match=r"reported no crashed_rate.*never set"):
            _train(cfg, eval_flags=("crashed",))

    def test_checkpoints_of_runs_that_kept_their_best_return_resume_with_it(self, tmp_path):
        from rl_pg.training.checkpoints import restore
        from rl_pg.training.metric import Metric

        _train(_cfg(tmp_path, total_updates=4, eval_interval=200))
        saved = read_run(tmp_path / "run")
        kept = saved["state"]["best_eval"]["eval/mean_return"]
        del saved["state"]["best_eval"]
        saved["state"]["best_mean_return"] = kept  # as checkpoints were written before
        cfg = _cfg(tmp_path)
        actor, critic = make_grid_models(make_grid())
        from rl_pg.training.optimisation import make_loss, make_optimizer

        loss = make_loss(cfg, actor, critic)
        state = restore(saved, loss, make_optimizer(cfg, loss), tmp_path / "run")
        assert state.best(Metric()) == kept
        state.last_eval = {"eval/mean_return": kept}
        assert not state.is_best(Metric())  # a tie keeps the earlier one
        state.last_eval = {"eval/mean_return": kept + 1}
        assert state.is_best(Metric()) and state.best(Metric()) == kept + 1


class TestMetric:
    def test_better_reaches_and_worst_follow_the_mode(self):
        from rl_pg.training.metric import Metric

        high, low = Metric("mean_return"), Metric("crashed_rate", "min")
        assert high.better(2.0, than=1.0) and not high.better(1.0, than=1.0)
        assert low.better(0.1, than=0.2) and not low.better(0.2, than=0.1)
        assert high.better(-5.0, than=None) and low.better(5.0, than=None)
        assert not high.better(float("nan"), than=None)
        assert high.reaches(1.0, 1.0) and not high.reaches(0.9, 1.0)
        assert low.reaches(0.2, 0.2) and not low.reaches(0.3, 0.2)
        assert high.worst([1.0, 3.0]) == 1.0 and low.worst([0.1, 0.3]) == 0.3

    @pytest.mark.parametrize(
        ("key", "mode", "match"),
        [("", "max", "evaluation entry's name"), ("mean_return", "highest", "'max'.*'min'")],
    )
    def test_a_malformed_metric_is_refused(self, key, mode, match):
        from rl_pg.training.metric import Metric

        with pytest.raises((TypeError, ValueError), match=match):
            Metric(key, mode)

    def test_the_mode_is_a_choice_of_the_config(self):
        with pytest.raises(ValueError, match="select_mode"):
            _cfg(Path("."), select_mode="highest")

    def test_reports_and_summaries_of_runs_before_the_choice_read_as_the_return(self):
        from rl_pg.training.metric import Metric

        assert Metric.of_summary({"best_eval_mean_return": 1.0}) == Metric("mean_return", "max")
        assert Metric.of_summary({"select_by": "crash_rate", "select_mode": "min"}) == Metric(
            "crash_rate", "min"
        )
