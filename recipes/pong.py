"""REINFORCE with a learned baseline on Atari Pong (the set-up of docs/recipes/pong.md).

In a checkout, `python recipes/pong.py [FLAGS]` is `rl-pg train pong [FLAGS]`;
the recipe itself is rl_pg/recipes/pong.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
