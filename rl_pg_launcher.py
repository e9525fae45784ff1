"""The ``rl-pg`` console script's entry point, outside the ``rl_pg`` package.

Importing anything in ``rl_pg`` first imports the package, and with it torch and
TorchRL: seconds in which a Ctrl-C would otherwise end the command with a traceback of
the imports. This module imports nothing heavy until the interrupt is caught: a Ctrl-C
at any moment ends ``rl-pg`` with status 130 (the shell's code for it) and no traceback.
"""

import sys


def main() -> None:
    """Runs ``rl-pg`` ([`run`][rl_pg.app.cli.run]) with its arguments."""
    try:
        from rl_pg.app.cli import run

        run()
    except KeyboardInterrupt:
        sys.exit(130)
