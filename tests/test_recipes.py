"""Every recipe trained on a tiny budget, one real CartPole solve, and deployment."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import re
import sys

import numpy as np
import pytest
import torch
from conftest import assert_same_run, averaged_weights
from PIL import Image, ImageSequence

from rl_pg.app import evaluate, play
from rl_pg.envs import GridWorldEnv
from rl_pg.recipes import NAMES, load
from rl_pg.training import load_models, read_run
from rl_pg.training.seeds import evaluation_seed, fresh_seed

bandit, cartpole, gridworld, gym, highway, lunarlander, pendulum, pong = (
    load(name)
    for name in (
        "bandit", "cartpole", "gridworld", "gym", "highway", "lunarlander", "pendulum", "pong"
    )
)  # fmt: skip

TINY = {"eval_episodes": 1, "checkpoint_interval": 1, "progress": False}
RECIPES = {
    "bandit": (bandit, {"total_updates": 20, "eval_interval": 10, "samples_per_update": 4}),
    "gridworld": (gridworld, {"total_updates": 3, "eval_interval": 100}),
    "cartpole": (cartpole, {"total_frames": 600, "eval_interval": 600}),
    "cartpole-whole-episodes": (
        cartpole,
        {"total_frames": 600, "eval_interval": 600, "batch_mode": "episodes", "num_envs": 1},
    ),
    # Continuous torque in [-2, 2]: the bounds are per dimension, not ±1.
    "pendulum": (pendulum, {"total_frames": 1_024, "eval_interval": 1_024}),
    "lunarlander": (lunarlander, {"total_frames": 1_500, "eval_interval": 1_500}),
    "lunarlander-continuous": (
        lunarlander,
        {"total_frames": 1_500, "eval_interval": 1_500, "continuous": True},
    ),
    "cartpole-envpool": (
        cartpole,
        {"total_frames": 600, "eval_interval": 600, "backend": "envpool"},
    ),
    "lunarlander-continuous-envpool": (
        lunarlander,
        {"total_frames": 1_500, "eval_interval": 1_500, "continuous": True, "backend": "envpool"},
    ),
    "highway": (highway, {"total_frames": 60, "eval_interval": 60, "episodes_per_batch": 1}),
    # The generic recipe on ids it has no recipe for: discrete and box actions.
    "gym-discrete": (gym, {"env_id": "Acrobot-v1", "total_frames": 512, "eval_interval": 512}),
    "gym-box": (
        gym,
        {"env_id": "MountainCarContinuous-v0", "total_frames": 512, "eval_interval": 512},
    ),
    "pong": (
        pong,
        {"total_frames": 400, "eval_interval": 400, "num_envs": 2, "segment_length": 20},
    ),
}


@pytest.mark.parametrize("name", list(RECIPES))
def test_recipe_trains_to_a_complete_run(name, tmp_path):
    recipe, overrides = RECIPES[name]
    run = tmp_path / name
    summary = recipe.train(recipe.config(run_dir=run, **TINY, **overrides))
    assert json.loads((run / "summary.json").read_text()) == summary
    for key in ("recipe", "seed", "frames", "train_wall_s", "eval_mean_return", "threshold"):
        assert key in summary
    assert summary["frames"] > 0 and summary["eval_mean_return"] is not None
    assert (run / "checkpoint.pt").is_file() and (run / "learning_curve.png").is_file()
    assert (run / "logs" / "csv" / "scalars" / "eval" / "mean_return.csv").is_file()


@pytest.mark.parametrize("recipe", [cartpole, lunarlander])
def test_the_envpool_backend_is_used_for_any_number_of_environments(recipe):
    from rl_pg.envs.envpool import EnvPoolEnv

    pytest.importorskip("envpool")
    for num_envs in (1, 3):
        env = recipe.make_env(recipe.config(backend="envpool", num_envs=num_envs))
        try:
            assert isinstance(env, EnvPoolEnv) and env.batch_size == (num_envs,)
        finally:
            env.close()
    assert not isinstance(recipe.make_env(recipe.config(num_envs=1)), EnvPoolEnv)


@pytest.mark.parametrize("backend", ["gymnasium", "envpool"])
def test_vectorised_cartpole_resumes_exactly(tmp_path, backend):
    """Killed between two environment restarts and resumed, a run ends as the
    uninterrupted one: the environments replay the recorded actions exactly."""
    if backend == "envpool":
        pytest.importorskip("envpool")
    common = {**TINY, "checkpoint_interval": 1000, "backend": backend, "num_envs": 4}
    common |= {"env_restart_interval": 4, "eval_interval": 10**6, "threshold": None}
    cartpole.train(cartpole.config(run_dir=tmp_path / "straight", total_updates=10, **common))
    cartpole.train(cartpole.config(run_dir=tmp_path / "split", total_updates=6, **common))
    resumed = cartpole.train(
        cartpole.config(run_dir=tmp_path / "split", total_updates=10, resume=True, **common)
    )
    assert_same_run(resumed, tmp_path / "split", tmp_path / "straight")


def test_highway_reports_the_crash_rate(tmp_path):
    summary = highway.train(
        highway.config(
            run_dir=tmp_path, total_frames=40, eval_interval=40, episodes_per_batch=1, **TINY
        )
    )
    assert 0.0 <= summary["crashed_rate"] <= 1.0


@pytest.mark.parametrize("flags", [{}, {"bounded": "tanh_normal"}], ids=["normal", "tanh_normal"])
def test_continuous_lunarlander_learns_one_scale_per_thrust_dimension(flags):
    scales = _scale_parameters(lunarlander.config(continuous=True, **flags))
    assert [tuple(p.shape) for p in scales] == [(2,)]  # one per thrust dimension


@pytest.mark.parametrize(
    "flags", [{}, {"continuous": True, "bounded": "beta"}], ids=["discrete", "beta"]
)
def test_lunarlander_refuses_a_state_dependent_scale_without_a_gaussian(flags):
    with pytest.raises(ValueError, match=r"--state-dependent-scale .* --continuous"):
        lunarlander.config(state_dependent_scale=True, **flags)


def test_continuous_lunarlander_starts_at_the_scale_asked():
    (scale,) = _scale_parameters(lunarlander.config(continuous=True, init_scale=0.3))
    torch.testing.assert_close(scale.detach().exp(), torch.full((2,), 0.3))


@pytest.mark.parametrize(
    "flags",
    [{}, {"continuous": True, "bounded": "beta"},
     {"continuous": True, "state_dependent_scale": True}],
    ids=["discrete", "beta", "state_dependent"],
)  # fmt: skip
def test_lunarlander_refuses_a_starting_scale_without_one_learned_scale(flags):
    with pytest.raises(ValueError, match=r"--init-scale 0.3 sets the starting scale"):
        lunarlander.config(init_scale=0.3, **flags)


def test_continuous_lunarlander_can_output_its_scale():
    assert not _scale_parameters(lunarlander.config(continuous=True, state_dependent_scale=True))


def _scale_parameters(cfg) -> list[torch.nn.Parameter]:
    """The parameters of the LunarLander actor ``cfg`` builds that hold a scale."""
    env = lunarlander.make_env(cfg)
    try:
        actor, _ = lunarlander.make_models(env, cfg)
    finally:
        env.close()
    return [p for name, p in actor.named_parameters() if "scale" in name]


@pytest.mark.parametrize("sticky", [0.0, 0.25])
def test_pong_evaluation_games_differ_only_with_sticky_actions(sticky):
    """A deterministic player meets one game per seed unless the game repeats actions:
    Pong's evaluations play with sticky actions so that their games differ."""
    pytest.importorskip("ale_py")
    env = pong.make_eval_env(pong.config(eval_episodes=2, eval_sticky=sticky))
    try:
        env.set_seed(0)  # two games, seeded apart
        td, same = env.reset(), True
        for t in range(300):  # up, down, up...: a repeated action is not the agent's
            td["action"] = torch.full((2,), 2 + t % 2)
            td = env.step(td)["next"]
            same &= torch.equal(td["observation"][0], td["observation"][1])
        assert same == (sticky == 0.0)
    finally:
        env.close()
    # rl-pg play deploys in the same game, recorded or not
    for render in (False, True):
        game = pong.make_play_env(pong.config(eval_sticky=sticky), render=render)
        try:
            ale = game.base_env._env.unwrapped.ale
            assert ale.getFloat("repeat_action_probability") == pytest.approx(sticky)
        finally:
            game.close()
    # the training games stick by their own flag, one game or a batch
    for num_envs in (1, 2):
        training = pong.make_env(pong.config(num_envs=num_envs, train_sticky=sticky / 2))
        try:
            games = training.base_env._env
            ales = [games.unwrapped.ale] if num_envs == 1 else [e.unwrapped.ale for e in games.envs]
            for ale in ales:
                assert ale.getFloat("repeat_action_probability") == pytest.approx(sticky / 2)
        finally:
            training.close()


