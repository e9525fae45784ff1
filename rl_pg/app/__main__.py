"""``python -m rl_pg.app``: the ``rl-pg`` command."""

from rl_pg.app.cli import run

run()
