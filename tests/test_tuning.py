"""rl-pg tune: an Optuna study over a recipe, stored and continued in its directory."""

from __future__ import annotations

import datetime
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import hide_module

from rl_pg.app import evaluate
from rl_pg.app.cli import main
from rl_pg.app.flags import flag
from rl_pg.recipes import load
from rl_pg.training.run_dir import locked
from rl_pg.training.seeds import evaluation_seed, fresh_seed, replay_seed
from rl_pg.training.studies import TRIAL_LOCK, abandoned
from rl_pg.training.tuning import tune

optuna = pytest.importorskip("optuna")
gridworld = load("gridworld")


def _base(**overrides):
    settings = {"total_updates": 2, "episodes_per_batch": 4, "progress": False, **overrides}
    return gridworld.config(**settings)


def _study(study_dir):
    return optuna.load_study(study_name="gridworld", storage=f"sqlite:///{study_dir / 'study.db'}")


def test_a_study_is_stored_and_continued(tmp_path):
    result = tune(
        gridworld, _base(), params=["lr", "entropy_coeff"], trials=2, seeds=[0, 1],
        study_dir=tmp_path,
    )  # fmt: skip
    assert result["trials"] == 2 and set(result["best_settings"]) == {"lr", "entropy_coeff"}
    assert json.loads((tmp_path / "best.json").read_text()) == result
    for trial in (0, 1):  # every trial trained every seed, in its own run directory
        for seed in (0, 1):
            assert (tmp_path / f"trial{trial}" / f"seed{seed}" / "summary.json").exists()
    best = _study(tmp_path).best_trial
    assert result["best_score"] == pytest.approx(sum(best.user_attrs["scores"]) / 2)

    # The same command again: the study already holds its trials.
    same = {"params": ["lr", "entropy_coeff"], "seeds": [0, 1], "study_dir": tmp_path}
    again = tune(gridworld, _base(), trials=2, **same)
    assert again["trials"] == 2 and not (tmp_path / "trial2").exists()
    # More trials: only the missing ones run.
    more = tune(gridworld, _base(), trials=3, **same)
    assert more["trials"] == 3 and (tmp_path / "trial2").exists()
    # ... with settings of its own: a search run again does not replay the first one's.
    lrs = [trial.params["lr"] for trial in _study(tmp_path).trials]
    assert len(set(lrs)) == 3


def test_a_search_with_other_settings_does_not_join_a_study(tmp_path):
    first = {"params": ["lr"], "seeds": [0], "study_dir": tmp_path}
    tune(gridworld, _base(), trials=1, **first)
    for changed, match in [
        ({"params": ["gamma"]}, r"params: \['lr'\] -> \['gamma'\]"),
        ({"seeds": [0, 1]}, r"seeds: \[0\] -> \[0, 1\]"),
        ({"objective": "best"}, "objective: 'final' -> 'best'"),
    ]:
        with pytest.raises(ValueError, match=match):
            tune(gridworld, _base(), trials=2, **{**first, **changed})
    with pytest.raises(ValueError, match=r"--gamma: 1.0 -> 0.9.*another --run-dir"):
        tune(gridworld, _base(gamma=0.9), trials=2, **first)  # another discount
    # what only sets the reference trial, or where the runs are watched, may differ
    more = tune(gridworld, _base(lr=0.02, threads=2), trials=2, **first)
    assert more["trials"] == 2


def test_the_first_trial_runs_the_given_settings(tmp_path):
    result = tune(gridworld, _base(lr=3e-3), params=["lr"], trials=2, study_dir=tmp_path)
    first, second = _study(tmp_path).trials
    assert first.user_attrs["reference"] and first.user_attrs["settings"] == {"lr": 3e-3}
    assert second.params["lr"] != 3e-3 and "reference" not in second.user_attrs
    assert result["reference_score"] == first.value
    # Settings outside the search space have no trial that could run them: said once.
    said = []
    tune(gridworld, _base(lr=0.5), params=["lr"], trials=1, study_dir=tmp_path / "outside",
         report=said.append)  # fmt: skip
    assert "reference" not in _study(tmp_path / "outside").trials[0].user_attrs
    assert said[0].startswith("No reference trial: lr is 0.5, outside the searched range")


