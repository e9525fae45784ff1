"""REINFORCE on the 4x4 gridworld, and the comparison of its return estimators.

In a checkout, `python recipes/gridworld.py [FLAGS]` is `rl-pg train gridworld [FLAGS]`;
the recipe itself is rl_pg/recipes/gridworld.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