@pytest.mark.parametrize("trunk", ["dense", "conv"])
@pytest.mark.parametrize("frame", [False, True])
def test_pong_sees_the_current_frame_only_when_asked(frame, trunk):
    """A difference shows nothing of a paddle that stands still: --frame feeds the current
    frame (FrameDifference's previous_frame, the next step's previous one) beside it, to
    either trunk."""
    pytest.importorskip("ale_py")
    cfg = pong.config(num_envs=2, frame=frame, trunk=trunk)
    env = pong.make_env(cfg)
    try:
        actor, value = pong.make_models(env, cfg)
        td = env.rollout(3, actor)[:, -1]
    finally:
        env.close()
    first = actor.module[0].module[0]
    if trunk == "dense":
        assert first.in_features == (12_800 if frame else 6_400)
    else:  # the images as channels, from orthogonal weights and a near-uniform policy
        assert first[0].in_channels == (2 if frame else 1)
        (head,) = (
            m.weight
            for m in actor.modules()
            if isinstance(m, torch.nn.Linear) and m.out_features == 6
        )
        assert torch.allclose(head @ head.T, 1e-4 * torch.eye(6), atol=1e-7)
    assert value(td.clone())["state_value"].shape == (2, 1)
    moved = td.clone()
    moved["previous_frame"] = torch.zeros_like(td["previous_frame"])
    assert td["previous_frame"].sum() > 0  # the paddles and the score are drawn
    logits = [actor(x.clone())["logits"] for x in (td, moved)]
    assert torch.equal(*logits) != frame


