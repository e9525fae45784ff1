"""``python -m rl_pg.recipes``: the ``rl-pg`` command."""

from rl_pg.recipes.cli import run

run()
