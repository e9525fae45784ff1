"""MetaDrive offline and headless: the environment builder and the recipe, on the real simulator.

MetaDrive runs one engine per process, so every test closes what it opens.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import hide_module
from PIL import Image

from rl_pg.app import cli, evaluate, play
from rl_pg.envs import metadrive as md
from rl_pg.envs.metadrive_assets import assets_pull_skipped
from rl_pg.recipes import load
from rl_pg.training import read_run
from rl_pg.training.seeds import evaluation_seed

needs_metadrive = pytest.mark.skipif(
    importlib.util.find_spec("metadrive") is None,
    reason="MetaDrive is not installed (Python >= 3.12 has no MetaDrive package)",
)
recipe = load("metadrive")


@pytest.fixture
def scenarios():
    """A MetaDriveScenarios over 5 scenarios, closed afterwards."""
    opened = []

    def make(**kwargs):
        kwargs.setdefault("horizon", 30)
        env = md.MetaDriveScenarios(kwargs.pop("start_seed", 0), kwargs.pop("num", 5), **kwargs)
        opened.append(env)
        return env

    yield make
    for env in opened:
        env.close()


def _site_packages_metadrive() -> Path:
    return Path(importlib.util.find_spec("metadrive").origin).parent


@needs_metadrive
def test_resets_offline_without_assets_and_writes_nothing_into_metadrive(scenarios):
    from metadrive.engine.base_engine import BaseEngine

    package = _site_packages_metadrive()
    if (package / "assets").exists():
        pytest.skip("MetaDrive's assets are installed here: nothing to skip")
    before = sorted(p.name for p in package.iterdir())
    pull = BaseEngine.__dict__["try_pull_asset"]
    env = scenarios()
    observation, info = env.reset(seed=0)
    observation, _, _, _, info = env.step(np.array([0.0, 1.0]))
    assert observation.shape == (259,) and 0.0 <= observation.min() <= observation.max() <= 1.0
    assert {"route_completion", "arrive_dest", "crash", "out_of_road"} <= set(info)
    assert sorted(p.name for p in package.iterdir()) == before  # no assets, lock or zip
    assert BaseEngine.__dict__["try_pull_asset"] is pull  # only skipped while starting


@needs_metadrive
def test_ctrl_c_inside_a_simulator_step_reaches_the_training_loops_handler(scenarios):
    """Panda3D defers a SIGINT that falls inside its frame and raises KeyboardInterrupt
    after it, past the caller's handler; the environment leaves SIGINT to the caller."""
    import os
    import signal

    import direct.task.Task as panda_tasks

    from rl_pg.training.interrupt import InterruptRequest

    env = scenarios()
    env.reset(seed=0)

    def ctrl_c_inside_the_frame(task):
        os.kill(os.getpid(), signal.SIGINT)
        return task.done

    def step_with_ctrl_c():
        env.env.engine.taskMgr.add(ctrl_c_inside_the_frame, "ctrl-c")
        with InterruptRequest() as interrupt:
            env.step(np.array([0.0, 1.0]))  # the update in progress ends normally
        return interrupt.requested

    assert panda_tasks.signal is None
    assert step_with_ctrl_c()
    panda_tasks.signal = signal  # negative control: Panda3D's own handling
    try:
        with pytest.raises(KeyboardInterrupt):
            step_with_ctrl_c()
    finally:
        panda_tasks.signal = None


@needs_metadrive
def test_episode_speed_is_the_average_speed_over_the_episode_in_km_h(scenarios):
    env = scenarios(horizon=40)
    for episode in range(2):  # the average starts afresh at each reset
        _, info = env.reset(seed=episode)
        assert info["episode_speed"] == 0.0
        speeds = []
        for _ in range(25):
            _, _, terminated, truncated, info = env.step(np.array([0.0, 1.0]))
            speeds.append(3.6 * info["velocity"])
            assert info["episode_speed"] == pytest.approx(np.mean(speeds))
            if terminated or truncated:
                break
        assert 5.0 < info["episode_speed"] < max(speeds)  # accelerating from standstill


