"""Deploy a trained agent: load a run directory (or checkpoint), play, record.

In a checkout, `python recipes/play.py [FLAGS]` is `rl-pg play [FLAGS]`;
the recipe itself is rl_pg/app/play.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
