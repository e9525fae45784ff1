"""Every benchmark script runs end to end on a tiny budget and writes its JSON.

The numbers themselves are machine-dependent: they are read, never asserted, here.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def _script(name):
    return importlib.import_module(name)


def test_returns(tmp_path):
    returns = _script("returns")
    out = returns.main(returns.Config(batch=8, steps=40, repeats=3, json_path=tmp_path / "r.json"))
    assert json.loads((tmp_path / "r.json").read_text()) == out
    assert out["reward_to_go_over_cumsum"] > 0 and out["machine"]["cores"] >= 1


def test_envs(tmp_path):
    envs = _script("envs")
    cfg = envs.Config(batch_sizes=[1, 8], seconds=0.02, repeats=1, json_path=tmp_path / "e.json")
    out = envs.main(cfg)
    medians = out["median_steps_per_s"]
    assert set(medians) == {
        "rl_pg GridWorldEnv",
        "rl_pg BanditEnv",
        "Python gridworld (gymnasium.Env, SyncVectorEnv)",
    }
    assert all(v > 0 for by_batch in medians.values() for v in by_batch.values())


def test_python_gridworld_matches_ours():
    """The Python contender is the same MDP as GridWorldEnv (same moves, rewards, ends)."""
    import torch

    from rl_pg.envs import GridWorldEnv

    envs = _script("envs")
    ours, theirs = GridWorldEnv(), envs.PythonGridWorld()
    generator = torch.Generator().manual_seed(0)
    td, (obs, _) = ours.reset(), theirs.reset(seed=0)
    for _ in range(300):
        action = int(torch.randint(4, (), generator=generator))
        td["action"] = torch.tensor(action)
        td, next_root = ours.step_and_maybe_reset(td)
        obs, reward, terminated, truncated, _ = theirs.step(action)
        assert td["next", "observation"].tolist() == obs.tolist()
        assert td["next", "reward"].item() == pytest.approx(reward)
        assert td["next", "terminated"].item() == terminated
        assert td["next", "truncated"].item() == truncated
        if terminated or truncated:
            obs, _ = theirs.reset()
        td = next_root


@pytest.mark.parametrize("script", ["throughput", "time_to_solve"])
def test_comparisons_with_sb3(script, tmp_path):
    pytest.importorskip("stable_baselines3")
    module = _script(script)
    if script == "throughput":
        cfg = module.Config(
            seconds=0.1,  # above the probe's frames: each contender is sized apart
            repeats=1,
            probe_frames=512,
            cartpole_envs=[32],  # the recipe's default: the stock-collector ratio reads it
            # LunarLander's contenders (the same code, another task) doubled this test's
            # time, to 2.5 min of the suite's 10: CartPole's alone are timed here.
            lunarlander_envs=[],
            json_path=tmp_path / "t.json",
        )
        out = module.main(cfg)
        assert out["ratios"] and all(r > 0 for r in out["ratios"].values())
        loop, floor = "rl_pg training loop (gymnasium)", "floor: gymnasium + MLP, no learning"
        assert f"CartPole x32 {loop} / CartPole x32 {floor}" in out["ratios"]
        plain = "the same algorithm in plain PyTorch (gymnasium)"
        assert f"CartPole x32 {loop} / CartPole x32 {plain}" in out["ratios"]
        kept = "the same in plain PyTorch, CleanRL's bookkeeping (gymnasium)"
        assert f"CartPole x32 {loop} / CartPole x32 {kept}" in out["ratios"]
        # The learning loops of a task and number of environments: the same frames.
        sized = out["frames_per_repeat"]
        assert len(set(sized.values())) > 2  # sized apart, or this would prove nothing
        task = "CartPole x32"
        assert sized[f"{task} {loop}"] == sized[f"{task} {plain}"] == sized[f"{task} {kept}"]
        assert out["rl_pg_over_stock_collector"] > 0
        assert out["ratio_intervals"].keys() == out["ratios"].keys()
        for name, (low, high) in out["ratio_intervals"].items():
            assert low <= out["ratios"][name] * (1 + 1e-9) and out["ratios"][name] <= high * (
                1 + 1e-9
            )
    else:
        for task, threshold in (("cartpole", 12.0), ("lunarlander", -1000.0)):
            cfg = module.Config(
                task=task,
                seeds=[0],
                eval_interval=512,
                eval_episodes=2,
                threshold=threshold,
                budget_frames=2_048,
                repeats=2 if task == "cartpole" else 1,
                json_path=tmp_path / f"{task}.json",
            )
            out = module.main(cfg)
            assert set(out["runs"]) == {"rl_pg", "sb3_a2c", "sb3_ppo"}
            runs = json.loads((tmp_path / f"{task}.json").read_text())["runs"]
            for run in runs.values():  # a seed's time: the median of its timed runs
                timed = run["0"]["train_wall_s_runs"]
                assert len(timed) == cfg.repeats and all(t > 0 for t in timed)
                assert run["0"]["train_wall_s"] == statistics.median(timed)
            if (
                task == "lunarlander"
            ):  # any return passes: every tool solves at its first evaluation
                assert all(run["0"]["solved_at_frames"] is not None for run in runs.values())


def test_ratio_intervals_resample_the_rounds_in_pairs():
    common = _script("common")
    drift = [1.0, 2.0, 0.5, 1.5, 0.7, 1.2]  # the machine's speed, round by round
    # One contender at 0.9x the other in every round: the drift they share is no
    # uncertainty of the ratio (resampled apart, it would span about 0.5 to 1.6).
    assert common.ratio_interval([0.9 * d for d in drift], drift) == [0.9, 0.9]
    rates = [1.0, 1.1, 0.9, 1.05, 0.95, 1.2, 0.8]
    low, high = common.ratio_interval(rates, [1.0] * 7)
    assert 0.8 <= low < statistics.median(rates) < high <= 1.2
    assert common.ratio_interval(rates, [1.0] * 7) == [low, high]  # seeded
    assert common.ratio_interval(rates, [1.0] * 7, level=0.5)[0] > low
    with pytest.raises(ValueError, match="equally long"):
        common.ratio_interval([1.0], [1.0, 2.0])


def test_the_plain_loop_with_bookkeeping_writes_what_a_cleanrl_script_writes(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    module = _script("throughput")
    loop = module.BookkeepingLoop(module.cartpole, 8, str(tmp_path))
    assert module._plain_rate(loop, 8 * loop.cfg.segment_length * 20) > 0  # 20 updates
    loop.writer.close()
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"charts/episodic_return", "losses/value_loss", "charts/SPS"} <= tags
    assert len(events.Scalars("losses/policy_loss")) == 20
    returns = [event.value for event in events.Scalars("charts/episodic_return")]
    assert returns and all(r >= 1 for r in returns)  # CartPole pays 1 a step


# SB3's tools run the same code but for the model: TRPO's is trained here, A2C's built
# (its short trainings hover to LunarLander's time limit: 15 s of evaluation here).
@pytest.mark.parametrize("tool", ["rl_pg", "sb3_trpo"])
def test_held_both_ways(tool, tmp_path, monkeypatch):
    pytest.importorskip("sb3_contrib" if tool == "sb3_trpo" else "stable_baselines3")
    module = _script("held_both_ways")
    if tool != "rl_pg":
        for other in module.ZOO:
            assert type(module.sb3_model(other, seed=0)).__name__ == other[4:].upper()
    cfg = module.Config(
        seeds=[0], tools=[tool], rl_pg_stored=[], budget_frames=1024, eval_interval=512,
        eval_episodes=2, final_episodes=10, json_path=tmp_path / "h.json",
    )  # fmt: skip
    out = module.main(cfg)
    (run,) = out["runs"][tool].values()
    assert run["best_at_frames"] >= 512 and out["held"] == {tool: "0/1"}
    assert set(run["greedy"]) == {"mean_return", "std_return"} == set(run["sampled"])
    # A second call continues the file: nothing is trained again.
    monkeypatch.setattr(module, "run_sb3", None)
    monkeypatch.setattr(module, "run_rl_pg", None)
    assert module.main(cfg)["runs"][tool][0] == run
    with pytest.raises(SystemExit, match="continue them with that budget"):
        module.main(module.Config(**{**vars(cfg), "budget_frames": 2048}))


def test_held_both_ways_reads_rl_pg_from_the_stored_runs(tmp_path):
    module = _script("held_both_ways")
    stored = Path(__file__).resolve().parents[1] / "results" / "lunarlander-seeds.json"
    runs = module.stored_rl_pg(stored, [0, 1])
    assert runs[0]["greedy"]["mean_return"] > 0 and set(runs) == {0, 1}
    # one row per store, named by it; the file keeps the stores' paths
    cfg = module.Config(seeds=[0, 1], tools=[], rl_pg_stored=[stored, stored],
                        json_path=tmp_path / "h.json")  # fmt: skip
    out = module.main(cfg)
    assert set(out["held"]) == {"rl_pg: lunarlander-seeds"}
    kept = json.loads((tmp_path / "h.json").read_text())
    assert kept["config"]["rl_pg_stored"] == [str(stored)] * 2
    with pytest.raises(SystemExit, match="no run evaluated both ways for seeds"):
        module.stored_rl_pg(stored, [0, 99])


def test_held_both_ways_summarises_tools_that_ran_different_seeds():
    module = _script("held_both_ways")

    def run(greedy, sampled):
        return {"greedy": {"mean_return": greedy}, "sampled": {"mean_return": sampled}}

    runs = {
        "rl_pg (stored)": {0: run(240, 210), 1: run(201, 123), 2: run(252, 231)},
        "sb3_a2c": {0: run(96, 87), 1: run(74, 38)},
        "sb3_trpo": {0: run(214, 205)},
    }
    out = module.summarise(runs, 200.0)
    assert out["held"] == {"rl_pg (stored)": "2/3", "sb3_a2c": "0/2", "sb3_trpo": "1/1"}


def test_time_to_solve_counts_unsolved_runs_as_never_solving():
    """A tool that spends its short budget without solving must not look fast."""
    module = _script("time_to_solve")

    def run(frames, wall):
        return {"solved_at_frames": frames, "train_wall_s": wall}

    runs = {
        "rl_pg": {0: run(500_000, 200.0), 1: run(None, 400.0), 2: run(700_000, 300.0)},
        "sb3_a2c": {0: run(None, 50.0), 1: run(None, 50.0), 2: run(100_000, 20.0)},
        "sb3_ppo": {0: run(400_000, 600.0), 1: run(600_000, 900.0), 2: run(800_000, 1200.0)},
    }
    out = module.summarise(runs, [0, 1, 2])
    assert out["medians"]["rl_pg"] == {
        "solved": "2/3",
        "median_frames": 700_000,
        "median_train_wall_s": 300.0,
    }
    assert out["medians"]["sb3_a2c"]["median_train_wall_s"] is None
    assert out["medians"]["sb3_a2c"]["median_frames"] is None
    assert out["rl_pg_over_sb3_wall"] == {"sb3_ppo": 300.0 / 900.0}
    assert out["rl_pg_over_best_sb3_wall"] == 300.0 / 900.0
    json.dumps(out, allow_nan=False)  # no Infinity in the results file


def test_contention(tmp_path):
    contention = _script("contention")
    cfg = contention.Config(frames=512, busy=1, repeats=1, json_path=tmp_path / "c.json")
    out = contention.main(cfg)
    assert set(out["slowdown"]) == {
        "rl_pg training loop (recipe)",
        "rl_pg, kernel on every numba thread (before)",
        "floor: SyncVectorEnv(32) + MLP",
    }
    assert out["rl_pg_slowdown_over_floor"] > 0


@pytest.mark.skipif(
    importlib.util.find_spec("metadrive") is None, reason="MetaDrive is not installed"
)
def test_evaluation(tmp_path):
    evaluation = _script("evaluation")
    cfg = evaluation.Config(episodes=2, horizon=20, repeats=1, json_path=tmp_path / "v.json")
    out = evaluation.main(cfg)
    assert json.loads((tmp_path / "v.json").read_text()) == out
    scores = out["scores"]  # the same scenarios and policy: the same score either way
    assert scores["EpisodeWorkers"]["mean_return"] == pytest.approx(
        scores["ParallelEnv"]["mean_return"]
    )
    assert out["parallel_env_over_workers"] > 0


@pytest.mark.skipif(
    importlib.util.find_spec("metadrive") is None, reason="MetaDrive is not installed"
)
def test_metadrive_maps(tmp_path):
    maps = _script("metadrive_maps")
    out = maps.main(maps.Config(scenarios=3, repeats=1, json_path=tmp_path / "m.json"))
    assert json.loads((tmp_path / "m.json").read_text()) == out
    assert [len(runs) for runs in out["runs"].values()] == [1, 1]
    kept = out["results"]["store_map"]
    assert out["gb_for_the_training_scenarios"] == pytest.approx(
        kept["mb_per_new_scenario"] * out["training_scenarios"] / 1024
    )
    for bad in (maps.Config(scenarios=2), maps.Config(scenarios=1001), maps.Config(repeats=0)):
        with pytest.raises(SystemExit, match=r"--scenarios|--repeats"):
            maps.main(replace(bad, json_path=tmp_path / "n.json"))
    assert not (tmp_path / "n.json").exists()


def test_command_times_whole_processes_through_both_entry_points(tmp_path, monkeypatch):
    command = _script("command")
    # The imports it times, each a process of its own, as cheap ones: what is tested is
    # how the script runs and reports them (the real ones cost 5 s of CPU each here).
    monkeypatch.setattr(command, "IMPORTS", {name: "import json" for name in command.IMPORTS})
    out = command.main(
        command.Config(commands=["--help"], repeats=1, json_path=tmp_path / "c.json")
    )
    assert json.loads((tmp_path / "c.json").read_text()) == out
    assert set(out["median_seconds"]) == {
        *command.IMPORTS,
        "rl-pg --help (entry: main)",
        "rl-pg --help (entry: run)",
    }
    assert all(len(times) == 1 and times[0] > 0 for times in out["seconds"].values())
    assert out["median_training_seconds"] == {}  # --help trains nothing
    assert set(out["run_over_main"]) == {"--help"}
    with pytest.raises(SystemExit, match="--repeats"):
        command.main(command.Config(repeats=0, json_path=tmp_path / "n.json"))
    with pytest.raises(SystemExit, match="no-such-command"):  # a failing command stops the run
        command.main(command.Config(commands=["no-such-command"], repeats=1,
                                    json_path=tmp_path / "n.json"))  # fmt: skip
    assert not (tmp_path / "n.json").exists()


def test_grad_stats(tmp_path):
    grad_stats = _script("grad_stats")
    # CartPole alone: LunarLander's runs are the same code at four times the cost
    cfg = grad_stats.Config(
        cartpole_frames=2_000, tasks=["CartPole"], intervals=[1], repeats=1,
        json_path=tmp_path / "g.json",
    )  # fmt: skip
    out = grad_stats.main(cfg)
    assert set(out["time_over_time_without"]) == {"CartPole --grad-stats 1"}
    assert all(v > 0 for v in out["time_over_time_without"].values())
    assert all(0 < v < 1 for v in out["measurement_share_of_training"].values())


def test_distributed(tmp_path, local_ray):
    """Ray against worker processes, the measured costs and the model they make."""
    module = _script("distributed")
    cfg = module.Config(
        recipe="cartpole", frames=1_024, repeats=1, cost_segments=2, predict=[8],
        json_path=tmp_path / "d.json",
    )  # fmt: skip
    out = module.main(cfg)
    assert set(out["median_frames_per_s"]) == {
        "1 worker, in the training process", "2 worker processes", "2 Ray workers",
        "1 Ray worker",
    }  # fmt: skip
    assert out["ratios"]["2 Ray workers / 2 worker processes"] > 0
    cost = out["costs"]
    assert cost["collect_s_per_segment"] > 0 and cost["learn_s_per_frame"] > 0
    # the model reproduces the run it was fitted on, and predicts the others
    assert out["predicted_frames_per_s"]["1"] == pytest.approx(
        out["median_frames_per_s"]["1 Ray worker"]
    )
    assert set(out["predicted_speedup"]) == {"1", "8"}
    assert out["model_checks"]["2 Ray workers"]["predicted"] > 0


ENV_REST = "around them (tensors, flags)"


def test_breakdown_times_the_segment_collectors_own_steps(tmp_path):
    """The breakdown takes SegmentCollector's lean path apart to time it: its batches
    must be the collector's, value for value, and the collector carries on from them."""
    from tensordict import assert_close

    from rl_pg.collectors import SegmentCollector
    from rl_pg.lean import lean_policy
    from rl_pg.recipes import load

    breakdown = _script("breakdown")
    recipe = load("cartpole")
    cfg = recipe.config(num_envs=4)
    envs = [recipe.make_env(cfg), recipe.make_env(cfg)]
    actor, _ = recipe.make_models(envs[0], cfg)
    timed, plain = (SegmentCollector(env, lean_policy(actor), frames_per_batch=32) for env in envs)
    for collector in (timed, plain):
        collector.set_seed(3)
    torch.manual_seed(0)
    expected = [plain.next() for _ in range(3)]
    torch.manual_seed(0)
    timer = breakdown._Timer()
    got = [breakdown.timed_segment(timed, timer) for _ in range(2)] + [timed.next()]
    for a, b in zip(got, expected, strict=True):
        assert_close(a, b, rtol=0, atol=0)
    assert set(timer.per_update(2)) == set(breakdown.PIECES[:3])
    out = breakdown.main(
        breakdown.Config(tasks=["cartpole:4"], rounds=1, updates=2, json_path=tmp_path / "b.json")
    )
    assert json.loads((tmp_path / "b.json").read_text()) == out
    for task, message in [("cartpole", "RECIPE:N"), ("pendulum:4", "categorical policy")]:
        with pytest.raises(ValueError, match=message):
            breakdown.main(breakdown.Config(tasks=[task], json_path=tmp_path / "x.json"))
    result = out["tasks"]["cartpole-x4"]
    parts = result["parts"]
    assert set(parts) == {*breakdown.PIECES, "total"}  # the repeated pass is not a piece
    assert parts["total"]["rl_pg"] == pytest.approx(
        sum(parts[p]["rl_pg"] for p in breakdown.PIECES)
    )
    repeated = result["loss_forward_repeated_at_once"]
    assert set(repeated) == {"rl_pg", "plain PyTorch"} and min(repeated.values()) > 0
    for who, ratio in result["loss_forward_in_loop_over_repeated"].items():
        assert ratio == pytest.approx(parts["update: loss forward"][who] / repeated[who])
    # The environments' piece split: its parts add up to it (one round: no medians
    # between them); the plain loop resets inside gymnasium's step.
    split = result["environments"]
    assert set(split) == {*breakdown.ENV_PARTS, breakdown.EPISODES}
    for who in ("rl_pg", "plain PyTorch"):
        inside = sum(split[part][who] for part in breakdown.ENV_PARTS)
        assert inside == pytest.approx(parts["collection: environments"][who])
        assert split["the vector env's step"][who] > 0 and split[ENV_REST][who] > 0
        assert split[breakdown.EPISODES][who] >= 0
    assert split["resets apart from the step"]["plain PyTorch"] == 0


