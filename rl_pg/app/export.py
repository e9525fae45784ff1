"""Trained agents as files: a run's deployed policy, exported without its training state,
and the agents shipped with rl_pg, to watch or evaluate without training.

rl-pg export runs/cartpole-seed0 --out cartpole.pt   # the run's best agent, as one file
rl-pg play cartpole.pt --gif cartpole.gif            # an agent file plays like a run
rl-pg play lunarlander --pretrained                  # the agent shipped for a recipe
rl-pg evaluate metadrive --pretrained --episodes 10
rl-pg export runs/cartpole-seed0 --out cartpole.pt --push-to-hub me/rl_pg-cartpole
rl-pg play me/rl_pg-cartpole --hub                   # an agent shared on the Hub

An agent file is a checkpoint (same format and checksum) that keeps only what rebuilds
and runs the models: the recipe, its config, the weights (the policy average's, for a
run trained with ``--policy-ema``: the ones its evaluations played) and where it came
from (the run, its frames, its last greedy and sampled ``rl-pg evaluate`` results, the
sessions that trained it). No optimiser state, random states or collector state: it
cannot be resumed, only deployed.

Sharing goes through the Hugging Face Hub (``pip install "rl_pg[hub]"``): a model
repository holds the agent file as ``agent.pt`` and a model card (``README.md``) with
its results and the command that plays it. ``--hub`` downloads it once into the Hub's
cache (``HF_HUB_OFFLINE=1`` reads only that cache, as on a machine without a network).
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tyro

from rl_pg._checks import require_extra
from rl_pg.app.outputs import claim_output
from rl_pg.app.sources import HUB_FILE
from rl_pg.app.stores import read_report
from rl_pg.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from rl_pg.training import read_run
from rl_pg.training.checkpoints import POLICY_AVERAGE, callback_states, resolve_latest

__all__ = ["ExportArgs", "export_agent", "is_agent_file", "main", "model_card", "push_agent"]


def model_card(agent: dict[str, Any], repo_id: str) -> str:
    """The Hub model card of an agent file's contents ``agent``: the metadata the Hub
    indexes (library, tags, its ``rl-pg evaluate`` results) and how to play it."""
    require_extra("huggingface_hub", "hub", "Sharing agents on the Hugging Face Hub")
    from huggingface_hub import EvalResult, ModelCardData

    recipe, config, info = agent["recipe"], agent["config"], agent.get("agent", {})
    env = config.get("env_id", recipe)
    evaluated = {
        mode: result for mode in ("greedy", "sampled") if (result := info.get(mode)) is not None
    }
    data = ModelCardData(
        library_name="rl_pg",
        tags=["reinforcement-learning", "rl_pg", "torchrl", "reinforce", recipe],
        model_name=f"REINFORCE on {env}",
        eval_results=[
            EvalResult(
                task_type="reinforcement-learning",
                dataset_type=env,
                dataset_name=env,
                metric_type="mean_reward",
                metric_name=f"mean return, {mode}",
                metric_value=f"{r['mean_return']:.2f} +/- {r['std_return']:.2f}",
            )
            for mode, r in evaluated.items()
        ]
        or None,
    )
    frames = agent.get("state", {}).get("frames")
    results = "".join(
        f"| {mode} | {r['mean_return']:.2f} ± {r['std_return']:.2f} ({r['episodes']}) |\n"
        for mode, r in evaluated.items()
    )
    return (
        f"---\n{data.to_yaml()}\n---\n\n"
        f"# REINFORCE on {env}, trained with rl_pg\n\n"
        f"The `{recipe}` recipe's agent from run `{info.get('exported_from')}`"
        + (f", after {frames:,} frames" if frames is not None else "")
        + " (weights and config, no training state).\n\n"
        "```bash\n"
        'pip install "rl_pg[hub]"\n'
        f"rl-pg play {repo_id} --hub\n"
        f"rl-pg evaluate {repo_id} --hub --episodes 100\n"
        "```\n"
        + (
            "\n`rl-pg evaluate` of this checkpoint, mean return (episodes):\n\n"
            f"| actions | return |\n|---|---|\n{results}"
            if evaluated
            else ""
        )
    )


def push_agent(agent_file: str | Path, repo_id: str, *, private: bool = False) -> str:
    """Uploads an agent file to the Hub model repository ``repo_id`` (created if
    needed) as ``agent.pt`` with its model card; returns the commit's URL. Needs a
    login (``hf auth login`` or ``HF_TOKEN``)."""
    require_extra("huggingface_hub", "hub", "Sharing agents on the Hugging Face Hub")
    from huggingface_hub import HfApi
    from huggingface_hub.errors import HfHubHTTPError, OfflineModeIsEnabled

    agent = load_checkpoint(agent_file)
    with tempfile.TemporaryDirectory() as folder:
        shutil.copyfile(agent_file, Path(folder) / HUB_FILE)
        (Path(folder) / "README.md").write_text(model_card(agent, repo_id))
        api = HfApi(library_name="rl_pg")
        try:
            api.create_repo(repo_id, exist_ok=True, private=private)
            commit = api.upload_folder(
                repo_id=repo_id,
                folder_path=folder,
                commit_message=f"rl-pg export of {agent.get('agent', {}).get('exported_from')}",
            )
        except OfflineModeIsEnabled as err:
            raise ValueError(
                f"Cannot push to {repo_id}: HF_HUB_OFFLINE is set. The agent file "
                f"{agent_file} is written; push it later with --push-to-hub."
            ) from err
        except HfHubHTTPError as err:
            raise ValueError(
                f"Cannot push to {repo_id} ({type(err).__name__}: {err}); log in with "
                f"`hf auth login` (or set HF_TOKEN). The agent file {agent_file} is written."
            ) from err
        except Exception as err:  # no network, DNS, a proxy: whatever the HTTP client raises
            raise ValueError(
                f"Cannot push to {repo_id}: the Hub cannot be reached ({type(err).__name__}: "
                f"{err}). The agent file {agent_file} is written; push it once the Hub "
                f"answers (rl-pg export again, with --push-to-hub)."
            ) from err
    return str(commit.commit_url)


def export_agent(
    run: str | Path, out: str | Path, *, which: str = "best", replace: bool = False
) -> dict[str, Any]:
    """Writes the deployed agent of ``run`` (a run directory or a checkpoint file) to
    ``out`` as an agent file (see the module's description); returns what it wrote.

    ``out`` may be a new file or an agent file written before; any other file only with
    ``replace``, and a run's own files (its checkpoints) never.

    Raises:
        CheckpointError: ``run`` has no such checkpoint, or it is damaged.
        ValueError: ``out`` is a directory, or a file it may not replace.
    """
    claim_output(out, flag="--out", writes="an agent file", ours=is_agent_file, suffix=".pt",
                 replace=replace)  # fmt: skip
    run = resolve_latest(run)  # runs/latest: the newest run, recorded by its own name
    saved = read_run(run, which=which)
    weights = {
        key: value
        for key, value in saved["loss"].items()
        if key.startswith(("actor_network.", "critic_network."))
    }
    average = callback_states(saved).get(POLICY_AVERAGE)
    if average is not None:  # deploy what the evaluations played: the average
        actor = {k: v for k, v in average["weights"].items() if k.startswith("module.")}
        weights = {k: v for k, v in weights.items() if not k.startswith("actor_network.")}
        weights |= {"actor_network." + k.removeprefix("module."): v for k, v in actor.items()}
    state = saved.get("state", {})
    agent = {
        "recipe": saved["recipe"],
        "recipe_module": saved.get("recipe_module"),
        "config": saved["config"],
        "loss": weights,
        "state": {
            k: state.get(k)
            for k in ("frames", "updates", "best_eval", "best_mean_return")
            if k in state
        },
        "agent": {
            "exported_from": Path(run).resolve().name,  # the run directory's (or file's) name
            "checkpoint": which if Path(run).is_dir() else Path(run).name,
            # the results rl-pg evaluate recorded are the best checkpoint's
            **(_history(Path(run)) if Path(run).is_dir() and which == "best" else {}),
        },
    }
    save_checkpoint(agent, out)
    return agent


def is_agent_file(path: str | Path) -> bool:
    """Whether ``path`` is an agent file ``rl-pg export`` wrote (not a checkpoint)."""
    try:
        return "agent" in load_checkpoint(path)
    except CheckpointError:
        return False


def _history(run: Path) -> dict[str, Any]:
    """The run's last greedy and sampled ``rl-pg evaluate`` results of its best
    checkpoint, as ``rl-pg report`` reads them, and the sessions that trained it."""
    try:
        report = read_report(run)
    except ValueError:  # no summary yet: a run still in its first session
        return {}
    return {
        "greedy": report.get("greedy"),
        "sampled": report.get("sampled"),
        "sessions": report.get("sessions"),
    }


@dataclass
class ExportArgs:
    """Write a run's deployed agent to one file, without its training state."""

    run: tyro.conf.Positional[Path]
    """Run directory (or checkpoint file) written by a recipe."""
    out: Path
    """The agent file to write (.pt). Play it with rl-pg play FILE, evaluate it with
    rl-pg evaluate FILE."""
    checkpoint: Literal["best", "last"] = "best"
    """Export the best checkpoint (what rl-pg play deploys), or the last."""
    push_to_hub: str | None = None
    """Also upload the agent to this Hugging Face Hub model repository, owner/name.
    Created if needed, with a model card; needs rl_pg[hub] and a login (`hf auth
    login`). Others play it with rl-pg play owner/name --hub."""
    private: bool = False
    """With --push-to-hub: create the repository private."""
    replace: bool = False
    """Overwrite --out when it is a file rl-pg export did not write. Never a run's own
    files (its checkpoints)."""


def main(args: ExportArgs) -> Path:
    """Exports the agent (and pushes it); prints what was written."""
    if args.push_to_hub is not None:  # before the export: a missing extra, a bad name
        require_extra("huggingface_hub", "hub", "Sharing agents on the Hugging Face Hub")
        from huggingface_hub.errors import HFValidationError
        from huggingface_hub.utils import validate_repo_id

        try:
            validate_repo_id(args.push_to_hub)
        except HFValidationError as err:
            raise ValueError(
                f"--push-to-hub takes a Hub repository id, owner/name; "
                f"{args.push_to_hub!r} is not one ({err})."
            ) from err
    agent = export_agent(args.run, args.out, which=args.checkpoint, replace=args.replace)
    size = Path(args.out).stat().st_size
    print(
        f"{args.out}: the {agent['recipe']} agent of {args.run} ({args.checkpoint} checkpoint, "
        f"{agent['state']['frames']:,} frames), {size / 1024:.0f} KiB"
    )
    if args.push_to_hub is not None:
        print(f"pushed to the Hub: {push_agent(args.out, args.push_to_hub, private=args.private)}")
    return Path(args.out)
