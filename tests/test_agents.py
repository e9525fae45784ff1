"""Agent files: a run's deployed agent exported without its training state, and the
agents shipped with rl_pg, played and evaluated without training."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys

import pytest
import torch
from conftest import hide_module
from test_cli import QUICK, in_process, rl_pg

from rl_pg.app.export import export_agent, model_card
from rl_pg.app.sources import HUB_FILE, SHIPPED, shipped_agent
from rl_pg.checkpoint import load_checkpoint
from rl_pg.recipes import load
from rl_pg.training import load_models, read_run

TRAINING_STATE = {"optimizer", "rng", "collection", "episodes", "callbacks"}


def _trained(tmp_path, capsys, *flags: str):
    run = tmp_path / "run"
    status, _, err = in_process("train", "gridworld", "--run-dir", str(run), *QUICK, *flags,
                                capsys=capsys)  # fmt: skip
    assert status == 0, err
    return run


def test_an_exported_agent_plays_and_evaluates_as_its_run_does(tmp_path, capsys):
    run = _trained(tmp_path, capsys)
    for mode in ((), ("--sample",)):
        assert in_process("evaluate", str(run), "--episodes", "3", *mode, capsys=capsys)[0] == 0
    status, out, err = in_process("export", str(run), "--out", str(tmp_path / "a.pt"),
                                  capsys=capsys)  # fmt: skip
    assert status == 0 and "the gridworld agent of" in out, err
    agent = load_checkpoint(tmp_path / "a.pt")
    assert not TRAINING_STATE & agent.keys()  # weights and config only: not resumable
    assert agent["agent"]["greedy"]["episodes"] == 3 and agent["agent"]["sampled"] is not None
    best = read_run(run, which="best")
    assert all(torch.equal(agent["loss"][k], best["loss"][k]) for k in agent["loss"])
    outputs = {}
    for source in (str(run), str(tmp_path / "a.pt")):
        for command in (("play", "--episodes", "2", "--sample"), ("evaluate", "--episodes", "4")):
            status, out, err = in_process(command[0], source, *command[1:], capsys=capsys)
            assert status == 0, err
            # the returns, not the wall-clock seconds after them
            outputs.setdefault(command[0], []).append(
                re.sub(r"\(\d+ s\)", "", out.split("return", 1)[1])
            )
    assert outputs["play"][0] == outputs["play"][1]  # the same episodes, the same returns
    assert outputs["evaluate"][0] == outputs["evaluate"][1]
    status, _, err = in_process("export", str(run), "--out", str(tmp_path), capsys=capsys)
    assert status == 1 and "is a directory: name the file to write there (an agent file)" in err
    # the last checkpoint's export carries no results: rl-pg evaluate's are the best one's
    last = export_agent(run, tmp_path / "last.pt", which="last")
    assert "greedy" not in last["agent"]
    assert last["state"]["frames"] == read_run(run)["state"]["frames"] != best["state"]["frames"]


def test_an_exported_agent_deploys_the_policy_average(tmp_path, capsys):
    run = _trained(tmp_path, capsys, "--policy-ema", "0.5")
    agent = export_agent(run, tmp_path / "a.pt")
    recipe = load("gridworld")
    cfg = recipe.config.from_stored(agent["config"])
    env = recipe.make_env(cfg)
    deployed, _ = recipe.make_models(env, cfg)
    load_models(read_run(run, which="best"), deployed)  # the average, as play deploys it
    exported, _ = recipe.make_models(env, cfg)
    load_models(load_checkpoint(tmp_path / "a.pt"), exported)
    trained = read_run(run, which="best")["loss"]
    for (name, a), b in zip(deployed.state_dict().items(), exported.state_dict().values(),
                            strict=True):  # fmt: skip
        assert torch.equal(a, b), name
    assert any(
        not torch.equal(v, trained[f"actor_network.{k}"]) for k, v in exported.state_dict().items()
    )  # the average is not the trained weights


def test_pretrained_names_a_recipe_with_a_shipped_agent(tmp_path, capsys):
    status, _, err = in_process("play", "pong-nothing", "--pretrained", capsys=capsys)
    assert status == 1 and "No agent is shipped for 'pong-nothing'" in err
    assert "cartpole" in err  # the message lists the shipped ones


@pytest.mark.parametrize("path", sorted(SHIPPED.glob("*.pt")), ids=lambda p: p.stem)
def test_every_shipped_agent_plays_one_episode_without_training(path, capsys, monkeypatch):
    agent = load_checkpoint(path)
    assert agent["recipe"] == path.stem and not TRAINING_STATE & agent.keys()
    assert agent["agent"]["greedy"] is not None  # its results ship with it (docs show them)
    # an agent file is its weights and a few KiB more; only Pong's network (6 400 inputs
    # to 200 units: 5 MB of weights) is over 1 MB
    weights = sum(t.numel() * t.element_size() for t in agent["loss"].values())
    assert path.stat().st_size < max(1_000_000, weights + 64_000)
    assert shipped_agent(path.stem) == path
    status, out, err = in_process("play", path.stem, "--pretrained", "--episodes", "1",
                                  capsys=capsys)  # fmt: skip
    assert status == 0 and "mean return" in out, err


def test_the_agents_are_shipped_in_the_package():
    shipped = {p.stem for p in SHIPPED.glob("*.pt")}
    assert {
        "bandit",
        "gridworld",
        "cartpole",
        "pendulum",
        "lunarlander",
        "highway",
        "metadrive",
        "pong",
    } <= shipped
    # what the wheel carries for them stays small beside torch itself (its CPU wheel is
    # about 200 MB); Pong's policy reads 12 800 inputs, 10 MB of its 11
    assert sum(p.stat().st_size for p in SHIPPED.glob("*.pt")) < 12_000_000
    pyproject = (SHIPPED.parents[2] / "pyproject.toml").read_text()
    assert '"recipes/agents/*.pt"' in pyproject  # package data of a built wheel


def test_every_recipe_plays_one_episode_per_return(tmp_path, capsys):
    """rl-pg play watches one environment: a gridworld trained on 30 copies returns at
    most the grid's best (0.5), not a sum over copies (it printed 15.0)."""
    run = _trained(tmp_path, capsys)
    status, out, err = in_process("play", str(run), "--episodes", "2", capsys=capsys)
    assert status == 0, err
    returns = [
        float(line.rsplit(" ", 1)[1]) for line in out.splitlines() if line.startswith("episode")
    ]
    assert len(returns) == 2 and max(returns) <= 0.5 + 1e-6