def test_torchrl_compat_runs_the_tests_on_each_class(tmp_path):
    # A stand-in for pytorch/rl (a git repository with test/objectives) whose one test
    # passes on TorchRL's class only: TorchRL's run counts it passed, rl_pg's failed.
    import subprocess

    tests = tmp_path / "rl" / "test" / "objectives"
    tests.mkdir(parents=True)
    (tests / "test_which.py").write_text(
        "from torchrl.objectives.reinforce import ReinforceLoss\n\n\n"
        "def test_torchrls_own_class():\n"
        "    assert ReinforceLoss.__module__ == 'torchrl.objectives.reinforce'\n"
    )
    git = ["git", "-C", str(tmp_path / "rl"), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "tests"], check=True)
    compat = _script("torchrl_compat")
    cfg = compat.Config(
        repo=tmp_path / "rl", selection="test_which.py", json_path=tmp_path / "c.json"
    )
    out = compat.main(cfg)
    assert json.loads((tmp_path / "c.json").read_text()) == out
    assert out["results"]["torchrl.objectives.ReinforceLoss"] == {
        "tests": 1, "passed": 1, "failed": 0, "skipped": 0,
    }  # fmt: skip
    assert out["results"]["rl_pg.ReinforceLoss"] == {
        "tests": 1, "passed": 0, "failed": 1, "skipped": 0,
    }  # fmt: skip
    assert len(out["tests"]["commit"]) == 40
    # not a clone, or a revision it lacks: one line that says what to do
    for bad in (compat.Config(repo=tmp_path), compat.Config(repo=tmp_path / "rl", rev="nope")):
        with pytest.raises(SystemExit, match="not a git clone of pytorch/rl"):
            compat.main(bad)