@needs_metadrive
@pytest.mark.parametrize(
    ("assets_present", "config", "skipped"),
    [
        (False, {}, True),
        (True, {}, False),  # a user who pulled the assets: MetaDrive checks their version
        (False, "camera", False),  # 3-D camera observations need them
    ],
)
def test_asset_pull_is_skipped_only_headless_and_without_assets(
    assets_present, config, skipped, monkeypatch, tmp_path
):
    from metadrive.engine.asset_loader import AssetLoader
    from metadrive.engine.base_engine import BaseEngine
    from metadrive.envs import MetaDriveEnv

    if config == "camera":
        from metadrive.component.sensors.rgb_camera import RGBCamera

        config = {
            "image_observation": True,
            "sensors": {"rgb_camera": (RGBCamera, 84, 84)},
            "vehicle_config": {"image_source": "rgb_camera"},
        }
    monkeypatch.setattr(AssetLoader, "asset_path", tmp_path / ("assets" if assets_present else "x"))
    (tmp_path / "assets").mkdir()
    env = MetaDriveEnv(config)  # no engine until the first reset
    pull = BaseEngine.try_pull_asset
    with assets_pull_skipped(env):
        assert (BaseEngine.try_pull_asset is not pull) == skipped
    assert BaseEngine.try_pull_asset is pull


@needs_metadrive
def test_seeds_anywhere_map_into_the_scenarios_reproducibly(scenarios):
    env = scenarios(start_seed=1000, num=5)
    seen = []
    for _ in range(2):
        _, info = env.reset(seed=2**31 + 7)  # far outside 1000-1004
        picks = [info["scenario"]] + [env.reset()[1]["scenario"] for _ in range(5)]
        seen.append(picks)
    assert seen[0] == seen[1]
    assert set(seen[0]) <= set(range(1000, 1005))


@needs_metadrive
def test_sequential_order_visits_every_scenario_once(scenarios):
    env = scenarios(start_seed=10, num=4, order="sequential")
    _, info = env.reset(seed=6)
    picks = [info["scenario"]] + [env.reset()[1]["scenario"] for _ in range(3)]
    assert picks == [12, 13, 10, 11]
    assert env.reset(options={"scenario": 11})[1]["scenario"] == 11
    with pytest.raises(
        ValueError, match="Scenario 14 is not in this environment's scenarios 10-13"
    ):
        env.reset(options={"scenario": 14})


@needs_metadrive
def test_time_limit_truncates(scenarios):
    env = scenarios(horizon=12)
    env.reset(seed=0)
    for step in range(1, 13):  # brake and stand still: nothing else ends the episode
        _, _, terminated, truncated, info = env.step(np.array([0.0, -1.0]))
        assert not terminated
        assert truncated == (step == 12)
    assert info["max_step"]


@needs_metadrive
def test_a_second_engine_in_one_process_is_refused_clearly(scenarios):
    first, second = scenarios(), scenarios()
    first.reset(seed=0)
    with pytest.raises(RuntimeError, match="one per process"):
        second.reset(seed=0)


@needs_metadrive
def test_registered_ids_make_through_gymnasium():
    import gymnasium as gym

    env = gym.make("MetaDrive-validation-v0", horizon=5)
    try:
        assert env.unwrapped.config["start_seed"] == 0
        assert env.unwrapped.config["num_scenarios"] == 1000
        _, info = env.reset(seed=123, options={})  # gymnasium 1.x passes options
        assert 0 <= info["scenario"] < 1000
    finally:
        env.close()
    assert gym.spec(md.HELD_OUT).kwargs == {"start_seed": 10_000, "num_scenarios": 100}
    assert gym.spec(md.SELECTION).kwargs == {"start_seed": 10_100, "num_scenarios": 100}


@needs_metadrive
def test_checkpoints_are_picked_and_scored_on_scenarios_apart_from_each_other_and_training():
    def scenarios(env_id):
        start, count = md.SCENARIO_SETS[env_id]
        return set(range(start, start + count))

    training = set().union(*(scenarios(i) for i in md.SCENARIO_SETS if not i.startswith("rl_pg/")))
    selection, held_out = scenarios(md.SELECTION), scenarios(md.HELD_OUT)
    assert not selection & held_out and not (selection | held_out) & training
    # The recipe picks on the selection scenarios and scores on the held-out ones (the
    # environments are built in processes of their own: read what they will build).
    # Each evaluation worker plays its own part of the set: together, each scenario once.
    cfg = recipe.config(workers=3)
    for make, env_id in ((recipe.make_eval_env, md.SELECTION), (recipe.test_env, md.HELD_OUT)):
        env = make(cfg)
        assert env.is_closed  # nothing started
        assert len(env.make_envs) == 3
        assert {make.args for make in env.make_envs} == {(env_id,)}
        parts = [make.keywords["scenarios"] for make in env.make_envs]
        assert sorted(k for part in parts for k in part) == sorted(scenarios(env_id))