def test_cartpole_reaches_475(tmp_path):
    summary = cartpole.train(cartpole.config(run_dir=tmp_path, progress=False))
    assert summary["solved_at_frames"] is not None
    assert summary["eval_mean_return"] >= 475


def test_gridworld_comparison_plot(tmp_path):
    cfg = gridworld.config(run_dir=tmp_path, n_seeds=1, total_updates=2, compare=True, **TINY)
    results = gridworld.run(cfg)
    assert set(results) == {
        "no baseline",
        "running-mean baseline",
        "reward-to-go",
        "reward-to-go - learned V",
    }
    assert (tmp_path / "comparison.png").is_file()


def test_a_comparisons_run_resumes_as_a_run(tmp_path, capsys):
    """A run of a comparison stores no command flag, and resuming it resumes it: it
    ran the whole comparison again inside the run's directory."""
    cfg = gridworld.config(run_dir=tmp_path, n_seeds=1, total_updates=2, compare=True, **TINY)
    gridworld.run(cfg)
    run = tmp_path / "reward-to-go" / "seed0"
    assert json.loads((run / "config.json").read_text())["compare"] is False
    resumed = gridworld.config.from_stored(
        json.loads((run / "config.json").read_text()), resume=True, run_dir=run
    )
    summary = gridworld.run(dataclasses.replace(resumed, total_updates=3))
    assert summary["updates"] == 3 and sorted(p.name for p in run.iterdir() if p.is_dir()) == [
        "logs"
    ]
    # a run stored with the flag (before this fix) resumes too, and says what it does
    gridworld.run(dataclasses.replace(resumed, total_updates=4, compare=True))
    assert "--compare starts new runs and does not resume" in capsys.readouterr().err
    assert not (run / "no baseline").exists()