def test_time_to_solve_refuses_to_pool_runs_that_solve_at_different_frames(monkeypatch):
    module = _script("time_to_solve")
    solved_at = iter([5_000, 10_000])
    monkeypatch.setattr(
        module,
        "run_rl_pg",
        lambda seed, cfg: {"solved_at_frames": next(solved_at), "train_wall_s": 1.0},
    )
    with pytest.raises(RuntimeError, match=r"seed 0: solved at 5000 frames.*--repeats 1"):
        module.main(module.Config(seeds=[0], tools=["rl_pg"], repeats=2))
    with pytest.raises(SystemExit, match="--repeats must be at least 1"):
        module.main(module.Config(repeats=0))


def test_natural_gradient(tmp_path):
    natural = _script("natural_gradient")
    out = natural.main(natural.Config(batches=2, repeats=2, json_path=tmp_path / "n.json"))
    assert set(out["ms_per_update"]) == set(natural.CONTENDERS)
    assert all(value > 0 for value in out["over_adam"].values())
    assert all(low <= high for low, high in out["over_adam_intervals"].values())


def test_loggers_times_each_backend_beside_the_csv_logs(tmp_path, monkeypatch):
    loggers = _script("loggers")
    short = ["--total-updates", "2", "--eval-interval", "100", "--eval-episodes", "1"]
    monkeypatch.setattr(loggers, "BACKENDS", {
        "csv only": short, "tensorboard": ["--tensorboard", *short],
    })  # fmt: skip
    out = loggers.main(loggers.Config(repeats=1, recipe="gridworld", out=tmp_path / "l.json"))
    assert set(out["training_over_csv_only"]) == {"csv only", "tensorboard"}
    assert out["training_over_csv_only"]["csv only"] == 1.0
    assert all(len(times) == 1 and times[0] > 0 for times in out["training_s"].values())
    assert json.loads((tmp_path / "l.json").read_text())["command_extra_s"]["csv only"] == 0


