"""REINFORCE on a 100-armed bandit: why a baseline matters (docs/recipes/bandit.md).

In a checkout, `python recipes/bandit.py [FLAGS]` is `rl-pg train bandit [FLAGS]`;
the recipe itself is rl_pg/recipes/bandit.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