def test_bandit_comparison_plot(tmp_path):
    cfg = bandit.config(
        run_dir=tmp_path, n_seeds=2, total_updates=30, eval_interval=10, compare=True, **TINY
    )
    results = bandit.run(cfg)
    assert [len(runs) for runs in results.values()] == [2, 2]
    assert all("final_running_reward" in run for runs in results.values() for run in runs)
    assert (tmp_path / "comparison.png").is_file()


def test_play_records_a_gif(tmp_path, capsys):
    cartpole.train(cartpole.config(run_dir=tmp_path, total_frames=300, **TINY))
    gif = tmp_path / "play.gif"
    returns = play.main(play.Args(run=tmp_path, episodes=2, gif=gif))
    assert len(returns) == 2 and gif.stat().st_size > 0
    with Image.open(gif) as image:  # a real animation of the rendered frames
        assert image.size == (600, 400) and image.n_frames > 1
        image.seek(image.n_frames - 1)
        assert len(image.convert("RGB").getcolors(maxcolors=256)) > 2
    assert "mean return" in capsys.readouterr().out


def test_evaluate_replays_the_runs_last_evaluation_and_defaults_to_fresh_episodes(tmp_path):
    cfg = cartpole.config(run_dir=tmp_path, total_frames=600, **{**TINY, "eval_episodes": 4})
    summary = cartpole.train(cfg)
    # The last checkpoint, on the training evaluations' seed: the run's last evaluation.
    again = evaluate.main(
        evaluate.Args(run=tmp_path, checkpoint="last", episodes=4, seed=evaluation_seed(0))
    )
    assert again["mean_return"] == pytest.approx(summary["eval_mean_return"])
    fresh = evaluate.main(evaluate.Args(run=tmp_path, episodes=5, sample=True))
    assert fresh["seed"] == fresh_seed(0) != evaluation_seed(0)
    assert fresh["mode"] == "sampled" and fresh["episodes"] == 5
    records = [
        json.loads(line) for line in (tmp_path / evaluate.EVALUATIONS).read_text().splitlines()
    ]
    assert records == [again, fresh]


def test_evaluate_plays_a_policy_average_or_on_request_the_trained_weights(
    tmp_path, capsys, monkeypatch
):
    import rl_pg.training.recipe as recipe_module

    played = []  # the actor's weights as evaluate_checkpoint loaded them

    def spy(saved, actor, critic=None, **kwargs):
        load_models(saved, actor, critic, **kwargs)
        played.append({k: v.clone() for k, v in actor.state_dict().items()})

    monkeypatch.setattr(recipe_module, "load_models", spy)
    cfg = cartpole.config(
        run_dir=tmp_path, total_frames=600, policy_ema=0.5, **{**TINY, "eval_episodes": 4}
    )
    summary = cartpole.train(cfg)
    args = {"run": tmp_path, "checkpoint": "last", "episodes": 4, "seed": evaluation_seed(0)}
    average = evaluate.main(evaluate.Args(**args))
    assert average["weights"] == "average"  # what the run's evaluations played
    assert average["mean_return"] == pytest.approx(summary["eval_mean_return"])
    trained = evaluate.main(evaluate.Args(**args, trained_weights=True))
    assert trained["weights"] == "trained" and "trained weights" in capsys.readouterr().out
    last = read_run(tmp_path, which="last")
    for weights, source, prefix in (
        (played[0], averaged_weights(last), "module."),
        (played[1], last["loss"], "actor_network."),
    ):
        for key, value in weights.items():
            assert torch.equal(value, source[prefix + key]), key
    assert not all(torch.equal(played[0][k], played[1][k]) for k in played[0])
    file = evaluate.main(evaluate.Args(**{**args, "run": tmp_path / "checkpoint.pt"}))
    assert file["checkpoint"] == "checkpoint.pt" and file["mean_return"] == average["mean_return"]
    assert "checkpoint.pt at " in capsys.readouterr().out