def test_mutation_makes_one_small_bug_at_a_time_outside_messages_and_docs():
    mutation = _script("mutation")
    source = '''def f(x, y):
    """Doc: 1 < 2."""
    if x < y and not y:
        raise ValueError(f"x={x + 1} is wrong")
    return -x * 2 + 0.5
'''
    found = {m.key for m in mutation.mutants(source)}  # none in the message, the docstring
    assert found == {
        "3:7 bool And->Or", "3:7 compare 0 Lt->LtE", "3:7 negate condition", "3:17 drop Not",
        "5:11 binary Add->Sub", "5:11 binary Mult->Div", "5:11 drop USub",
        "5:16 constant 2->3", "5:20 constant 0.5->1.0",
    }  # fmt: skip
    namespace = {}
    for mutant in mutation.mutants(source):
        exec(mutation.apply(source, mutant), namespace)  # each one compiles and differs
        exec(source, original := {})
        changed = [
            (x, y) for x in (-2, 0, 3) for y in (0, 1, 5)
            if _outcome(namespace["f"], x, y) != _outcome(original["f"], x, y)
        ]  # fmt: skip
        assert changed, mutant.key
    # each key is its own bug, even where two operations start at one place (5:11)
    applied = [mutation.apply(source, mutant) for mutant in mutation.mutants(source)]
    assert len(set(applied)) == len(applied)
    outcomes = {"3:7 bool And->Or": "killed", "5:16 constant 2->3": "survived", "4:1 x": "timeout"}
    results = {"modules": {"rl_pg.m": {"total": 3, "mutants": outcomes}}}
    mutation._summarise(results)
    assert results["summary"]["rl_pg.m"] == {"mutants": 3, "scored": 3, "killed": 2,
                                             "score": 2 / 3}  # fmt: skip
    assert results["modules"]["rl_pg.m"]["survivors"] == ["5:16 constant 2->3"]


