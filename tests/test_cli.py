"""The ``rl-pg`` command as users run it: in subprocesses, from a checkout and from a wheel."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
import textwrap
import time
from pathlib import Path

import pytest
import torch
from conftest import hide_module

from rl_pg.app.cli import main
from rl_pg.app.flags import field_docs
from rl_pg.recipes import NAMES, load
from rl_pg.training import TrainConfig

REPO = Path(__file__).resolve().parents[1]
QUICK = ["--total-updates", "2", "--eval-interval", "100", "--eval-episodes", "1"]


def rl_pg(*args: str, cwd: Path, python: str = sys.executable, **kwargs):
    """``rl-pg ARGS`` (the installed entry point: ``python -m rl_pg.app``)."""
    return subprocess.run(
        [python, "-m", "rl_pg.app", *args], cwd=cwd, capture_output=True, text=True, **kwargs
    )


def in_process(*args: str, capsys) -> tuple[int, str, str]:
    """``rl-pg ARGS`` in this process: (exit status, stdout, stderr)."""
    try:
        main(list(args))
        status = 0
    except SystemExit as stop:
        status = stop.code if isinstance(stop.code, int) else 1
        if isinstance(stop.code, str):
            print(stop.code, file=sys.stderr)  # what Python prints for sys.exit("...")
    out, err = capsys.readouterr()
    return status, out, err


def test_list_names_every_recipe_with_what_it_trains(capsys):
    status, out, _ = in_process("list", capsys=capsys)
    assert status == 0
    lines = out.splitlines()
    assert [line.split()[0] for line in lines] == list(NAMES)
    assert "CartPole-v1" in lines[NAMES.index("cartpole")]
    # each description whole: a sentence that ends, however many lines its docstring takes
    assert all(line.rstrip().endswith((".", ")")) for line in lines), out
    assert "held-out scenarios" in lines[NAMES.index("metadrive")]


def test_train_resume_and_play_a_run_by_its_directory_alone(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    status, out, err = in_process(
        "train", "gridworld", "--run-dir", "run", "--lr", "0.05", *QUICK, capsys=capsys
    )
    assert status == 0, err
    assert out.startswith("gridworld, seed 0: ")
    # A fresh process, which knows nothing of the run but its directory.
    resumed = rl_pg("resume", "run", "--total-updates", "4", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    # only its own words: a stored pair read back as a list once made tyro warn
    assert "Warning" not in resumed.stderr, resumed.stderr
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert (config["lr"], config["total_updates"]) == (0.05, 4)  # stored, then changed
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["updates"] == 4
    status, out, err = in_process("play", "run", "--episodes", "2", capsys=capsys)
    assert status == 0, err
    assert "mean return" in out


def _with_cell_policy(saved: dict, actions: list[int]) -> dict:
    """``saved`` with a gridworld actor that takes ``actions[cell]`` in each cell."""
    weights = dict(saved["loss"])
    first, last = "actor_network.module.0.module.0", "actor_network.module.0.module.2"
    hidden, cells = weights[f"{first}.weight"].shape
    read = torch.zeros(hidden, cells)
    read[:cells] = torch.eye(cells)  # unit c fires in cell c alone
    choose = torch.zeros(weights[f"{last}.weight"].shape)
    choose[actions, range(cells)] = 20.0
    weights.update({
        f"{first}.weight": read, f"{first}.bias": torch.zeros(hidden),
        f"{last}.weight": choose, f"{last}.bias": torch.zeros(len(choose)),
    })  # fmt: skip
    return {**saved, "loss": weights}


def test_every_command_deploys_the_best_checkpoint_unless_told_otherwise(tmp_path, capsys):
    """best.pt walks the shortest path; checkpoint.pt repeats one move until the time
    limit. What play, evaluate and Agent.load deploy from a run directory shows which."""
    from collections import deque

    from rl_pg.app import Agent
    from rl_pg.checkpoint import load_checkpoint, save_checkpoint
    from rl_pg.envs import GridWorldEnv

    run = tmp_path / "run"
    assert in_process("train", "gridworld", "--run-dir", str(run), *QUICK, capsys=capsys)[0] == 0
    env = GridWorldEnv()
    towards = {env.goal: 0}  # each cell's first move on a shortest path to the goal
    queue = deque([env.goal])
    while queue:
        cell = queue.popleft()
        for before in range(env.next_cell.shape[0]):
            for move, after in enumerate(env.next_cell[before].tolist()):
                if after == cell and before not in towards and before != env.pit:
                    towards[before] = move
                    queue.append(before)
    shortest = [towards.get(cell, 0) for cell in range(env.next_cell.shape[0])]
    saved = load_checkpoint(run / "best.pt")
    save_checkpoint(_with_cell_policy(saved, shortest), run / "best.pt")
    other = (shortest[env.start] + 1) % 4  # any one move repeated stays clear of the goal
    save_checkpoint(_with_cell_policy(saved, [other] * len(shortest)), run / "checkpoint.pt")
    best, last = f"{env.optimal_return:.2f}", "-10.00"

    def played(*args):
        status, out, err = in_process("play", str(run), "--episodes", "1", *args, capsys=capsys)
        assert status == 0, err
        return out.splitlines()[-1]

    assert played() == f"mean return {best} over 1 episodes"
    assert played("--checkpoint", "last") == f"mean return {last} over 1 episodes"
    status, out, _ = in_process("evaluate", str(run), "--episodes", "1", capsys=capsys)
    assert status == 0 and f"return {best} " in out, out
    agent = Agent.load(run)
    start = env.reset()["observation"]
    assert agent.act(start) == shortest[env.start]
    assert Agent.load(run, checkpoint="last").act(start) == other


def test_resume_refuses_what_is_not_safe_to_change(tmp_path, capsys):
    run = str(tmp_path / "run")
    assert in_process("train", "gridworld", "--run-dir", run, *QUICK, capsys=capsys)[0] == 0
    status, _, err = in_process("resume", run, "--total-updates", "4", "--gamma", "0.5",
                                capsys=capsys)  # fmt: skip
    assert status == 1 and "gamma: 1.0 -> 0.5" in err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["train", "tetris"], "No recipe called 'tetris'. The built-in recipes are bandit"),
        (["resume", "nowhere"], "rl-pg: nowhere does not exist: give a run directory"),
        (["play", "nowhere"], "rl-pg: nowhere does not exist: give a run directory"),
        (["resume", "."], "rl-pg: . holds no checkpoint.pt: not a run directory"),
        (["play", "."], "rl-pg: . holds no best.pt: not a run directory"),
        (["play", "cartpole"], "rl-pg: cartpole is no file or folder here, but a recipe's"),
        (["train", "metadrive"], "MetaDrive is not installed"),
        (["report", "."], "rl-pg report: . has no summary.json: not a run directory"),
    ],
)
def test_mistakes_get_one_line(tmp_path, args, message, capsys, monkeypatch):
    if args[-1] == "metadrive":  # as on a machine without it
        hide_module(monkeypatch, "metadrive")
    monkeypatch.chdir(tmp_path)
    status, _, err = in_process(*args, capsys=capsys)
    assert status == 1 and message in err


def _gridworld_runs(tmp_path, capsys) -> list[str]:
    """Two short gridworld runs (seeds 0 and 1) trained through the command line."""
    runs = [str(tmp_path / f"seed{seed}") for seed in (0, 1)]
    for seed, run in enumerate(runs):
        status, _, err = in_process(
            "train", "gridworld", "--seed", str(seed), "--run-dir", run, *QUICK, capsys=capsys
        )
        assert status == 0, err
    return runs


def test_report_tabulates_runs_with_their_best_checkpoints_evaluations(tmp_path, capsys):
    runs = _gridworld_runs(tmp_path, capsys)
    assert in_process("evaluate", runs[0], "--episodes", "3", capsys=capsys)[0] == 0
    evaluated = json.loads((tmp_path / "seed0" / "evaluations.jsonl").read_text())

    figure = tmp_path / "curves.png"
    status, out, err = in_process("report", *runs, "--plot", str(figure), capsys=capsys)
    assert status == 0, err
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| seed")]
    assert [(row[0], row[1], row[2]) for row in rows] == [
        ("| seed0", "gridworld", "0"),
        ("| seed1", "gridworld", "1"),
    ]
    greedy = f"{evaluated['mean_return']:.2f} ± {evaluated['std_return']:.2f} (3)"
    assert rows[0][-2:] == [greedy, "— |"]  # no sampled evaluation yet
    assert rows[1][-2:] == ["—", "— |"]
    assert figure.read_bytes()[:4] == b"\x89PNG"
    # A result on another of a recipe's test sets (`--on`) does not describe best.pt.
    with open(tmp_path / "seed0" / "evaluations.jsonl", "a") as file:
        file.write(json.dumps({**evaluated, "on": "training", "mean_return": -1.0}) + "\n")
    status, out, err = in_process("report", runs[0], capsys=capsys)
    assert status == 0 and greedy in out, err
    status, _, err = in_process("evaluate", runs[0], "--on", "training", capsys=capsys)
    assert status == 1 and "'gridworld' has no test set 'training'" in err

    status, _, err = in_process("report", runs[0], "--plot", str(figure), "--metric", "eval/nope",
                                capsys=capsys)  # fmt: skip
    assert status == 1 and "logged no 'eval/nope'" in err

    status, out, _ = in_process("evaluate", runs[0], "--episodes", "3", "--sample",
                                "--action-stats", capsys=capsys)  # fmt: skip
    assert status == 0 and "actions played (index: share of steps): 0:" in out
    assert "action_switch_rate" in out and "mean_entropy" in out
    record = json.loads((tmp_path / "seed0" / "evaluations.jsonl").read_text().splitlines()[-1])
    assert len(record["action_shares"]) == 4 and sum(record["action_shares"]) == pytest.approx(1)
    status, out, err = in_process("report", *runs, capsys=capsys)  # reads that record too
    assert status == 0, err


def test_a_mistake_in_a_subprocess_is_one_line_without_traceback(tmp_path):
    result = rl_pg("play", "nowhere", cwd=tmp_path)
    assert result.returncode == 1
    assert (
        result.stderr
        == "rl-pg: nowhere does not exist: give a run directory or a checkpoint file.\n"
    )


def test_a_run_that_cannot_start_here_is_refused_in_one_line(tmp_path, capsys):
    (tmp_path / "notes").write_text("mine")
    quick = ["--total-updates", "1", "--no-progress"]
    status, _, err = in_process(
        "train", "gridworld", "--run-dir", str(tmp_path / "notes"), *quick, capsys=capsys
    )
    assert status == 1 and err == (
        f"rl-pg: The run directory {tmp_path / 'notes'} is a file; choose another --run-dir.\n"
    )
    status, _, err = in_process(
        "train", "gridworld", "--run-dir", str(tmp_path / "notes" / "run"), *quick, capsys=capsys
    )
    assert status == 1 and "as a run directory (Not a directory)" in err
    assert err.count("\n") == 1 and (tmp_path / "notes").read_text() == "mine"
    if not torch.cuda.is_available():  # a CPU build or machine
        run = tmp_path / "cuda"
        args = ["--run-dir", str(run), "--device", "cuda", *quick]
        status, _, err = in_process("train", "gridworld", *args, capsys=capsys)
        assert status == 1 and err.startswith("rl-pg: device (--device) is 'cuda' but torch")
        assert err.count("\n") == 1 and not run.exists()


@pytest.mark.parametrize("args", [[], ["frobnicate"], ["train"], ["resume", "--total-frames"]])
def test_usage_for_anything_else(args, capsys):
    status, _, err = in_process(*args, capsys=capsys)
    assert status == 2 and err.startswith("usage: rl-pg")


def test_train_help_shows_the_recipes_defaults(capsys):
    status, out, _ = in_process("train", "cartpole", "--help", capsys=capsys)
    assert status == 0
    assert "usage: rl-pg train cartpole" in out
    assert "(default: 0.005)" in out  # the recipe's lr, not TrainConfig's 1e-3


def test_help_shows_the_flags_in_groups_by_concern(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")
    status, out, _ = in_process("train", "lunarlander", "--help", capsys=capsys)
    assert status == 0
    titles = re.findall(r"^\W*(\w+) options", out, flags=re.MULTILINE)
    assert titles == ["recipe", *TrainConfig.groups]  # the recipe's own settings first
    optimiser = out[out.index("optimiser options") : out.index("evaluation options")]
    assert "--lr FLOAT" in optimiser and "(default: 0.001)" in optimiser
    assert "--continuous, --no-continuous" in out.split("run options")[0]
    # each flag shows its docstring's first sentence, wrapped whole (not cut where the
    # source wrapped it); the docs' tables give the rest
    assert "live. 'auto': CUDA" not in out
    assert "Where the models and the optimiser live. (default: cpu)" in out
    assert "Environments step on the CPU" not in out
    assert "\n" not in field_docs(TrainConfig)["device"]
    assert "Environments step on the CPU" in field_docs(TrainConfig)["device"]


@pytest.mark.parametrize(
    "command",
    [f"train {name}" for name in NAMES]
    + ["evaluate", "play", "report", "export", "tune cartpole", "lab variance cartpole"],
)
def test_help_gives_each_flag_one_line(command, capsys, monkeypatch):
    # A flag's help is its docstring's first sentence and default, on one line of a
    # 120-column terminal: beside the flag, or under a flag too long for the column.
    monkeypatch.setenv("COLUMNS", "120")
    status, out, _ = in_process(*command.split(), "--help", capsys=capsys)
    assert status == 0
    entries: list[list[str]] = []
    for line in out.splitlines():
        body = line.strip("│| ")  # box borders, drawn or not as the terminal allows
        if line[:1] not in "│| ":  # the usage and the description, above the boxes
            continue
        if re.match(r"--?[a-z]|[A-Z]+  ", body):  # a flag, or a positional argument
            entries.append([body])
            indent = len(line) - len(line.lstrip("│| "))
        elif body and not body.startswith("─-") and entries and entries[-1]:
            # deeper than its flag: the help under it or wrapped; else a box's text
            inside = len(line) - len(line.lstrip("│| ")) > indent
            entries[-1].append(body) if inside else entries.append([])
        else:
            entries.append([])
    entries = [entry for entry in entries if entry]
    assert len(entries) > (50 if command.startswith("train") else 2)
    for first, *rest in entries:
        beside = "  " in first.strip()  # the help starts on the flag's line
        assert len(rest) == (0 if beside else 1), [first, *rest]


def test_every_config_field_is_in_one_group():
    grouped = [name for _, names in TrainConfig.groups.values() for name in names]
    assert sorted(grouped) == sorted(f.name for f in dataclasses.fields(TrainConfig))
    assert len(grouped) == len(set(grouped))


def test_a_recipe_of_your_own_trains_resumes_and_plays(tmp_path, capsys, monkeypatch):
    (tmp_path / "my_recipe.py").write_text(  # an importable module of the user's
        textwrap.dedent(
            """
            from dataclasses import dataclass

            from rl_pg.envs import GridWorldEnv
            from rl_pg.models import mlp_actor_critic
            from rl_pg.training import TrainConfig
            from rl_pg.training.recipe import Recipe


            @dataclass
            class Config(TrainConfig, total_updates=2, eval_episodes=1, progress=False):
                size: int = 4


            def make_env(cfg, *, render=False):
                return GridWorldEnv(batch_size=8)


            def make_models(env, cfg):
                return mlp_actor_critic(env, hidden=(8,))


            RECIPE = Recipe("my-grid", Config, make_env, make_models)
            """
        )
    )
    monkeypatch.syspath_prepend(tmp_path)
    monkeypatch.chdir(tmp_path)
    from my_recipe import RECIPE, Config

    RECIPE.train(Config(run_dir="run"))
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert (config["recipe"], config["recipe_module"]) == ("my-grid", "my_recipe")
    assert in_process("resume", "run", "--total-updates", "3", capsys=capsys)[0] == 0
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["updates"] == 3
    status, out, _ = in_process("play", "run", "--episodes", "1", capsys=capsys)
    assert status == 0 and "mean return" in out


def test_a_run_that_cannot_be_rebuilt_says_what_play_needs(tmp_path, capsys):
    from rl_pg.envs import GridWorldEnv
    from rl_pg.models import mlp_actor_critic
    from rl_pg.training import TrainConfig, train

    cfg = TrainConfig(run_dir=tmp_path / "run", total_updates=1, eval_episodes=1, progress=False)
    train(cfg, recipe="mine", make_env=GridWorldEnv, make_models=mlp_actor_critic)
    status, _, err = in_process("play", str(tmp_path / "run"), capsys=capsys)
    assert status == 1 and "No recipe called 'mine'" in err
    assert "rl_pg.training.load_models(saved, actor, critic)" in err


def test_the_command_forks_its_workers_from_a_server_that_imported_rl_pg(monkeypatch):
    # TorchRL sets "spawn" when imported; the command's own process replaces it, so that
    # a worker does not import torch, TorchRL and rl_pg again.
    import contextlib
    import multiprocessing

    from rl_pg.app import cli

    calls = []
    monkeypatch.setattr(multiprocessing, "set_start_method", lambda *a, **k: calls.append(a))
    monkeypatch.setattr(multiprocessing, "set_forkserver_preload", calls.append)
    monkeypatch.setattr(cli, "main", lambda argv: calls.append(argv))
    monkeypatch.setattr(cli, "frozen_heap", contextlib.nullcontext)  # for a whole process only
    cli.run(["list"])
    assert calls == [("forkserver",), cli.WORKER_IMPORTS, ["list"]]


def test_checkout_scripts_are_the_command(tmp_path):
    # recipes/metadrive.py must not shadow the metadrive package from its own folder.
    expected = {"metadrive": "rl-pg train metadrive", "play": "rl-pg play"}
    processes = {
        name: subprocess.Popen(
            [sys.executable, str(REPO / "recipes" / f"{name}.py"), "--help"],
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for name in expected
    }  # both at once: each spends its time importing
    for name, process in processes.items():
        out, err = process.communicate(timeout=300)
        assert process.returncode == 0, err
        assert f"usage: {expected[name]}" in out


def test_the_command_works_from_a_wheel_outside_the_checkout(tmp_path):
    """Build the wheel, install it into a fresh virtual environment (its dependencies
    from this one's site-packages), and import, list, train and play from another folder."""
    dist = tmp_path / "dist"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(dist), str(REPO)],
        check=True, capture_output=True,
    )  # fmt: skip
    (wheel,) = dist.glob("rl_pg-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = str(venv / "bin" / "python")
    site = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    # Only a path: the .pth files there (this checkout's editable install) are not read.
    Path(site, "deps.pth").write_text(sysconfig.get_path("purelib") + "\n")
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps",
         str(wheel)],
        check=True, capture_output=True,
    )  # fmt: skip
    work = tmp_path / "elsewhere"
    work.mkdir()
    command = str(venv / "bin" / "rl-pg")
    # What a collector's worker process imports: a recipe, from the wheel, and neither
    # the plotting library nor the compiled kernels (seconds of start-up per worker).
    check = (
        "import sys, rl_pg.recipes.cartpole as r;"
        "print(r.__file__, 'matplotlib' in sys.modules, 'numba' in sys.modules)"
    )
    where = subprocess.run(
        [python, "-c", check], cwd=work, capture_output=True, text=True, check=True
    ).stdout.split()
    assert where[0].startswith(site) and where[1:] == ["False", "False"]
    # `list` runs while the training does (each spends most of its time importing).
    listed = subprocess.Popen(
        [command, "list"], cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    trained = subprocess.run(
        [command, "train", "gridworld", "--run-dir", "run", *QUICK], cwd=work,
        capture_output=True, text=True,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    out, err = listed.communicate(timeout=300)
    assert listed.returncode == 0 and "cartpole" in out, err
    played = subprocess.run(
        [command, "play", "run", "--episodes", "1"], cwd=work, capture_output=True, text=True
    )
    assert played.returncode == 0 and "mean return" in played.stdout, played.stderr


def refresh_page(page: Path, capsys) -> tuple[int, str, str]:
    """``python docs/pages.py PAGE`` in this process: (exit status, stdout, stderr)."""
    from pages import main as refresh

    try:
        refresh([str(page)])
        status = 0
    except SystemExit as stop:
        status = 1
        print(stop.code, file=sys.stderr)
    out, err = capsys.readouterr()
    return status, out, err


def test_report_stores_its_table_and_refreshes_pages_from_the_file(tmp_path, capsys):
    runs = _gridworld_runs(tmp_path, capsys)
    for run in runs:
        for mode in ((), ("--sample",)):
            assert in_process("evaluate", run, "--episodes", "3", *mode, capsys=capsys)[0] == 0
    # A result on other episodes (--seed) comes after, and does not replace the ones on
    # rl-pg evaluate's own fresh episodes.
    status, _, _ = in_process("evaluate", runs[0], "--episodes", "3", "--sample", "--seed",
                                  "424242", capsys=capsys)  # fmt: skip
    assert status == 0
    # the final checkpoint's results are kept too (the best one's, when they are the same)
    for mode in ((), ("--sample",)):
        status, _, err = in_process("evaluate", runs[1], "--episodes", "3", "--checkpoint",
                                    "last", *mode, capsys=capsys)  # fmt: skip
        assert status == 0, err
    stored = tmp_path / "results" / "seeds.json"
    stored.parent.mkdir()
    status, table, err = in_process("report", *runs, "--store", str(stored), capsys=capsys)
    assert status == 0, err
    table = table.split("stored: ")[0].strip()
    records = [json.loads(line) for line in (tmp_path / "seed0" / "evaluations.jsonl").open()]
    fresh = records[1]  # the sampled one on the fresh episodes, before the --seed one
    assert records[-1]["seed"] == 424242 and fresh["seed"] != 424242
    assert f"{fresh['mean_return']:.2f} ± {fresh['std_return']:.2f} (3)" in table
    saved = json.loads(stored.read_text())["runs"]
    assert [run["name"] for run in saved] == ["seed0", "seed1"]
    assert saved[0]["config"]["seed"] == 0 and saved[0]["curve"]["metric"] == "eval/mean_return"
    speed = saved[0]["report"]["frames"] / saved[0]["report"]["train_wall_s"]
    assert saved[0]["report"]["frames_per_s"] == pytest.approx(speed)
    assert len(saved[0]["curve"]["frames"]) == len(saved[0]["curve"]["values"]) >= 1
    # read back: the same table, without the run directories
    for run in runs:
        shutil.rmtree(run)
    status, again, err = in_process("report", "--stored", str(stored), capsys=capsys)
    assert status == 0 and again.strip() == table, err
    # a page shows it between its markers; the docs' tooling rewrites what drifted
    page = tmp_path / "RESULTS.md"
    opening = "<!-- rl-pg report --stored results/seeds.json -->"
    page.write_text(f"Intro.\n\n{opening}\n| stale |\n<!-- end of report -->\n\nAfter.\n")
    status, out, err = refresh_page(page, capsys)
    assert status == 0 and "refreshed" in out, err
    assert page.read_text() == f"Intro.\n\n{opening}\n{table}\n<!-- end of report -->\n\nAfter.\n"
    status, out, _ = refresh_page(page, capsys)
    assert status == 0 and "current" in out
    # performance profiles of two stored settings; a page names one, --refresh draws it
    other = stored.with_name("other.json")
    saved_runs = json.loads(stored.read_text())
    for run in saved_runs["runs"]:
        for mode in ("greedy", "sampled"):
            run["report"][mode]["mean_return"] += 0.25
    other.write_text(json.dumps(saved_runs))
    status, out, err = in_process("report", "--stored", str(stored), str(other), "--profile",
                                  str(tmp_path / "profile.png"), capsys=capsys)  # fmt: skip
    assert status == 0 and f"{stored}:" in out and f"{other}:" in out, err
    assert (tmp_path / "profile.png").is_file()
    page.write_text("<!-- rl-pg report --stored results/seeds.json results/other.json "
                    "--profile profile.png -->\n")  # fmt: skip
    (tmp_path / "profile.png").unlink()
    status, out, err = refresh_page(page, capsys)
    assert status == 0 and "refreshed" in out and (tmp_path / "profile.png").is_file(), err
    # two stored settings on one figure, one aggregate curve each
    status, out, err = in_process("report", "--stored", str(stored), str(other), "--plot",
                                  str(tmp_path / "two.png"), capsys=capsys)  # fmt: skip
    assert status == 0 and (tmp_path / "two.png").is_file(), err
    # one row per stored setting: the flags its runs share beyond the recipe's defaults
    for run in saved_runs["runs"]:
        run["config"]["lr"] = 0.5
        run["config"]["target_kl"] = 0.5  # inert without --lr-control kl: no setting
    saved_runs["runs"][1]["config"]["gamma"] = 0.9  # a flag the runs disagree on
    other.write_text(json.dumps(saved_runs))
    status, out, err = in_process("report", "--stored", str(stored), str(other), "--settings",
                                  capsys=capsys)  # fmt: skip
    assert status == 0, err
    first, second, _, shared = out.strip().splitlines()[2:]
    # what both share is said once, below; the row of those flags alone is no default
    assert first.startswith("| only the flags below | 0 1 |")
    assert shared == "Every row: `--total-updates 2` `--eval-interval 100`."
    # runs of one file that differ in more than their seed are not seeds of one setting
    from rl_pg.app.settings import by_setting

    groups = by_setting(saved_runs["runs"])
    assert {label: len(runs) for label, runs in groups.items()} == {
        "--gamma 1.0": 1, "--gamma 0.9": 1}  # fmt: skip
    status, _, err = in_process("report", "--stored", str(other), "--plot",
                                str(tmp_path / "mixed.png"), capsys=capsys)  # fmt: skip
    assert status == 1 and "the setting 'other: --gamma 1.0' has 1 run" in err, err
    assert "`--gamma 1.0 / --gamma 0.9`" in second and "`--lr 0.5`" in second
    assert "--target-kl" not in second
    reports = [run["report"] for run in saved_runs["runs"]]
    held = sum(
        min(r["greedy"]["mean_return"], r["sampled"]["mean_return"]) >= r["threshold"]
        for r in reports
    )
    assert f"| {held}/2 |" in second
    # settings of two recipes: each row names its recipe
    mixed = json.loads(other.read_text())
    for run in mixed["runs"]:
        run["report"]["recipe"] = "bandit"
    (tmp_path / "bandit.json").write_text(json.dumps(mixed))
    status, two, err = in_process("report", "--stored", str(stored), str(tmp_path / "bandit.json"),
                                  "--settings", capsys=capsys)  # fmt: skip
    assert status == 0 and "| gridworld: " in two and "| bandit: " in two, err
    page.write_text("<!-- rl-pg report --stored results/seeds.json results/other.json "
                    "--settings -->\n| stale |\n<!-- end of report -->\n")  # fmt: skip
    assert refresh_page(page, capsys)[0] == 0
    assert out.strip() in page.read_text()
    # the stored evaluations as a table, one column per run, the kept one in bold
    status, curves, err = in_process("report", "--stored", str(stored), "--curves",
                                     capsys=capsys)  # fmt: skip
    assert status == 0, err
    header, _, *rows = curves.strip().splitlines()
    assert header == "| frames | seed0 | seed1 |"
    rows = [row.strip("|").split("|") for row in rows if row.startswith("| ")]
    assert len(rows) == max(len(run["curve"]["values"]) for run in saved_runs["runs"])
    for run, column in zip(saved_runs["runs"], (1, 2), strict=True):
        frames, values = run["curve"]["frames"], run["curve"]["values"]
        for k, row in enumerate(rows):  # row k: each run's k-th evaluation
            if k >= len(values):
                assert row[column].strip() == "—"
                continue
            low, _, high = row[0].strip().replace(",", "").partition("–")
            assert int(low) <= frames[k] <= int(high or low)
            bold = frames[k] == run["report"]["best_at_frames"]
            text = f"{values[k]:.4g}"
            assert row[column].strip() == (f"**{text}**" if bold else text), (k, row)
    page.write_text("<!-- rl-pg report --stored results/seeds.json --curves -->\n| stale |\n"
                    "<!-- end of report -->\n")  # fmt: skip
    assert refresh_page(page, capsys)[0] == 0
    assert curves.strip() in page.read_text() and "stale" not in page.read_text()
    # every rl-pg evaluate result of the best and final checkpoints, one row each
    status, evaluations, err = in_process("report", "--stored", str(stored), "--evaluations",
                                          capsys=capsys)  # fmt: skip
    assert status == 0, err
    expected = []
    for run in json.loads(stored.read_text())["runs"]:
        report = run["report"]
        final = report["last"] if report["best_at_frames"] != report["frames"] else {}
        assert run["name"] != "seed1" or all(report["last"].values())
        expected += [(run["name"], "best", mode, report[mode]) for mode in ("greedy", "sampled")]
        expected += [(run["name"], "final", mode, final[mode]) for mode in final if final[mode]]
    header, _, *rows = evaluations.strip().splitlines()
    assert header.startswith("| run | checkpoint | actions | episodes | return | length |")
    assert len(rows) == len(expected)
    for row, (name, which, mode, record) in zip(rows, expected, strict=True):
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        assert cells[0] == name and cells[1].startswith(which) and cells[2] == mode, row
        assert cells[3:6] == [
            str(record["episodes"]),
            f"{record['mean_return']:.1f} ± {record['std_return']:.1f}",
            f"{record['mean_length']:.0f}",
        ], row
    page.write_text("<!-- rl-pg report --stored results/seeds.json --evaluations -->\n"
                    "| stale |\n<!-- end of report -->\n")  # fmt: skip
    assert refresh_page(page, capsys)[0] == 0
    assert evaluations.strip() in page.read_text() and "stale" not in page.read_text()
    # a figure in a sentence: the stored value at a JSON pointer, written by --refresh
    page.write_text("Seed 1 took <!-- value results/seeds.json /runs/1/report/frames "
                    "{:,} --> 12<!-- /value --> frames.\n")  # fmt: skip
    assert refresh_page(page, capsys)[0] == 0
    frames = saved_runs["runs"][1]["report"]["frames"]
    assert page.read_text().endswith(f"{{:,}} -->{frames:,}<!-- /value --> frames.\n")
    # a figure summarising every entry of a * pointer: how many, how many set, min, max
    page.write_text("The <!-- value results/seeds.json /runs/*/report/frames "
                    "{0.count}/{0.n}:{0.min:,}–{0.max:,} --> ?<!-- /value --> runs.\n")  # fmt: skip
    assert refresh_page(page, capsys)[0] == 0
    every = [run["report"]["frames"] for run in saved_runs["runs"]]
    assert f"-->2/2:{min(every):,}–{max(every):,}<!-- /value --> runs." in page.read_text()
    page.write_text("<!-- value results/seeds.json /runs/*/report {0.held}/{0.n} -->?<!-- /value "
                    "--> hold.\n")  # fmt: skip
    assert refresh_page(page, capsys)[0] == 0
    reports = [run["report"] for run in json.loads(stored.read_text())["runs"]]
    held = sum(
        min(r["greedy"]["mean_return"], r["sampled"]["mean_return"]) >= r["threshold"]
        for r in reports
    )
    assert f"-->{held}/2<!-- /value --> hold." in page.read_text()
    # below a *, a record that is null (not evaluated) gathers as missing; an absent
    # key is still an error
    partly = json.loads(stored.read_text())
    partly["runs"][1]["report"]["sampled"] = None
    (page.parent / "results" / "partly.json").write_text(json.dumps(partly))
    page.write_text("<!-- value results/partly.json /runs/*/report/sampled/mean_return "
                    "{0.count}/{0.n}:{0.missing} -->?<!-- /value --> sampled.\n")  # fmt: skip
    assert refresh_page(page, capsys)[0] == 0
    assert "-->1/2:1<!-- /value --> sampled." in page.read_text()
    page.write_text("<!-- value results/partly.json /runs/*/report/nowhere/mean_return "
                    "{0.n} -->?<!-- /value -->\n")  # fmt: skip
    status, _, err = refresh_page(page, capsys)
    assert status == 1 and "has nothing at" in err, err
    # a table of a JSON object's entries, one row each
    page.write_text("<!-- table results/seeds.json /runs/1/report {} | entry | value -->\n"
                    "| stale |\n<!-- end of table -->\n")  # fmt: skip
    assert refresh_page(page, capsys)[0] == 0
    assert f"| frames | {frames:,} |" in page.read_text() and "stale" not in page.read_text()
    page.write_text("<!-- table results/seeds.json /runs/1/report/frames {} | a | b -->\n"
                    "<!-- end of table -->\n")  # fmt: skip
    status, _, err = refresh_page(page, capsys)
    assert status == 1 and "not an object of rows" in err, err
    page.write_text("<!-- table results/seeds.json /runs/1 {} | a | b | c -->\n"
                    "<!-- end of table -->\n")  # fmt: skip
    status, _, err = refresh_page(page, capsys)
    assert status == 1 and "needs one for the rows and one for each of its values" in err, err
    # a marker that cannot be written names what is wrong with it
    for marker, message in [
        ("results/none.json /a {}", "none.json does not exist"),
        ("results/seeds.json /runs/7/report/frames {}", "has nothing at /runs/7/report/frames"),
        ("results/seeds.json /runs/1/report/frames {:.2q}", "cannot write"),
        ("results/seeds.json /runs/*/report/frames {:,}", "gathers several values"),
    ]:
        page.write_text(f"A <!-- value {marker} -->1<!-- /value -->.\n")
        status, _, err = refresh_page(page, capsys)
        assert status == 1 and message in err and err.count("\n") == 1, (marker, err)
    # runs that stopped when solved: the share of them solved by each frame
    status, out, err = in_process("report", "--stored", str(stored), "--plot",
                                  str(tmp_path / "solved.png"), capsys=capsys)  # fmt: skip
    assert status == 0 and (tmp_path / "solved.png").is_file(), err
    trained_on = tmp_path / "trained_on.json"
    runs_on = json.loads(stored.read_text())
    for run in runs_on["runs"]:
        run["config"]["stop_when_solved"] = False
    # evaluated at other frames (a whole-episode batch's frames depend on its episodes)
    late = runs_on["runs"][1]["curve"]
    late["frames"] = [frames + 777 for frames in late["frames"]]
    trained_on.write_text(json.dumps(runs_on))
    no_evaluation = tmp_path / "no_evaluation.json"
    bare = json.loads(stored.read_text())
    for run in bare["runs"]:
        run["curve"]["frames"], run["curve"]["values"] = [], []
    no_evaluation.write_text(json.dumps(bare))
    unevaluated = json.loads(stored.read_text())
    unevaluated["runs"][1]["report"]["sampled"] = None
    other.write_text(json.dumps(unevaluated))
    never_evaluated = tmp_path / "never_evaluated.json"
    for run in unevaluated["runs"]:
        run["report"]["greedy"] = run["report"]["sampled"] = None
        run["report"].pop("last")  # as files stored before final checkpoints were
    never_evaluated.write_text(json.dumps(unevaluated))
    namesake = shutil.copy(stored, tmp_path / stored.name)  # another file of the same stem
    broken_value, short_curve = tmp_path / "broken_value.json", tmp_path / "short_curve.json"
    broken = json.loads(stored.read_text())
    broken["runs"][1]["report"]["frames"] = "many"
    broken_value.write_text(json.dumps(broken))
    broken = json.loads(stored.read_text())
    broken["runs"][0]["curve"]["frames"], broken["runs"][0]["curve"]["values"] = [1, 2], [1, 2, 3]
    short_curve.write_text(json.dumps(broken))
    # what cannot be done says so
    for args, message in [
        (("report",), "one of the two"),
        (("report", runs[0], "--stored", str(stored)), "one of the two"),
        (("report", "--stored", str(tmp_path)), "is not a stored report"),
        (("report", "--profile", "x.png"), "name them with --stored"),
        (("report", runs[0], "--settings"), "compares stored files"),
        (("report", runs[0], "--curves"), "tabulates stored curves"),
        (("report", "--stored", str(stored), "--curves", "--settings"), "ask for one"),
        (("report", runs[0], "--evaluations"), "tabulates stored evaluations"),
        (("report", "--stored", str(stored), "--evaluations", "--curves"), "ask for one"),
        (
            ("report", "--stored", str(never_evaluated), "--evaluations"),
            "holds no evaluation of a best or final checkpoint",
        ),
        (("report", "--stored", str(no_evaluation), "--curves"), "holds no evaluation"),
        (("report", "--stored", str(other), "--profile", "x.png"), "run seed1 has no greedy"),
        (("report", "--stored", str(stored), str(namesake), "--plot", "x.png"), "repeat one"),
        (("report", "--stored", str(tmp_path / "none.json")), "does not exist"),
        (("report", "--stored", str(page)), "is not a stored report"),
        (("report", "--stored", str(broken_value)), 'run 1, report: "frames" should be a whole'),
        (("report", "--stored", str(short_curve)), "run 0, curve: 2 frames for 3 values"),
        (("report", "--stored", str(stored), "--store", "x.json"), "leave it out"),
        # these two runs were evaluated at different frames, and did not stop when solved
        (
            ("report", "--stored", str(trained_on), "--plot", "x.png"),
            "evaluated at the same frames",
        ),
    ]:
        status, _, err = in_process(*args, capsys=capsys)
        assert status == 1 and message in err, (args, err)


def test_a_setting_names_a_resolved_default_only_where_a_run_left_it():
    # LunarLander's scale_lr_factor defaults to None, resolved by the policy (30 for the
    # continuous Gaussian, 1 otherwise) and stored resolved: a run at its policy's
    # value shows no flag, a run that set another one does.
    from rl_pg.app.settings import setting_flags
    from rl_pg.training.config import config_dict

    lunarlander = load("lunarlander")

    def runs(**flags):
        config = config_dict(lunarlander.config(**flags))
        return [{"report": {"recipe": "lunarlander"}, "config": config}]

    assert setting_flags(runs()) == []
    assert setting_flags(runs(continuous=True)) == ["--continuous"]
    assert sorted(setting_flags(runs(continuous=True, scale_lr_factor=1.0))) == [
        "--continuous",
        "--scale-lr-factor 1.0",
    ]
    assert setting_flags(runs(scale_lr_factor=1.0)) == []
    both = runs(continuous=True) + runs(continuous=True, scale_lr_factor=10.0)
    assert sorted(setting_flags(both)) == [
        "--continuous",
        "--scale-lr-factor 30.0 / --scale-lr-factor 10.0",
    ]


def _page_lines():
    """(where, line, line before) of every line of the pages outside code fences."""
    pages = [REPO / "README.md", REPO / "RESULTS.md", REPO / "benchmarks" / "README.md",
             *sorted((REPO / "docs").rglob("*.md"))]  # fmt: skip
    for page in pages:
        fenced, before = False, ""
        for number, line in enumerate(page.read_text().splitlines(), 1):
            fenced ^= line.lstrip().startswith("```")
            if not fenced:
                yield f"{page.relative_to(REPO)}:{number}", line, before
            before = line


def test_no_value_marker_opens_a_line_of_a_page():
    # Markdown opens an HTML block at a comment that starts a line: the sentence around
    # the value would be cut into paragraphs (and the comment shown raw on GitHub).
    opening = [where for where, line, _ in _page_lines() if line.lstrip().startswith("<!-- value")]
    assert not opening, f"value markers that open a line (join them to words): {opening}"


def test_no_number_opens_a_line_inside_a_sentence():
    # "... the former defaults held\n  5. Does ..." is an ordered list item to Markdown:
    # the sentence loses its number and breaks in two.
    item = re.compile(r"^\s*(\d+[.)]|[-*+]) ")
    opening = [
        where
        for where, line, before in _page_lines()
        if re.match(r"^\s*\d+[.)] ", line)
        and before.strip()
        and not item.match(before)
        and not before.lstrip().startswith(("|", "<", "#"))
    ]
    assert not opening, f"a number that opens a line in a sentence (join it): {opening}"


def test_torn_or_bad_records_cost_only_themselves(tmp_path, capsys):
    run = tmp_path / "run"
    status, _, err = in_process("train", "gridworld", "--run-dir", str(run), *QUICK,
                                capsys=capsys)  # fmt: skip
    assert status == 0, err
    evaluations = run / "evaluations.jsonl"
    assert in_process("evaluate", str(run), "--episodes", "2", capsys=capsys)[0] == 0
    with open(evaluations, "a") as file:
        file.write('{"checkpoint": "best", "frames": 1')  # a write killed half-way
    # the next result starts on a line of its own and is kept
    assert in_process("evaluate", str(run), "--episodes", "2", "--sample", capsys=capsys)[0] == 0
    lines = evaluations.read_text().splitlines()
    assert len(lines) == 3 and json.loads(lines[2])["mode"] == "sampled"
    with open(evaluations, "a") as file:
        file.write('["not", "a", "record"]\n{"mode": "greedy"}\n')
    status, out, err = in_process("report", str(run), capsys=capsys)
    assert status == 0, err
    for number in (2, 4, 5):
        assert f"evaluations.jsonl, line {number}, is not an evaluation record" in err
    row = next(line for line in out.splitlines() if line.startswith("| run | gridworld"))
    assert row.count("(2)") == 2  # both results read, greedy and sampled
    # a bad summary is named, with what writes it again
    (run / "summary.json").write_text('{"recipe": "gridworld"}')
    status, _, err = in_process("report", str(run), capsys=capsys)
    assert status == 1 and "summary.json is not a run summary" in err and "rl-pg resume" in err
    (run / "summary.json").write_text("{torn")
    status, _, err = in_process("report", str(run), capsys=capsys)
    assert status == 1 and "is not a run summary" in err
    # values, not only keys: each wrong one named with its file and field, in one line
    summary = json.loads(json.dumps({"recipe": "gridworld", "seed": 0, "frames": 10,
                                     "train_wall_s": 1.0, "best_at_frames": None}))  # fmt: skip
    for field, value, said in [
        ("frames", "ten", "\"frames\" should be a whole number ≥ 0, got 'ten'"),
        ("seed", -1, '"seed" should be a whole number ≥ 0, got -1'),
        ("train_wall_s", None, '"train_wall_s" should be a number, got None'),
        ("best_at_frames", 1.5, '"best_at_frames" should be a whole number ≥ 0, got 1.5'),
        ("recipe", 3, '"recipe" should be text, got 3'),
        ("interrupted", "no", "\"interrupted\" should be true or false, got 'no'"),
    ]:
        (run / "summary.json").write_text(json.dumps({**summary, field: value}))
        status, _, err = in_process("report", str(run), capsys=capsys)
        assert status == 1 and said in err and err.count("\n") == 1, (field, err)
    (run / "summary.json").write_text(json.dumps(summary))
    with open(evaluations, "a") as file:
        file.write('{"checkpoint": "best", "frames": 0, "mode": "both", "seed": 1, '
                   '"mean_return": 1}\n')  # fmt: skip
    status, _, err = in_process("report", str(run), capsys=capsys)
    assert status == 0 and 'line 6, is not an evaluation record ("mode" should be ' in err


@pytest.mark.parametrize(
    ("hidden", "args", "extra"),
    [
        ("Box2D", ["train", "lunarlander"], "box2d"),
        ("ale_py", ["train", "pong"], "atari"),
        ("highway_env", ["train", "highway"], "highway"),
        ("optuna", ["tune", "cartpole", "--params", "lr"], "tune"),
    ],
)
def test_a_missing_extra_is_one_line_naming_it(tmp_path, capsys, monkeypatch, hidden, args, extra):
    hide_module(monkeypatch, hidden)
    monkeypatch.chdir(tmp_path)
    status, _, err = in_process(*args, capsys=capsys)
    assert status == 1, err
    assert f'pip install -c constraints.txt "rl_pg[{extra}]"' in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_an_mlflow_server_that_does_not_answer_fails_at_once_and_leaves_nothing(tmp_path, capsys):
    pytest.importorskip("mlflow")
    import socket

    with socket.socket() as free:  # a port nothing listens on
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    run = tmp_path / "run"
    unreachable = f"http://127.0.0.1:{port}"
    train = ("train", "gridworld", "--run-dir", str(run), *QUICK, "--mlflow", "--mlflow-uri")
    status, _, err = in_process(*train, unreachable, capsys=capsys)
    assert status == 1 and f"No MLflow server answers at --mlflow-uri {unreachable}" in err
    assert "sqlite:///mlflow.db" in err and "Traceback" not in err
    assert not run.exists()  # nothing blocks the retry
    status, _, err = in_process(*train, f"sqlite:///{tmp_path / 'm.db'}", capsys=capsys)
    assert status == 0, err


def test_drawing_classic_control_frames_names_the_classic_extra(tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    status, _, err = in_process("train", "cartpole", "--run-dir", str(run), *QUICK,
                                capsys=capsys)  # fmt: skip
    assert status == 0, err
    hide_module(monkeypatch, "pygame")
    status, _, err = in_process("play", str(run), "--gif", str(tmp_path / "x.gif"),
                                capsys=capsys)  # fmt: skip
    assert status == 1 and '"rl_pg[classic]"' in err and "CartPole" in err
    assert "Traceback" not in err


def test_a_recipe_module_that_fails_to_import_says_why(tmp_path, monkeypatch):
    from rl_pg.recipes import load

    monkeypatch.syspath_prepend(str(tmp_path))
    (tmp_path / "needs_more.py").write_text("import no_such_package_here\n")
    (tmp_path / "raises.py").write_text("raise RuntimeError('bad config file')\n")
    with pytest.raises(ValueError, match=r"needs 'no_such_package_here', which is not installed"):
        load("mine", "needs_more")
    with pytest.raises(ValueError, match=r"failed to import: RuntimeError: bad config file"):
        load("mine", "raises")
    with pytest.raises(ValueError, match=r"No recipe called 'mine' \(its module 'gone'"):
        load("mine", "gone")  # a module that is not there at all


def test_a_reported_evaluation_shows_its_crash_rate():
    """The driving recipes' targets count crashes: the table says how many."""
    from rl_pg.app.tables import format_report

    record = {"mean_return": 21.5, "std_return": 2.2, "episodes": 100, "crashed_rate": 0.02}
    report = {"recipe": "highway", "seed": 0, "frames": 50_176, "train_wall_s": 948.0,
              "threshold": 20.0, "solved_at_frames": 20_224, "best_eval_mean_return": 22.2,
              "best_at_frames": 35_136, "greedy": record,
              "sampled": {**record, "crashed_rate": 0.37}}  # fmt: skip
    row = format_report([report], ["seed0"]).splitlines()[2]
    assert "21.50 ± 2.20 (100), 2% crashed" in row and "37% crashed" in row


def test_a_report_names_the_metric_a_run_picked_its_checkpoint_by_and_judges_it_so():
    """MetaDrive's best.pt is its best success rate: the table shows it, and whether the
    checkpoint holds its threshold both ways is judged on it too."""
    from rl_pg.app.stores import holds
    from rl_pg.app.tables import format_report

    record = {"mean_return": 250.0, "std_return": 90.0, "episodes": 100,
              "arrive_dest_rate": 0.61, "mean_route_completion": 0.81}  # fmt: skip
    report = {"recipe": "metadrive", "seed": 0, "frames": 2_000_000, "train_wall_s": 9000.0,
              "threshold": 0.5, "solved_at_frames": None, "best_eval_mean_return": 240.0,
              "best_at_frames": 1_250_000, "select_by": "arrive_dest_rate",
              "select_mode": "max", "best_eval_value": 0.58, "greedy": record,
              "sampled": {**record, "arrive_dest_rate": 0.45}}  # fmt: skip
    row = format_report([report], ["seed0"]).splitlines()[2]
    assert "arrive_dest_rate 58% at 1,250,000" in row  # the kept evaluation, by its metric
    assert "(100), arrive_dest_rate 61%" in row and "arrive_dest_rate 45%" in row
    assert holds(report) is False  # sampled 45 % < 50 %, though both returns are high
    assert holds({**report, "threshold": 0.45}) is True
    crashes = {
        **report,
        "select_by": "crash_rate",
        "select_mode": "min",
        "threshold": 0.2,
        "greedy": {**record, "crash_rate": 0.1},
        "sampled": {**record, "crash_rate": 0.3},
    }
    assert holds(crashes) is False and holds({**crashes, "threshold": 0.3}) is True
    # a run from before the choice reads as picked by its return
    old = {k: v for k, v in report.items() if not k.startswith(("select", "best_eval_v"))}
    assert "240.00 at 1,250,000" in format_report([old], ["seed0"]).splitlines()[2]


def test_every_way_of_starting_the_command_freezes_its_heap():
    """The console script, ``python -m rl_pg.app`` and a checkout's recipe scripts
    start at ``run`` (the heap frozen), not at ``main``, which tests call in-process."""
    import tomllib

    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["rl-pg"] == "rl_pg_launcher:main"  # which starts at run
    assert (
        "from rl_pg.app.cli import run\n\n        run()" in (REPO / "rl_pg_launcher.py").read_text()
    )
    assert "cli import run\n\nrun()" in (REPO / "rl_pg/app/__main__.py").read_text()
    source = (REPO / "rl_pg/app/cli.py").read_text()
    checkout = source[source.index("def run_checkout_script") :]
    assert "    run([" in checkout and "main([" not in checkout


def test_a_frozen_heap_still_collects_what_the_process_makes_afterwards(capsys):
    import gc
    import weakref

    from rl_pg._process import frozen_heap
    from rl_pg.app.cli import run

    class Node:
        pass

    def cycle() -> weakref.ref:
        node = Node()
        node.self = node  # garbage only the cycle collector frees
        return weakref.ref(node)

    before = cycle()  # made before the freeze, not yet collected: frozen with the rest
    try:
        with frozen_heap():
            frozen = gc.get_freeze_count()
            assert frozen > 0 and before() is not None
            after = cycle()
            gc.collect()
            assert after() is None, "an object made after the freeze was not collected"
            assert before() is not None  # what was frozen stays out of the collector's sight
        gc.unfreeze()
        with pytest.raises(SystemExit):  # the command's entry point freezes, however it ends
            run(["no-such-command"])
        assert "rl-pg" in capsys.readouterr().err
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()  # this test process goes on living
    gc.collect()
    assert before() is None


def test_commands_write_only_names_they_own(tmp_path, capsys, monkeypatch):
    """report --store/--plot/--profile and export --out never replace a run's files, and
    replace another existing file only with --replace; their own earlier output they do."""
    monkeypatch.chdir(tmp_path)
    assert in_process("train", "gridworld", "--run-dir", "run", *QUICK, capsys=capsys)[0] == 0
    run_files = {p.name: p.read_bytes() for p in Path("run").iterdir() if p.is_file()}
    refused = [
        ("report", "run", "--store", "run/checkpoint.pt"),
        ("report", "run", "--store", "run/config.json", "--replace"),
        ("report", "run", "--plot", "run/best.pt"),
        ("report", "run", "--plot", "run/learning_curve.png", "--replace"),
        ("export", "run", "--out", "run/checkpoint.pt"),
        ("export", "run", "--out", "run/summary.json", "--replace"),
    ]
    for args in refused:
        status, _, err = in_process(*args, capsys=capsys)
        assert status != 0 and "never replaces a run's own files" in err, (args, err)
    assert {p.name: p.read_bytes() for p in Path("run").iterdir() if p.is_file()} == run_files

    for name in ("notes.json", "notes.png", "notes.pt"):  # the user's files, by their names
        Path(name).write_text("mine")
    for args in (
        ("report", "run", "--store", "notes.json"),
        ("report", "run", "--plot", "notes.png"),
        ("export", "run", "--out", "notes.pt"),
    ):
        status, _, err = in_process(*args, capsys=capsys)
        assert status != 0 and "pass --replace to overwrite it" in err, (args, err)
    assert {Path(name).read_text() for name in ("notes.json", "notes.png", "notes.pt")} == {"mine"}
    # A name that hides what is written (a PNG as notes.txt; an agent file "folder" where
    # a folder was meant): refused, with the name it would take.
    for args, expected in (
        (("report", "run", "--store", "table.txt"), "its name ends in .json, e.g. table.json"),
        (("report", "run", "--plot", "curves.pdf"), "its name ends in .png, e.g. curves.png"),
        (("export", "run", "--out", "folder/"), "its name ends in .pt, e.g. folder.pt"),
    ):
        status, _, err = in_process(*args, capsys=capsys)
        assert status == 1 and expected in err and err.count("\n") == 1, (args, err)
        assert not Path(args[-1]).exists()

    for twice in ("first", "second"):  # their own output, again: replaced
        assert in_process("report", "run", "--store", "s.json", "--plot", "p.png",
                          capsys=capsys)[0] == 0, twice  # fmt: skip
        assert in_process("export", "run", "--out", "agent.pt", capsys=capsys)[0] == 0, twice
    assert in_process("report", "run", "--store", "notes.json", "--replace", capsys=capsys)[0] == 0
    assert json.loads(Path("notes.json").read_text())["runs"]


def test_a_lock_file_that_is_a_link_is_refused_and_its_target_kept(tmp_path):
    from rl_pg.training.run_dir import RunDirectory, locked

    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / ".lock").symlink_to(target)
    with pytest.raises(OSError, match=r"\.lock is a symbolic link"), RunDirectory(tmp_path / "run"):
        pass
    (tmp_path / ".study.lock").symlink_to(target)
    with pytest.raises(OSError, match="is a symbolic link"), locked(tmp_path / ".study.lock"):
        pass
    assert target.read_text() == "keep me"


@pytest.mark.parametrize(
    ("args", "shows"),
    [
        (("train",), "usage: rl-pg train RECIPE"),
        (("resume", "--help"), "usage: rl-pg resume RUN_DIR"),
        (("tune", "-h"), "usage: rl-pg tune RECIPE"),
        (("lab", "--help"), "usage: rl-pg lab variance RECIPE"),
        (("lab", "variance", "--help"), "usage: rl-pg lab variance RECIPE"),
        (("lab", "variance"), "usage: rl-pg lab variance RECIPE"),
    ],
)
def test_every_command_has_its_own_usage(args, shows, capsys):
    """`rl-pg COMMAND --help` (or a missing recipe) shows that command's usage, not the
    top-level one; help exits 0 on stdout, a missing recipe 2 on stderr."""
    status, out, err = in_process(*args, capsys=capsys)
    asked = args[-1] in ("-h", "--help")
    assert status == (0 if asked else 2)
    text = out if asked else err
    assert text.startswith(shows) and "rl-pg list" not in text
    if args[0] != "resume":
        assert "Recipes: bandit, gridworld, cartpole" in text


def test_a_report_over_runs_star_counts_the_newest_run_once(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for seed in ("0", "1"):  # default run directories: runs/gridworld-seedS-TIME, runs/latest
        status, _, err = in_process("train", "gridworld", "--seed", seed, *QUICK, capsys=capsys)
        assert status == 0, err
    assert Path("runs/latest").is_file()
    runs = sorted(str(p) for p in Path("runs").iterdir())
    assert len(runs) == 3
    status, out, err = in_process("report", *runs, capsys=capsys)
    assert status == 0, err
    rows = [line for line in out.splitlines() if line.startswith("| gridworld-seed")]
    assert len(rows) == 2 and "latest" not in out, out


def test_a_report_of_several_runs_gives_their_interquartile_mean_and_its_interval(capsys):
    from scipy.stats import trim_mean

    store = REPO / "results" / "cartpole-seeds.json"
    status, out, _ = in_process("report", "--stored", str(store), capsys=capsys)
    assert status == 0
    (line,) = [line for line in out.splitlines() if "interquartile mean" in line]
    runs = json.loads(store.read_text())["runs"]
    for mode in ("greedy", "sampled"):
        scores = [run["report"][mode]["mean_return"] for run in runs]
        iqm = trim_mean(scores, 0.25)
        match = re.search(rf"{mode} ([-\d.]+) \[([-\d.]+), ([-\d.]+)\]", line)
        assert match and float(match[1]) == pytest.approx(iqm, abs=0.01), line
        assert float(match[2]) <= iqm <= float(match[3])
    assert f"of {len(runs)} runs" in line


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (lambda d: d.__setitem__("config", [1, 2]), '"config" should be a mapping'),
        (lambda d: d["state"].__setitem__("frames", "x"), 'state: "frames" should be a whole'),
        (lambda d: d.__setitem__("recipe", 5), '"recipe" should be text, got 5'),
        (lambda d: d.pop("loss"), '"loss" is missing'),
        (lambda d: d["loss"].__setitem__("x", [1.0]), "\"loss\" should hold tensors, and 'x'"),
        (lambda d: d["config"].__setitem__("lr", "fast"), "config does not fit the gridworld"),
        (lambda d: d["config"].__setitem__("hidden", -3), "hidden (--hidden) must be an integer"),
        (lambda d: d["loss"].__setitem__(next(iter(d["loss"])), torch.zeros(1)), "size mismatch"),
    ],
    ids=["config", "frames", "recipe", "loss", "tensor", "lr", "hidden", "shape"],
)
@pytest.mark.parametrize("command", ["play", "resume"])  # evaluate reads as play does
def test_a_checkpoint_with_a_wrong_value_is_named_in_one_line(
    command, edit, said, tmp_path, capsys, trained_gridworld
):
    from rl_pg.checkpoint import load_checkpoint, save_checkpoint

    run = tmp_path / "run"
    shutil.copytree(trained_gridworld, run)
    for name in ("best.pt", "checkpoint.pt"):
        saved = load_checkpoint(run / name)
        edit(saved)
        save_checkpoint(saved, run / name)  # whole and checksummed: only the value is wrong
    args = {"play": ("--episodes", "1"), "evaluate": ("--episodes", "1"),
            "resume": ("--total-updates", "4")}  # fmt: skip
    status, _, err = in_process(command, str(run), *args[command], capsys=capsys)
    assert status == 1 and said in err and err.count("\n") == 1, err
    assert str(run) in err or said == "size mismatch", err  # the file is named


@pytest.fixture(scope="module")
def trained_gridworld(tmp_path_factory):
    run = tmp_path_factory.mktemp("trained") / "run"
    cfg = load("gridworld").config(run_dir=run, total_updates=2, eval_episodes=1, progress=False)
    load("gridworld").train(cfg)
    return run


@pytest.mark.parametrize("after", [0.2, 1.0])
def test_a_ctrl_c_while_the_command_starts_ends_it_without_a_traceback(after, tmp_path):
    # torch and TorchRL take seconds to import: a Ctrl-C then is a Ctrl-C, not a fault
    script = Path(sys.executable).parent / "rl-pg"
    if not script.is_file():
        pytest.skip("rl-pg is not installed beside this interpreter")
    start = subprocess.Popen(
        [str(script), "train", "cartpole", "--run-dir", str(tmp_path / "run")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    time.sleep(after)
    start.send_signal(signal.SIGINT)
    _, err = start.communicate(timeout=120)
    assert start.returncode == 130 and "Traceback" not in err, err


@pytest.mark.parametrize(("content", "said"), [("{bad", "Expecting property name"),
                                               ("[1]", "should hold a JSON object")])  # fmt: skip
def test_a_run_config_that_is_not_one_is_named_by_report_and_lab(
    content, said, tmp_path, capsys, trained_gridworld
):
    run = tmp_path / "lab" / "seed0"
    shutil.copytree(trained_gridworld, run)
    (run / "config.json").write_text(content)
    for args in (("report", str(run), "--store", str(tmp_path / "s.json")),
                 ("lab", "variance", "gridworld", "--seeds", "0", "--run-dir",
                  str(tmp_path / "lab"), *QUICK)):  # fmt: skip
        status, _, err = in_process(*args, capsys=capsys)
        assert status == 1 and f"{run / 'config.json'} is not a run's config" in err, err
        assert said in err and err.count("\n") == 1