@needs_metadrive
def test_a_scenario_is_the_same_whichever_part_of_its_set_it_is_played_from(scenarios):
    def drive(env, **reset):
        observations = [env.reset(**reset)[0]]
        for step in range(40):  # steer a little, full throttle: the road and traffic move
            observations.append(env.step(np.array([0.3 * (step % 3 - 1), 1.0]))[0])
        env.close()
        return np.stack(observations)

    whole = drive(scenarios(start_seed=10_000, num=100), options={"scenario": 10_067})
    part = md.split_scenarios(md.HELD_OUT, 3)[2]  # range(10067, 10100)
    alone = drive(scenarios(start_seed=part.start, num=len(part), order="sequential"), seed=0)
    np.testing.assert_allclose(whole, alone, atol=1e-5)
    with pytest.raises(ValueError, match="consecutive scenarios of rl_pg/MetaDrive-heldout-v0"):
        md.metadrive_env(md.HELD_OUT, scenarios=range(10_090, 10_110))
    with pytest.raises(ValueError, match="cannot be cut into 101 parts"):
        md.split_scenarios(md.HELD_OUT, 101)
    with pytest.raises(ValueError, match="its first 101 cannot be cut"):
        md.split_scenarios(md.HELD_OUT, 2, count=101)


@needs_metadrive
def test_torchrl_env_tutorial_action_table_reaches_metadrive_as_fed():
    env = md.metadrive_env(md.HELD_OUT, horizon=5)
    try:
        assert env.action_spec.space.n == 9
        env.set_seed(0)
        td = env.reset()
        td["action"] = torch.tensor(1)  # the tutorial's (+1, 0): steering +1, throttle 0
        td = env.step(td)
        raw = env.base_env._env.unwrapped.agent.last_current_action[-1]  # [steering, throttle]
        assert list(np.round(raw, 3)) == [1.0, 0.0]
        for key in (*md.METADRIVE_VALUES, *md.METADRIVE_FLAGS):
            assert ("next", key) in td.keys(include_nested=True)
    finally:
        env.close()


@needs_metadrive
@pytest.mark.parametrize(
    ("flags", "shapes"),
    [
        ({}, [(259, 128), (128, 9)]),  # the tutorial's network
        ({"layers": 2, "hidden": 16}, [(259, 16), (16, 16), (16, 9)]),
    ],
)
def test_network_has_the_configured_hidden_layers(flags, shapes):
    env = md.metadrive_env(md.HELD_OUT, horizon=5)
    try:
        actor, critic = recipe.make_models(env, recipe.config(**flags))
    finally:
        env.close()
    for module, out in ((actor, 9), (critic, 1)):
        linears = [m for m in module.modules() if isinstance(m, torch.nn.Linear)]
        *trunk, (width, _) = shapes
        assert [(m.in_features, m.out_features) for m in linears] == [*trunk, (width, out)]


def test_runs_stored_before_the_failure_penalty_resume_with_metadrives_own():
    from rl_pg.training.config import config_dict

    stored = config_dict(recipe.config(seed=3))
    assert stored["failure_penalty"] == 50.0  # the recipe's default
    del stored["failure_penalty"]  # as a version without the field wrote it
    assert recipe.config.from_stored(stored).failure_penalty == 5.0
    assert recipe.config.from_stored(stored, failure_penalty=50.0).failure_penalty == 50.0


def test_runs_stored_before_the_selection_metric_keep_their_best_return():
    from rl_pg.training.config import config_dict

    stored = config_dict(recipe.config())
    del stored["select_by"]  # as a version that picked best.pt by the return wrote it
    assert recipe.config.from_stored(stored).select_by == "mean_return"
    assert recipe.config().select_by == "arrive_dest_rate"