def test_evaluate_on_names_one_of_the_recipes_test_sets():
    # Checked before any environment is built, so no simulator is needed here.
    with pytest.raises(ValueError, match=r"'cartpole' has no test set 'training'.*leave --on"):
        cartpole.test_env(cartpole.config(), on="training")
    metadrive = load("metadrive")
    with pytest.raises(ValueError, match=r"no test set 'train': choose one of \['selection', "):
        metadrive.test_env(metadrive.config(), on="train")


def test_training_evaluate_and_play_run_on_the_runs_threads_then_restore_them(
    tmp_path, monkeypatch
):
    """Small models on torch's one-thread-per-core default wait on each other beside
    other work: training, rl-pg evaluate and rl-pg play all run on cfg.threads, and
    leave the caller's thread count as they found it."""
    import rl_pg.app.play as play_module
    import rl_pg.training.recipe as recipe_module
    import rl_pg.training.selection as selection_module

    seen = []

    def spy(function):
        def wrapped(*args, **kwargs):
            seen.append(torch.get_num_threads())
            return function(*args, **kwargs)

        return wrapped

    for module, name in ((selection_module, "evaluate"), (recipe_module, "evaluate"),
                         (play_module, "play")):  # fmt: skip
        monkeypatch.setattr(module, name, spy(getattr(module, name)))
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        cartpole.train(cartpole.config(run_dir=tmp_path, total_frames=300, **TINY))
        assert torch.get_num_threads() == 2
        evaluate.main(evaluate.Args(run=tmp_path, episodes=2))
        assert torch.get_num_threads() == 2
        play.main(play.Args(run=tmp_path, episodes=1))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(previous)
    assert len(seen) == 3 and set(seen) == {1}  # the recipe's default threads=1


def test_evaluate_reports_the_recipes_flags(tmp_path, capsys):
    highway.train(
        highway.config(
            run_dir=tmp_path, total_frames=40, eval_interval=40, episodes_per_batch=1, **TINY
        )
    )
    result = evaluate.main(evaluate.Args(run=tmp_path, episodes=2))
    assert 0.0 <= result["crashed_rate"] <= 1.0
    assert "crashed_rate" in capsys.readouterr().out


@pytest.mark.parametrize("which", ["best", "last"])
def test_play_deploys_the_best_or_the_last_checkpoint(tmp_path, capsys, which):
    cartpole.train(cartpole.config(run_dir=tmp_path, total_frames=600, **TINY))
    returns = play.main(play.Args(run=tmp_path, episodes=1, checkpoint=which))
    assert len(returns) == 1


def test_play_uses_one_environment_of_a_batched_run(tmp_path, capsys):
    summary = cartpole.train(cartpole.config(run_dir=tmp_path, total_frames=300, **TINY))
    assert summary["frames"] >= 32 * 8  # trained on the default batch of 32 CartPoles
    returns = play.main(play.Args(run=tmp_path, episodes=3, sample=True))
    assert len(returns) == 3 and all(r >= 1 for r in returns)