def test_the_stored_mutation_scores_are_of_every_core_module_as_it_is():
    # A module edited since it was scored shows a score its code no longer has.
    mutation = _script("mutation")
    stored = json.loads(mutation.RESULTS.read_text())["modules"]
    assert sorted(stored) == sorted(mutation.TARGETS)
    stale = [
        name
        for name, entry in stored.items()
        if entry["source"]
        != mutation.source_digest((mutation.REPO / (name.replace(".", "/") + ".py")).read_text())
    ]
    assert stale == [], f"rescore them: python benchmarks/mutation.py --modules {stale}"


def test_mutation_runs_on_different_modules_share_the_results_file(tmp_path, monkeypatch):
    mutation = _script("mutation")
    monkeypatch.setattr(mutation, "RESULTS", tmp_path / "mutation.json")
    first = {"modules": {"rl_pg.a": {"total": 1, "mutants": {"1:1 x": "killed"}}}}
    second = {"modules": {"rl_pg.b": {"total": 1, "mutants": {"2:2 y": "survived"}}}}
    mutation._save(first, ["rl_pg.a"])
    mutation._save(second, ["rl_pg.b"])  # a run that started before the first saved
    first["modules"]["rl_pg.a"]["mutants"]["1:1 x"] = "survived"  # its module again
    mutation._save(first, ["rl_pg.a"])
    stored = json.loads((tmp_path / "mutation.json").read_text())
    assert sorted(stored["modules"]) == ["rl_pg.a", "rl_pg.b"]
    assert (stored["killed"], stored["scored"]) == (0, 2)


def _outcome(f, *args):
    try:
        return f(*args)
    except ValueError:
        return "raised"