def test_play_gives_each_copy_of_a_batch_its_own_return(tmp_path):
    from rl_pg.envs import GridWorldEnv
    from rl_pg.models import mlp_actor
    from rl_pg.recording import play

    torch.manual_seed(0)
    env = GridWorldEnv(batch_size=3, max_steps=20)
    returns = play(mlp_actor(env), env, episodes=5, deterministic=False)
    # 5 episodes from two rounds of 3 copies; each at most the grid's best and at least
    # 20 steps at -0.1 or the pit (nothing summed over copies or over later episodes)
    assert len(returns) == 5 and all(-2.0 - 1e-6 <= r <= 0.5 + 1e-6 for r in returns)
    assert len(set(returns)) > 1  # the copies played their own episodes
    with pytest.raises(ValueError, match="A recording shows one environment"):
        play(mlp_actor(env), env, episodes=1, record=tmp_path / "x.gif")
    one = GridWorldEnv(batch_size=1)  # a batch of one is one environment
    assert len(play(mlp_actor(one), one, episodes=1)) == 1


def _hub_cache(cache, repo_id: str, agent_file) -> None:
    """Lays ``agent_file`` out in a Hugging Face cache as ``repo_id``'s agent.pt at a
    commit, where a download would have put it."""
    commit = "0123456789abcdef0123456789abcdef01234567"
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    (repo / "snapshots" / commit).mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(commit)
    (repo / "snapshots" / commit / HUB_FILE).write_bytes(agent_file.read_bytes())