@needs_metadrive
def test_training_reward_flags_shape_the_training_reward_and_no_evaluation():
    from rl_pg.evaluation import evaluate as score

    plain, lateral = (  # MetaDrive's own penalty of 5, not the recipe's default
        recipe.config(horizon=40, workers=1, lateral_reward=on, failure_penalty=5.0)
        for on in (False, True)
    )
    penalised = recipe.config(horizon=40, workers=1, lateral_reward=True, failure_penalty=20.0)
    # A driver that steers hard left (action 0) from its lane's centre off the road.
    env = recipe.make_env(plain)
    try:
        actor, _ = recipe.make_models(env, plain)
    finally:
        env.close()
    last = [m for m in actor.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([100.0] + [0.0] * 8))

    def rewards(env, seed=None):
        try:
            if seed is not None:  # random order: seeded for the same scenario
                env.set_seed(seed)
            rollout = env.rollout(40, actor, break_when_any_done=True)
            return rollout["next", "reward"].flatten().double()
        finally:
            env.close()

    shaped, default, punished = (
        rewards(recipe.make_env(cfg), seed=0) for cfg in (lateral, plain, penalised)
    )
    assert len(shaped) == len(default) < 40 and shaped[-1] == default[-1] == -5.0  # off road
    assert shaped[0].item() == pytest.approx(default[0].item(), rel=1e-2)  # lane's centre
    assert (shaped - default).abs().max() > 0.05  # progress pays less away from it
    # The same episode; only leaving the road costs more.
    assert punished[-1] == -20.0 and torch.equal(punished[:-1], shaped[:-1])
    # The evaluation plays the first held-out scenario, scored by MetaDrive's reward.
    held_out = partial(md.metadrive_env, md.HELD_OUT, order="sequential", horizon=40)
    default = rewards(held_out()).sum().item()
    assert rewards(held_out(config={"use_lateral_reward": True})).sum().item() != default
    env = recipe.make_test_env(penalised)
    try:
        assert score(actor, env, episodes=1)["mean_return"] == pytest.approx(default)
    finally:
        env.close()


def test_missing_metadrive_says_how_to_install(monkeypatch, tmp_path):
    hide_module(monkeypatch, "metadrive")
    install = r'pip install -c constraints.txt "rl_pg\[metadrive\]"'
    with pytest.raises(ModuleNotFoundError, match=install):
        md.require_metadrive()
    with pytest.raises(ModuleNotFoundError, match=install):
        recipe.train(recipe.config(run_dir=tmp_path / "run"))
    assert not (tmp_path / "run").exists()
    monkeypatch.setattr(sys, "version_info", (3, 12, 0))
    with pytest.raises(ModuleNotFoundError, match=r"needs Python < 3.12.*rl-pg train highway"):
        md.require_metadrive()


@needs_metadrive
def test_recipe_trains_evaluates_in_its_own_process_and_plays_a_gif(tmp_path):
    from metadrive.engine.base_engine import BaseEngine

    run = tmp_path / "run"
    cfg = recipe.config(
        run_dir=run, workers=1, horizon=40, episodes_per_batch=2, total_updates=1,
        eval_episodes=2, progress=False,
    )  # fmt: skip
    summary = recipe.train(cfg)
    assert summary["updates"] == 1
    rates = {k: summary[k] for k in ("arrive_dest_rate", "crash_rate", "out_of_road_rate",
                                     "max_step_rate")}  # fmt: skip
    # shares of 2 episodes, each of which ended some way; 40 steps (4 s) arrive nowhere
    assert all(rate * 2 == round(rate * 2) for rate in rates.values()), rates
    assert sum(rates.values()) >= 1.0 and rates["arrive_dest_rate"] == 0.0
    # best.pt is picked by success, the target's metric, not by the return
    assert summary["select_by"] == "arrive_dest_rate"
    assert summary["best_eval_value"] == rates["arrive_dest_rate"]
    assert read_run(run, which="best")["state"]["best_eval"]["eval/arrive_dest_rate"] == 0.0
    assert 0.0 < summary["eval_mean_route_completion"] < 0.5
    assert BaseEngine.singleton is None  # training closed its engine
    # The deployed agent standardises what it sees as it did in training.
    counts = [v for k, v in read_run(run)["loss"].items() if k.endswith("stats.count")]
    assert counts and all(count == summary["frames"] for count in counts)
    result = evaluate.main(evaluate.Args(run=run, episodes=1))
    assert 0.0 < result["mean_route_completion"] < 0.5 and result["arrive_dest_rate"] == 0.0
    assert result["mean_episode_speed"] >= 0.0
    assert "on" not in result
    on_training = evaluate.main(evaluate.Args(run=run, episodes=1, on="training"))
    assert on_training["on"] == "training" and 0.0 <= on_training["mean_route_completion"] <= 1.0
    # On the selection scenarios, with the training's seed: the run's last evaluation.
    again = evaluate.main(
        evaluate.Args(run=run, checkpoint="last", episodes=2, seed=evaluation_seed(0),
                      on="selection")
    )  # fmt: skip
    assert again["mean_return"] == pytest.approx(summary["eval_mean_return"])
    assert BaseEngine.singleton is None
    gif = tmp_path / "drive.gif"
    returns = play.main(play.Args(run=run, episodes=1, gif=gif))
    assert len(returns) == 1
    with Image.open(gif) as image:
        assert image.n_frames >= 2 and image.size == (400, 400)
    assert BaseEngine.singleton is None
    assert json.loads((run / "config.json").read_text())["actions"] == "tutorial"


