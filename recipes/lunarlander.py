"""REINFORCE with a learned baseline on LunarLander-v3 (solved at a greedy mean of 200).

In a checkout, `python recipes/lunarlander.py [FLAGS]` is `rl-pg train lunarlander [FLAGS]`;
the recipe itself is rl_pg/recipes/lunarlander.py.
"""

from rl_pg.app.cli import run_checkout_script

if __name__ == "__main__":
    run_checkout_script(__file__)