def test_a_trial_below_the_median_is_pruned_at_the_evaluation_it_falls_behind(tmp_path):
    # Five earlier trials whose every evaluation scored 1.0: a gridworld run of a few
    # updates (stuck at -10) falls below their median, and stops after its third.
    base = _base(total_updates=6, eval_interval=1)
    tune(gridworld, base, params=["lr"], trials=1, study_dir=tmp_path, report=None)
    study = _study(tmp_path)
    reference = study.trials[0]
    for lr in (1e-3, 2e-3, 3e-3, 4e-3, 5e-3):
        study.add_trial(optuna.trial.create_trial(
            params={"lr": lr}, distributions=reference.distributions, value=1.0,
            intermediate_values=dict.fromkeys(range(6), 1.0), user_attrs={"settings": {"lr": lr}},
        ))  # fmt: skip
    said = []
    result = tune(gridworld, base, params=["lr"], trials=8, study_dir=tmp_path, report=said.append)
    trials = _study(tmp_path).trials
    assert [t.state for t in trials[6:]] == [optuna.trial.TrialState.PRUNED] * 2
    assert result["trials"] == 8 and result["pruned"] == 2  # pruned trials count as done
    for trial in trials[6:]:
        assert sorted(trial.intermediate_values) == [0, 1, 2]  # judged at the third only
        summary = json.loads((tmp_path / f"trial{trial.number}/seed0/summary.json").read_text())
        assert summary["updates"] == 3  # the run stopped there
    assert "(7 of 8 done) pruned at " in said[0] and "below the median" in said[0]
    assert reference.state == optuna.trial.TrialState.COMPLETE
    # without a pruner, the same trials train whole
    tune(gridworld, base, params=["lr"], trials=9, study_dir=tmp_path, pruner="none",
         report=None)  # fmt: skip
    assert _study(tmp_path).trials[8].state == optuna.trial.TrialState.COMPLETE


def _running_trial(study_dir):
    """A trial the study lists as running, as a search that is (or was) in it leaves it."""
    study = optuna.create_study(
        study_name="gridworld", storage=f"sqlite:///{study_dir / 'study.db'}",
        direction="maximize", load_if_exists=True,
    )  # fmt: skip
    trial = study.ask()
    (study_dir / f"trial{trial.number}").mkdir()
    return study_dir / f"trial{trial.number}" / TRIAL_LOCK


def test_a_killed_search_s_trial_is_failed_and_the_search_goes_on(tmp_path):
    _running_trial(tmp_path).touch()  # its lock file, free: the process that held it died
    result = tune(gridworld, _base(), params=["lr"], trials=1, study_dir=tmp_path)
    states = [t.state for t in _study(tmp_path).trials]
    assert states == [optuna.trial.TrialState.FAIL, optuna.trial.TrialState.COMPLETE]
    assert result["best_trial"] == 1


def test_a_second_search_on_the_same_study_leaves_the_first_one_s_trial_alone(tmp_path):
    with locked(_running_trial(tmp_path)) as held:  # held as the live search holds it
        assert held
        result = tune(gridworld, _base(), params=["lr"], trials=1, study_dir=tmp_path)
    states = [t.state for t in _study(tmp_path).trials]
    assert states == [optuna.trial.TrialState.RUNNING, optuna.trial.TrialState.COMPLETE]
    assert result["trials"] == 1  # complete trials of both searches count towards --trials