def test_play_records_an_mp4_into_a_missing_folder(tmp_path):
    cartpole.train(cartpole.config(run_dir=tmp_path / "run", total_frames=300, **TINY))
    video = tmp_path / "videos" / "new" / "cartpole.mp4"
    play.main(play.Args(run=tmp_path / "run", episodes=1, gif=video, fps=50))
    assert video.stat().st_size > 0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"episodes": 0}, r"episodes \(--episodes\) must be an integer >= 1, got 0"),
        ({"fps": 0}, r"fps \(--fps\) must be a finite number > 0, got 0"),
        ({"fps": float("inf")}, r"fps \(--fps\) must be a finite number > 0"),
    ],
)
def test_play_refuses_bad_arguments(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        play.Args(run=tmp_path, **kwargs)


@pytest.mark.parametrize("name", ["out.avi", "out", "out.gif.txt"])
def test_play_refuses_an_unknown_recording_format_before_playing(tmp_path, name):
    # The run does not even exist: the recording is checked first, not after the episodes.
    with pytest.raises(ValueError, match=r"must end in \.gif or \.mp4"):
        play.Args(run=tmp_path / "no-run", gif=tmp_path / name)


def test_play_refuses_a_recording_over_a_folder(tmp_path):
    (tmp_path / "x.gif").mkdir()
    with pytest.raises(ValueError, match="it is a folder"):
        play.Args(run=tmp_path / "no-run", gif=tmp_path / "x.gif")


def test_mp4_without_an_encoder_says_how_to_install_one(tmp_path, monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ModuleNotFoundError, match=r"rl_pg\[video\]"):
        play.Args(run=tmp_path / "no-run", gif=tmp_path / "x.mp4")


def test_play_says_what_it_needs_for_a_run_of_other_code(tmp_path):
    from rl_pg.envs import GridWorldEnv
    from rl_pg.models import mlp_actor_critic
    from rl_pg.training import TrainConfig, train

    cfg = TrainConfig(run_dir=tmp_path / "api", total_updates=1, eval_episodes=1, progress=False)
    train(cfg, recipe="my-own", make_env=GridWorldEnv, make_models=mlp_actor_critic)
    with pytest.raises(ValueError, match=r"No recipe called 'my-own'.*load_models"):
        play.main(play.Args(run=tmp_path / "api"))


def test_play_refuses_to_record_what_does_not_render(tmp_path, monkeypatch):
    gridworld.train(gridworld.config(run_dir=tmp_path, total_updates=1, **TINY))
    module = sys.modules[gridworld.make_env.__module__]  # a recipe that draws nothing
    blind = dataclasses.replace(module.RECIPE, make_env=lambda cfg, render=False: GridWorldEnv())
    monkeypatch.setattr(module, "RECIPE", blind)
    with pytest.raises(ValueError, match=r"gridworld recipe draws no frames.*without --gif"):
        play.main(play.Args(run=tmp_path, episodes=1, gif=tmp_path / "x.gif"))
    assert not (tmp_path / "x.gif").exists()


@pytest.mark.parametrize("name", ["bandit", "gridworld"])
def test_the_torch_native_recipes_record_what_their_agent_does(name, tmp_path):
    recipe = load(name)
    recipe.train(recipe.config(run_dir=tmp_path, total_updates=1, **TINY))
    gif = tmp_path / "play.gif"
    play.main(play.Args(run=tmp_path, episodes=2, gif=gif))
    with Image.open(gif) as image:
        frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(image)]
    env = recipe.make_env(recipe.config(), render=True)
    start = env.reset()["pixels"].numpy()
    assert (frames[0] == start).all()  # the environment's own drawing of its start
    if name == "bandit":  # each pull: the arms, then the pulled one coloured
        assert len(frames) >= 2 and (frames[1] != start).any()


def test_a_run_shorter_than_its_log_interval_ends_with_its_summary(tmp_path):
    # 5 updates, logged every 10: no training curve, and still a summary
    summary = bandit.train(bandit.config(run_dir=tmp_path, total_updates=5, progress=False))
    assert summary["updates"] == 5 and summary["final_running_reward"] is None
    assert json.loads((tmp_path / "summary.json").read_text())["updates"] == 5