def test_an_agent_shared_on_the_hub_plays_from_its_cache_offline(tmp_path, capsys):
    run = _trained(tmp_path, capsys)
    agent_file = tmp_path / "a.pt"
    export_agent(run, agent_file)
    _hub_cache(tmp_path / "hub", "me/gridworld", agent_file)
    offline = {**os.environ, "HF_HUB_CACHE": str(tmp_path / "hub"), "HF_HUB_OFFLINE": "1"}
    done = rl_pg("evaluate", "me/gridworld", "--hub", "--episodes", "4", cwd=tmp_path,
                 env=offline)  # fmt: skip
    assert done.returncode == 0, done.stderr
    status, out, err = in_process("evaluate", str(agent_file), "--episodes", "4", capsys=capsys)
    result = [re.sub(r"\(\d+ s\)", "", text.split("return", 1)[1]) for text in (done.stdout, out)]
    assert status == 0 and result[0] == result[1], err  # the same episodes (not the time)
    done = rl_pg("play", "me/absent", "--hub", cwd=tmp_path, env=offline)
    assert done.returncode == 1 and "is not in the Hugging Face cache" in done.stderr
    assert done.stderr.count("\n") == 1  # one line, no traceback
    # pushing needs the network: said in one line, and the agent file is kept
    done = rl_pg("export", str(run), "--out", str(tmp_path / "b.pt"), "--push-to-hub",
                 "me/gridworld", cwd=tmp_path, env=offline)  # fmt: skip
    assert done.returncode == 1 and "HF_HUB_OFFLINE is set" in done.stderr
    assert done.stderr.count("\n") == 1 and (tmp_path / "b.pt").is_file()
    # a name the Hub refuses is refused before anything is written
    status, _, err = in_process("export", str(run), "--out", str(tmp_path / "c.pt"),
                                "--push-to-hub", "not a repo id", capsys=capsys)  # fmt: skip
    assert status == 1 and "is not one" in err and not (tmp_path / "c.pt").exists()


def test_the_hub_model_card_carries_the_agents_results_and_how_to_play_it(tmp_path, capsys):
    from huggingface_hub import ModelCard

    run = _trained(tmp_path, capsys)
    for mode in ((), ("--sample",)):
        assert in_process("evaluate", str(run), "--episodes", "3", *mode, capsys=capsys)[0] == 0
    agent = export_agent(run, tmp_path / "a.pt")
    card = ModelCard(model_card(agent, "me/gridworld"))
    assert card.data.library_name == "rl_pg" and "reinforcement-learning" in card.data.tags
    values = [result.metric_value for result in card.data.eval_results]
    expected = [agent["agent"][mode] for mode in ("greedy", "sampled")]
    assert values == [f"{r['mean_return']:.2f} +/- {r['std_return']:.2f}" for r in expected]
    assert "rl-pg play me/gridworld --hub" in card.text
    # an agent without results (a last checkpoint) gets a card without them
    last = export_agent(run, tmp_path / "last.pt", which="last")
    assert ModelCard(model_card(last, "me/gridworld")).data.eval_results is None


def test_hub_sharing_without_its_extra_or_with_two_sources_says_so(tmp_path, capsys, monkeypatch):
    status, _, err = in_process("play", "cartpole", "--pretrained", "--hub", capsys=capsys)
    assert status == 1 and "use one" in err
    hide_module(monkeypatch, "huggingface_hub")
    for args in (("play", "me/x", "--hub"), ("evaluate", "me/x", "--hub"),
                 ("export", str(tmp_path), "--out", "a.pt", "--push-to-hub", "me/x")):  # fmt: skip
        status, _, err = in_process(*args, capsys=capsys)
        assert status == 1 and "rl_pg[hub]" in err and err.count("\n") == 1, (args, err)