def test_two_searches_share_one_study(tmp_path):
    # rl-pg tune --jobs 2: a second search in a process of its own, on the same study;
    # the command reports once, after both
    done = subprocess.run(
        [sys.executable, "-m", "rl_pg.app", "tune", "gridworld", "--trials", "4",
         "--jobs", "2", "--params", "lr", "--total-updates", "2", "--no-progress",
         "--run-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.count(" trials in ") == 1  # one summary, by the command itself
    states = [t.state for t in _study(tmp_path).trials]
    complete = states.count(optuna.trial.TrialState.COMPLETE)
    assert complete in (4, 5) and len(states) == complete  # at most one trial over
    lrs = [trial.params["lr"] for trial in _study(tmp_path).trials]
    assert len(set(lrs)) == len(lrs)  # neither repeats the other's settings
    assert json.loads((tmp_path / "best.json").read_text())["trials"] == complete


def test_a_running_trial_without_a_lock_is_abandoned_once_it_is_old():
    now = datetime.datetime.now()
    young = SimpleNamespace(number=0, datetime_start=now)
    old = SimpleNamespace(number=0, datetime_start=now - datetime.timedelta(minutes=5))
    assert not abandoned(young, Path("no-such-study"))  # a search that just asked for it
    assert abandoned(old, Path("no-such-study"))  # killed before it locked, or older code


def test_the_sampled_settings_reach_the_runs(tmp_path):
    tune(gridworld, _base(), params=["lr", "returns", "gae_lambda"], trials=2, study_dir=tmp_path)
    for trial in _study(tmp_path).trials:
        settings = trial.user_attrs["settings"]
        stored = json.loads(
            (tmp_path / f"trial{trial.number}" / "seed0" / "config.json").read_text()
        )
        assert stored["lr"] == settings["lr"] and stored["returns"] == settings["returns"]
        # gae_lambda is read by GAE alone: searched only when GAE was picked.
        assert ("gae_lambda" in settings) == (settings["returns"] == "gae")


def test_held_out_scores_hold_both_ways_and_worst_takes_the_weakest_seed(tmp_path):
    result = tune(
        gridworld, _base(eval_interval=50), params=["lr"], trials=1, seeds=[0, 1],
        objective="held_out", held_out_episodes=6, seed_score="worst", study_dir=tmp_path,
    )  # fmt: skip
    runs = result["best_runs"]
    for key, run in runs.items():  # each run: its best checkpoint, as rl-pg evaluate plays it
        seed, run_dir = int(key), tmp_path / "trial0" / f"seed{key}"
        # on episodes of their own: rl-pg evaluate's default ones confirm what was tuned
        assert replay_seed(seed) not in (fresh_seed(seed), evaluation_seed(seed))
        for mode in ("greedy", "sampled"):
            args = evaluate.Args(
                run=run_dir, episodes=6, sample=mode == "sampled", seed=replay_seed(seed)
            )
            assert run[mode] == evaluate.main(args)["mean_return"]
        assert run["score"] == min(run["greedy"], run["sampled"])
    assert result["best_score"] == min(run["score"] for run in runs.values())
    assert result["seed_score"] == "worst" and result["objective"] == "held_out"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"params": ["learning_rate"]}, r"Cannot tune \['learning_rate'\].*'lr'"),
        ({"params": ["backend"]}, r"Cannot tune \['backend'\]"),  # gridworld has none
        ({"params": []}, "Cannot tune nothing"),
        ({"params": ["lr"], "seeds": []}, "at least one seed"),
        ({"params": ["lr"], "trials": 0}, "at least 1"),
        ({"params": ["lr"], "objective": "mean"}, "objective must be"),
        ({"params": ["lr"], "seed_score": "median"}, "seed_score must be"),
        ({"params": ["lr"], "held_out_episodes": 0}, "held_out_episodes must be at least 1"),
    ],
)
def test_bad_requests(tmp_path, kwargs, match):
    kwargs = {"trials": 1, **kwargs}
    with pytest.raises(ValueError, match=match):
        tune(gridworld, _base(), study_dir=tmp_path, **kwargs)