@needs_metadrive
def test_references_measure_random_and_full_throttle(tmp_path, capsys):
    # As a user runs it: one line per driver, then where the results were written, and
    # the file holds the same results with the config and the machine they ran on.
    run = tmp_path / "references"
    cli.main([
        "train", "metadrive", "--references", "--eval-episodes", "2", "--horizon", "30",
        "--run-dir", str(run),
    ])  # fmt: skip
    *lines, written = capsys.readouterr().out.strip().splitlines()
    assert written == f"written to {run / 'references.json'}"
    results = {}
    for line in lines:
        name, _, values = line.partition(": ")
        results[name] = {k: float(v) for k, v in (item.split() for item in values.split(", "))}
    assert set(results) == {"random", "full throttle"}
    for result in results.values():
        assert 0.0 <= result["mean_route_completion"] <= 1.0
        assert result["mean_length"] <= 30
    # Full throttle drives further along the route than a random driver in 30 steps.
    assert (
        results["full throttle"]["mean_route_completion"]
        > results["random"]["mean_route_completion"]
    )
    stored = json.loads((run / "references.json").read_text())
    assert stored["config"]["horizon"] == 30 and stored["config"]["eval_episodes"] == 2
    assert stored["session"]["machine"]["cores"] >= 1
    for name, result in results.items():
        assert result == pytest.approx(stored["drivers"][name], abs=5e-4)


@needs_metadrive
@pytest.mark.parametrize("bounded", ["normal", "beta"])
def test_continuous_actions_train_and_evaluate(tmp_path, bounded):
    # MetaDrive's own [steering, throttle] in [-1, 1]^2, from a Gaussian or a Beta.
    run = tmp_path / "run"
    cfg = recipe.config(
        run_dir=run, workers=1, horizon=6, actions="continuous", bounded=bounded,
        segment_length=16, total_updates=2, eval_episodes=2, progress=False, grad_stats=1,
    )  # fmt: skip
    summary = recipe.train(cfg)
    assert summary["updates"] == 2
    actor, _ = recipe.make_models(md.metadrive_env(md.HELD_OUT, actions=None, horizon=5), cfg)
    assert type(actor.module[-1]).__name__ != "Categorical"
    result = evaluate.main(evaluate.Args(run=run, episodes=1))
    assert 0.0 <= result["mean_route_completion"] <= 1.0
    scalars = run / "logs" / "csv" / "scalars" / "grad" / "gae"
    assert (scalars / "noise_scale.csv").is_file()


def test_bounded_needs_continuous_actions():
    with pytest.raises(ValueError, match="add --actions continuous"):
        recipe.config(bounded="beta")


def test_evaluations_never_count_a_scenario_twice():
    # Checked when the config is made, not 125k steps into training.
    with pytest.raises(ValueError, match=r"--eval-episodes 101: .* Ask for at most 100"):
        recipe.config(eval_episodes=101)
    recipe.config(eval_episodes=100)


@needs_metadrive
def test_rl_pg_evaluate_refuses_more_episodes_than_held_out_scenarios():
    from rl_pg.recipes.metadrive import make_test_env

    for workers in (1, 3):
        env = make_test_env(recipe.config(workers=workers))
        assert env.distinct_episodes == 100 and env.is_closed  # nothing started yet
