"""REINFORCE driving in highway-env with continuous actions discretised.

In a checkout, `python recipes/highway.py [FLAGS]` is `rl-pg train highway [FLAGS]`;
the recipe itself is rl_pg/recipes/highway.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