def test_without_optuna(tmp_path, monkeypatch):
    hide_module(monkeypatch, "optuna")
    with pytest.raises(ImportError, match=r'pip install -c constraints.txt "rl_pg\[tune\]"'):
        tune(gridworld, _base(), params=["lr"], trials=1, study_dir=tmp_path)


def test_the_command(tmp_path, capsys):
    args = ["tune", "gridworld", "--trials", "1", "--params", "lr", "normalize_advantage",
            "--objective", "best", "--total-updates", "2", "--no-progress", "--lr", "0.003",
            "--run-dir", str(tmp_path)]  # fmt: skip
    main(args)
    out = capsys.readouterr().out
    # each trial is reported as it ends, before the search's summary
    assert out.index("trial 0 (1 of 1 done): score ") < out.index("1 trials in")
    assert "with lr=0.003, normalize_advantage=False; best so far: trial 0" in out
    assert f"1 trials in {tmp_path} (0 pruned); best: trial 0" in out
    assert "The settings as given (trial 0) scored" in out
    assert "--lr 0.003 --no-normalize-advantage" in out  # as flags of rl-pg train
    assert json.loads((tmp_path / "best.json").read_text())["objective"] == "best"


def test_the_printed_flags_give_back_the_trial_s_exact_values():
    # Rounded, a sampled learning rate starts a different run from the same seed.
    lr = 0.0020299660450482514
    assert float(flag("lr", lr).split()[1]) == lr


@pytest.mark.parametrize("content", [b"not a database, just text\n" * 100, b""])
def test_a_study_file_that_is_not_a_study_is_named(tmp_path, capsys, content):
    (tmp_path / "study.db").write_bytes(content)
    if not content:  # an empty file is a valid empty SQLite database: a new study
        assert tune(gridworld, _base(), params=["lr"], trials=1, study_dir=tmp_path,
                    report=None)["trials"] == 1  # fmt: skip
        return
    with pytest.raises(ValueError, match=r"study.db is not a study this Optuna can open \(file "
                       r"is not a database\)\. Move it away"):  # fmt: skip
        tune(gridworld, _base(), params=["lr"], trials=1, study_dir=tmp_path)
    with pytest.raises(SystemExit, match=r"rl-pg tune: .*study\.db is not a study"):
        main(["tune", "gridworld", "--trials", "1", "--params", "lr", "--run-dir", str(tmp_path)])


def test_a_study_scores_the_metric_the_runs_select_by_and_keeps_its_direction(tmp_path):
    # The shortest evaluation episodes are best here: the study minimises their length.
    base = _base(select_by="mean_length", select_mode="min", eval_episodes=2)
    result = tune(gridworld, base, params=["lr"], trials=2, study_dir=tmp_path,
                  objective="best", pruner="none", report=None)  # fmt: skip
    study = _study(tmp_path)
    assert study.direction.name == "MINIMIZE"
    scores = {t.number: t.value for t in study.trials}
    for number, value in scores.items():
        summary = json.loads((tmp_path / f"trial{number}" / "seed0" / "summary.json").read_text())
        assert value == summary["best_eval_value"]
        assert summary["select_by"] == "mean_length"
    assert result["best_score"] == min(scores.values())
    # The same study asked to maximise: refused, naming both directions.
    highest = _base(eval_episodes=2, select_by="mean_length")
    with pytest.raises(ValueError, match=r"minimizes its score.*maximize it"):
        tune(gridworld, highest, params=["lr"], trials=3, study_dir=tmp_path,
             objective="best", pruner="none", report=None)  # fmt: skip
    # An entry the recipe's evaluations do not report: refused before any trial.
    with pytest.raises(ValueError, match=r"--select-by crashed_rate"):
        tune(gridworld, _base(select_by="crashed_rate"), params=["lr"], trials=1,
             study_dir=tmp_path / "other", report=None)  # fmt: skip
    assert not (tmp_path / "other").exists()