def test_pendulum_runs_stored_before_its_kl_set_rate_resume_at_the_plain_rate():
    # The recipe's rate became KL-set: a run whose stored config predates the field ran
    # at --lr alone, and resumes (and is labelled in comparisons) so.
    from rl_pg.training.config import config_dict

    pendulum = load("pendulum")
    stored = config_dict(pendulum.config(seed=3))
    assert (stored["lr_control"], stored["target_kl"]) == ("kl", 0.002)
    for field in ("lr_control", "target_kl"):
        del stored[field]  # as a version without the field wrote it
    old = pendulum.config.from_stored(stored)
    assert (old.lr_control, old.target_kl) == ("none", 0.01)
    assert pendulum.config.from_stored(stored, lr_control="kl").lr_control == "kl"


@pytest.mark.parametrize(
    ("flags", "factor"),
    [
        ({}, 1.0),  # discrete engines: no scale
        ({"continuous": True}, 30.0),  # one learned scale per thrust dimension
        ({"continuous": True, "bounded": "tanh_normal"}, 30.0),
        ({"continuous": True, "state_dependent_scale": True}, 1.0),  # the network's
        ({"continuous": True, "bounded": "beta"}, 1.0),
        ({"continuous": True, "scale_lr_factor": 5.0}, 5.0),  # given: kept
        ({"continuous": True, "optimizer": "natural", "lr_control": "none"}, 1.0),
    ],
)
def test_lunarlander_steps_the_continuous_gaussians_scale_at_thirty_times_the_rate(flags, factor):
    # The default None resolves by the policy, and is stored resolved: config.json says
    # what ran, and a run stored before the field trained at one rate.
    from rl_pg.training.config import config_dict

    lunarlander = load("lunarlander")
    cfg = lunarlander.config(**flags)
    assert cfg.scale_lr_factor == factor
    stored = config_dict(cfg)
    assert stored["scale_lr_factor"] == factor
    assert lunarlander.config.from_stored(stored).scale_lr_factor == factor
    del stored["scale_lr_factor"]  # as a version without the field wrote it
    assert lunarlander.config.from_stored(stored).scale_lr_factor == 1.0
    # a recipe that does not choose by policy: None is the one rate
    assert load("pendulum").config(scale_lr_factor=None).scale_lr_factor == 1.0


def test_lunarlander_runs_stored_before_its_kl_set_rate_resume_at_the_plain_rate():
    # LunarLander's defaults became the KL-set rate without the entropy bonus, best.pt
    # confirmed both ways: a stored config that predates lr_control ran at --lr alone.
    from rl_pg.training.config import config_dict

    lunarlander = load("lunarlander")
    stored = config_dict(lunarlander.config(seed=3))
    assert (stored["lr_control"], stored["target_kl"]) == ("kl", 0.001)
    assert (stored["entropy_coeff"], stored["confirm_episodes"]) == (0.0, 100)
    for field in ("lr_control", "target_kl"):
        del stored[field]  # as a version without the field wrote it
    old = lunarlander.config.from_stored(stored)
    assert (old.lr_control, old.target_kl) == ("none", 0.01)


def test_the_generic_recipe_takes_any_gymnasium_id_and_its_threshold(tmp_path):
    with pytest.raises(ValueError, match="rl-pg train gym needs --env-id"):
        gym.config()
    with pytest.raises(ValueError, match="'Nope-v0' is not a registered gymnasium id"):
        gym.config(env_id="Nope-v0")
    # the registry's own target, unless the user sets one
    assert gym.config(env_id="Acrobot-v1").threshold == -100.0
    assert gym.config(env_id="Acrobot-v1", threshold=-150.0).threshold == -150.0
    assert gym.config(env_id="Pendulum-v1").threshold is None  # the registry has none


