"""The ``rl-pg`` application, above the recipes: the command and its subcommands
(train, resume, play, evaluate, export, report, lab, tune), and
[`Agent`][rl_pg.app.acting.Agent], which loads a trained agent and acts from Python.

Examples:
    >>> from rl_pg.app import Agent
    >>> Agent.load("cartpole", pretrained=True).recipe.name
    'cartpole'
"""

from rl_pg.app.acting import Agent

__all__ = ["Agent"]
