"""REINFORCE with a learned baseline on Pendulum-v1 (solved at a greedy mean of -200).

In a checkout, `python recipes/pendulum.py [FLAGS]` is `rl-pg train pendulum [FLAGS]`;
the recipe itself is rl_pg/recipes/pendulum.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