@pytest.mark.parametrize(
    ("env_id", "observes"),
    [
        ("FrozenLake-v1", "observes Discrete(16)"),  # a cell's number
        ("Blackjack-v1", "observes Tuple(Discrete(32)"),  # three numbers
        ("CarRacing-v3", "observes Box(0, 255, (96, 96, 3), uint8)"),  # images
    ],
)
def test_the_generic_recipe_refuses_observations_its_networks_cannot_read(env_id, observes):
    # before anything is built, in one line that says what it reads and where to go
    with pytest.raises(ValueError, match=rf"--env-id {env_id} {re.escape(observes)}.*flat vector"):
        gym.config(env_id=env_id)


def test_the_generic_recipe_learns_an_environment_it_was_not_written_for(tmp_path):
    # MountainCarContinuous: box actions, a reward only for reaching the flag; the
    # defaults find it (a greedy 90, the registry's threshold) within 50k steps.
    cfg = gym.config(env_id="MountainCarContinuous-v0", run_dir=tmp_path / "run",
                     total_frames=50_000, progress=False)  # fmt: skip
    summary = gym.train(cfg)
    assert summary["recipe"] == "gym" and summary["threshold"] == 90.0
    assert summary["best_eval_mean_return"] >= 90.0


def test_every_recipe_has_its_page_in_the_docs():
    # What adding a recipe takes: its module in rl_pg/recipes (NAMES finds it) and its
    # page, in the site's navigation.
    from pathlib import Path

    from rl_pg.recipes import NAMES

    docs = Path(__file__).parents[1] / "docs"
    nav = (docs.parent / "mkdocs.yml").read_text()
    for name in NAMES:
        assert (docs / "recipes" / f"{name}.md").is_file(), f"docs/recipes/{name}.md is missing"
        assert f"recipes/{name}.md" in nav, f"recipes/{name}.md is not in mkdocs.yml's nav"


def _picked_by() -> dict[str, str]:
    """The recipe index's "best.pt picked by" column: the metric each recipe's target
    is judged by, as the docs tell users."""
    from pathlib import Path

    index = (Path(__file__).parents[1] / "docs" / "recipes" / "index.md").read_text()
    head = next(line for line in index.splitlines() if line.startswith("| recipe |"))
    column = [cell.strip() for cell in head.strip("|").split("|")].index("best.pt picked by")
    rows = re.findall(r"^\| \[(\w[\w-]*)\]\(\1\.md\) \|(.*)$", index, flags=re.M)
    return {
        name: re.search(r"`(\w+)`", rest.split("|")[column - 1]).group(1) for name, rest in rows
    }


@pytest.mark.parametrize("name", NAMES)
def test_best_pt_is_picked_by_the_metric_the_recipes_target_names(name):
    # Two evaluations that disagree: the first has the better return, the second the
    # better value of the recipe's metric. The run keeps the second, unless its metric is
    # the return (then the two cannot disagree, and the first is kept).
    from rl_pg.evaluation import reported
    from rl_pg.training.checkpoints import RunState
    from rl_pg.training.metric import Metric

    recipe = load(name)
    metric = Metric.of(recipe.config)
    assert metric.key == _picked_by()[name]  # what the docs say it is
    assert metric.key in reported(recipe.eval_flags, recipe.eval_values)
    good, bad = (0.9, 0.1) if metric.mode == "max" else (0.1, 0.9)
    entries = {f"eval/{key}": 0.5 for key in reported(recipe.eval_flags, recipe.eval_values)}
    first = {**entries, "eval/mean_return": 10.0}
    second = {**entries, "eval/mean_return": 5.0}
    if metric.key != "mean_return":
        first[metric.logged], second[metric.logged] = bad, good
    state = RunState()
    for frames, evaluation in ((100, first), (200, second)):
        state.frames, state.last_eval = frames, evaluation
        state.is_best(metric)
    kept = 100 if metric.key == "mean_return" else 200
    assert state.best_at_frames == kept
    assert state.best(metric) == (10.0 if kept == 100 else good)