def test_a_push_to_an_unreachable_hub_says_so_in_one_line_and_keeps_the_file(
    tmp_path, capsys, monkeypatch
):
    pytest.importorskip("huggingface_hub")
    monkeypatch.setenv("HF_ENDPOINT", "http://127.0.0.1:9")  # nothing listens: refused
    monkeypatch.setenv("HF_TOKEN", "hf_not_a_real_token")
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    run = tmp_path / "run"
    assert in_process("train", "gridworld", "--run-dir", str(run), *QUICK, capsys=capsys)[0] == 0
    out = tmp_path / "agent.pt"
    status, _, err = in_process("export", str(run), "--out", str(out), "--push-to-hub",
                                "me/agent", capsys=capsys)  # fmt: skip
    assert status == 1 and "Cannot push to me/agent" in err, err
    assert "Traceback" not in err and err.count("\n") == 1 and out.is_file()


# Quick enough to replay in the suite (seconds); highway, MetaDrive and Pong take minutes.
REPLAYED = ("bandit", "gridworld", "cartpole", "pendulum", "lunarlander")


@pytest.mark.parametrize("name", REPLAYED)
def test_a_shipped_agents_advertised_figures_are_what_evaluate_gives(name):
    """The play page and the model card show the results an agent file carries: they must
    be what `rl-pg evaluate NAME --pretrained [--sample]` gives, episode for episode."""
    agent = load_checkpoint(shipped_agent(name))
    for mode in ("greedy", "sampled"):
        advertised = agent["agent"][mode]
        measured = load(name).evaluate_checkpoint(
            agent, episodes=advertised["episodes"], sample=mode == "sampled",
            seed=advertised["seed"],
        )  # fmt: skip
        assert measured["mean_return"] == pytest.approx(advertised["mean_return"], abs=1e-3)
        assert measured["std_return"] == pytest.approx(advertised["std_return"], abs=1e-3)


@pytest.mark.parametrize("path", sorted(SHIPPED.glob("*.pt")), ids=lambda p: p.stem)
def test_a_shipped_agents_figures_were_measured_under_todays_protocol(path):
    """An evaluation setting a recipe has (Pong's sticky actions) is stored in the agent
    file with the value its figures were measured under, and it is what `rl-pg evaluate
    --pretrained` uses: a default changed later cannot re-label them."""
    agent = load_checkpoint(path)
    config = load(path.stem).config
    protocol = {
        f.name for f in dataclasses.fields(config)
        if f.name.startswith("eval_") and f.name not in ("eval_interval", "eval_episodes")
    }  # fmt: skip
    for name in protocol:
        assert name in agent["config"], f"{path.name} does not say its {name}"


@pytest.mark.parametrize(
    ("args", "extra"),
    [
        (["play", "cartpole", "--pretrained", "--episodes", "1", "--gif", "x.gif"], "pygame"),
        (["play", "pong", "--pretrained", "--episodes", "1"], "ale_py"),
    ],
    ids=["rendered", "atari"],
)
def test_a_played_agent_leaves_only_its_own_words_on_the_console(args, extra, tmp_path):
    # No display probing (SDL's "XDG_RUNTIME_DIR is invalid"), no leak report at exit
    # (a simulator's bindings, which TorchRL's kept import error held alive).
    pytest.importorskip(extra)
    env = {k: v for k, v in os.environ.items() if k not in ("XDG_RUNTIME_DIR", "SDL_VIDEODRIVER")}
    done = subprocess.run([sys.executable, "-m", "rl_pg.app", *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0 and done.stderr == "", done.stderr[-2000:]
    assert done.stdout.splitlines()[-1].startswith(("mean return", "recorded"))
