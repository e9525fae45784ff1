"""Where a trained agent comes from: a run directory, a checkpoint or agent file, the
agent shipped with rl_pg for a recipe (``--pretrained``), or one shared on the Hugging
Face Hub (``--hub``). What ``rl-pg play``, ``rl-pg evaluate`` and ``Agent.load`` read.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import tyro

from rl_pg import recipes
from rl_pg._checks import require_extra
from rl_pg.checkpoint import CheckpointError
from rl_pg.training.checkpoints import resolve_latest

__all__ = ["HUB_FILE", "SHIPPED", "AgentSource", "agent_path", "hub_agent", "shipped_agent"]

HUB_FILE = "agent.pt"
"""The agent file's name in a Hugging Face Hub model repository."""

SHIPPED = Path(recipes.__file__).resolve().parent / "agents"
"""The folder of the agents shipped with rl_pg, one ``<recipe>.pt`` each, beside the
recipes that trained them."""


def shipped_agent(recipe: str) -> Path:
    """The agent file shipped for ``recipe``.

    Raises:
        ValueError: no agent is shipped for it (the message lists those that are).
    """
    path = SHIPPED / f"{recipe}.pt"
    if not path.is_file():
        names = sorted(p.stem for p in SHIPPED.glob("*.pt"))
        raise ValueError(
            f"No agent is shipped for {recipe!r}; --pretrained plays one of {names}. "
            f"Train one (rl-pg train {recipe}), or play an agent file: rl-pg play FILE.pt."
        )
    return path


def hub_agent(repo_id: str) -> Path:
    """The agent file of the Hugging Face Hub model repository ``repo_id``
    (``owner/name``), downloaded once into the Hub's cache and read from there after.

    Raises:
        ModuleNotFoundError: huggingface_hub is not installed (names the extra).
        ValueError: not a repository id, no such repository (or a private one without a
            login), no agent in it, or not in the cache while the Hub cannot be reached.
    """
    require_extra("huggingface_hub", "hub", "Sharing agents on the Hugging Face Hub")
    from huggingface_hub import hf_hub_download
    from huggingface_hub.errors import (
        EntryNotFoundError,
        HfHubHTTPError,
        HFValidationError,
        LocalEntryNotFoundError,
        RepositoryNotFoundError,
    )

    try:
        return Path(hf_hub_download(repo_id, HUB_FILE, library_name="rl_pg"))
    except HFValidationError as err:
        raise ValueError(
            f"--hub takes a Hub repository id, owner/name; {repo_id!r} is not one."
        ) from err
    except LocalEntryNotFoundError as err:
        raise ValueError(
            f"{repo_id}'s {HUB_FILE} is not in the Hugging Face cache and the Hub cannot be "
            "reached (no network, or HF_HUB_OFFLINE=1): play it once online, then offline."
        ) from err
    except RepositoryNotFoundError as err:
        raise ValueError(
            f"No Hugging Face Hub model {repo_id!r} (or a private one: log in with "
            "`hf auth login`)."
        ) from err
    except EntryNotFoundError as err:
        raise ValueError(
            f"The Hub model {repo_id} has no {HUB_FILE}: it holds no agent that "
            "rl-pg export --push-to-hub wrote."
        ) from err
    except HfHubHTTPError as err:
        raise ValueError(f"The Hub did not give {repo_id}'s agent: {err}") from err


def agent_path(run: str | Path, *, pretrained: bool = False, hub: bool = False) -> Path:
    """What ``rl-pg play RUN`` and ``rl-pg evaluate RUN`` load: the run directory or
    file itself, the agent shipped for the recipe RUN names (``pretrained``), or the
    agent of the Hub repository RUN names (``hub``)."""
    if not isinstance(run, (str, os.PathLike)) or not str(run):
        raise TypeError(
            f"An agent's source is a run directory, a checkpoint or agent file (a path), "
            f"a recipe's name with --pretrained, or a Hub repository with --hub; got "
            f"{run!r} ({type(run).__name__})."
        )
    if pretrained and hub:
        raise ValueError("--pretrained and --hub name two sources of an agent: use one.")
    if pretrained:
        return shipped_agent(str(run))
    if hub:
        return hub_agent(str(run))
    if not Path(run).exists() and (SHIPPED / f"{run}.pt").is_file():
        raise CheckpointError(
            f"{run} is no file or folder here, but a recipe's name: the agent rl-pg ships "
            f"for it plays with --pretrained (rl-pg play {run} --pretrained; in Python, "
            f"Agent.load({str(run)!r}, pretrained=True))."
        )
    return resolve_latest(run)  # runs/latest: the newest run


@dataclass
class AgentSource:
    """The flags that name an agent, which ``rl-pg play`` and ``rl-pg evaluate`` share
    (``agent_path`` reads them)."""

    run: tyro.conf.Positional[Path]
    """Run directory, checkpoint or agent file. With --pretrained, a recipe's name; with
    --hub, a Hugging Face Hub repository, owner/name."""
    pretrained: bool = False
    """The agent rl_pg ships for the recipe RUN names. See rl-pg export."""
    hub: bool = False
    """The agent of the Hugging Face Hub repository RUN names. Downloaded once into the
    Hub's cache; needs rl_pg[hub]."""
